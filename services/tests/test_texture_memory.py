"""Figure 4 (crowdbake.bake.texture_memory): the paper's section-6 arithmetic, and the same sums over a
bundle's real layer sizes."""
from __future__ import annotations

import pytest

from crowdbake.bake import texture_memory
from crowdbake.bake.texture_memory import MIB, MapBytes


def test_paper_assumptions_give_the_papers_map_sizes():
    paper = texture_memory.paper_map_bytes()
    # 10 frames of 1024² RGB normal maps at DXT1's 6:1: 10 * 3 MiB / 6.
    assert paper.normal == 5 * MIB
    # 10 frames of 1024² RGBA detail or UV maps at DXT3's 4:1: 10 * 4 MiB / 4.
    assert paper.detail == paper.uv == 10 * MIB
    # One 1024² RGBA diffuse texture per variation, DXT3.
    assert paper.diffuse_per_variation == 1 * MIB


def test_figure4_series():
    series = texture_memory.series(texture_memory.paper_map_bytes(), 8)
    assert series["variations"] == list(range(1, 9))
    # detail-mapped(n) = 5 + 11 n, UV-mapped(n) = 15 + n (MiB): equal at one variation.
    assert series["detail_mapped_mib"] == [5 + 11 * n for n in range(1, 9)]
    assert series["uv_mapped_mib"] == [15 + n for n in range(1, 9)]
    assert series["detail_mapped_mib"][0] == series["uv_mapped_mib"][0] == 16
    assert series["detail_mapped_mib"][-1] == 93 and series["uv_mapped_mib"][-1] == 23
    assert texture_memory.break_even_variations(texture_memory.paper_map_bytes()) == 1.0


def test_bundle_bytes_with_16_bit_uv_maps_break_even_later():
    # A bundle like the default bake: 2048x384 atlases, 10 layers; BC1 normal, BC2 detail, rgba16 UV.
    texels = 2048 * 384 * 10
    bundle = MapBytes(normal=texels / 2, uv=texels * 8, detail=texels * 1, diffuse_per_variation=1024 * 1024)
    assert texture_memory.break_even_variations(bundle) == 8.0
    assert bundle.uv_mapped(9) < bundle.detail_mapped(9) and bundle.uv_mapped(7) > bundle.detail_mapped(7)
    report = texture_memory.texture_memory_report(bundle, 10, 8)
    assert report["bundle"]["variations_in_bundle"] == 8 and len(report["bundle"]["uv_mapped_mib"]) == 10
    assert report["paper"]["detail_mapped_mib"][7] == 93


def test_bundle_bytes_with_uv32_maps_break_even_at_half_the_variations():
    # The default bake's layout with the default uv32 UV map: 4 bytes a texel against BC2's 1.
    texels = 2048 * 384 * 10
    rgba16 = MapBytes(normal=texels / 2, uv=texels * 8, detail=texels * 1, diffuse_per_variation=1024 * 1024)
    uv32 = MapBytes(normal=texels / 2, uv=texels * 4, detail=texels * 1, diffuse_per_variation=1024 * 1024)
    assert texture_memory.break_even_variations(uv32) == 4.0
    assert texture_memory.break_even_variations(uv32) * 2 == texture_memory.break_even_variations(rgba16)
    assert uv32.uv_mapped(5) < uv32.detail_mapped(5) and uv32.uv_mapped(3) > uv32.detail_mapped(3)


def test_series_needs_a_variation():
    with pytest.raises(ValueError):
        texture_memory.series(texture_memory.paper_map_bytes(), 0)


def test_break_even_count_is_the_first_variation_count_where_uv_mapping_costs_no_more():
    """UV-mapped(n) <= detail-mapped(n) exactly when uv <= n·detail: with a UV map 1.5 times a detail map
    the crossing is at 2 variations; with equal maps at 1 (the paper's figure 4); never with no detail map bytes
    to save and a UV map."""
    from crowdbake.bake.texture_memory import MapBytes, break_even_count

    assert break_even_count(MapBytes(normal=5.0, uv=15.0, detail=10.0, diffuse_per_variation=1.0)) == 2
    assert break_even_count(MapBytes(normal=5.0, uv=10.0, detail=10.0, diffuse_per_variation=1.0)) == 1
    assert break_even_count(MapBytes(normal=5.0, uv=40.0, detail=10.0, diffuse_per_variation=1.0)) == 4
    assert break_even_count(MapBytes(normal=5.0, uv=1.0, detail=0.0, diffuse_per_variation=1.0), limit=100) is None
