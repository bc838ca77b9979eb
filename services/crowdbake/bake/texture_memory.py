"""Figure 4 of the paper: texture memory of detail-mapped against UV-mapped impostors, 1 to N variations.

Section 6 (Dobbyn et al. 2006): "These calculations use a single clothed character and assume that the
detail mapped and UV mapped impostor consist of 10 frames of animation, each normal map being a 1024x1024
sized RGB image and both the detail map and UV map are 1024x1024 sized RGBA images. Additionally, each
diffuse texture used by the clothed character's mesh representation is a 1024x1024 RGBA sized image. DXT3
texture compression is used in these calculations to reduce the memory requirements by 4 for all RGBA
images and by 6 for all RGB images."

The character switches between its mesh and its impostor, so the mesh's diffuse textures are resident in
both schemes. With n texture variations:

    detail-mapped(n) = normal maps + n · detail maps + n · diffuse
    UV-mapped(n)     = normal maps + UV maps         + n · diffuse

because a detail map bakes one diffuse texture in, while one UV map serves every diffuse texture. With the
paper's figures (MiB): normal maps 10 · 3/6 = 5, detail or UV maps 10 · 4/4 = 10 each, diffuse 4/4 = 1,
so detail-mapped(n) = 5 + 11 n and UV-mapped(n) = 15 + n: equal at one variation, and each further
variation costs 11 MiB against 1 MiB.

`bundle_series` applies the same sums to the byte sizes of a real bundle's layers, where the UV map is
uvblock by default (1.5 bytes a texel, not DXT3's 1: block-coded 12-bit coordinates with coverage and
material exact, SPEC.md pixel format 6), uv32 (4 bytes) or rgba16 (8 bytes). `break_even_count` is the
smallest variation count at which the UV-mapped impostor costs no more than the detail-mapped one.
Pure arithmetic; no I/O.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

MIB = 1024 * 1024


@dataclass(frozen=True)
class PaperAssumptions:
    """Section 6's assumptions. Sizes in texels per side; ratios are DXT3's reduction factors."""

    frames: int = 10
    map_size: int = 1024
    diffuse_size: int = 1024
    rgba_bytes_per_texel: int = 4
    rgb_bytes_per_texel: int = 3
    rgba_compression: float = 4.0  # DXT3 on RGBA (32 bits -> 8)
    rgb_compression: float = 6.0  # DXT1 on RGB (24 bits -> 4)


@dataclass(frozen=True)
class MapBytes:
    """Bytes resident for one character: all frames of each impostor map, one diffuse variation.

    normal, uv, detail: every baked frame of that map (detail = one diffuse variation baked in);
    diffuse_per_variation: one layer of every material's diffuse texture; surface: every baked frame of the
    surface map both impostor kinds reproject with (crowdbake.bake.surface_maps; not in the paper: 0 there),
    shared by both schemes as the normal maps are.
    """

    normal: float
    uv: float
    detail: float
    diffuse_per_variation: float
    surface: float = 0.0

    def detail_mapped(self, variations: int) -> float:
        return self.normal + self.surface + variations * (self.detail + self.diffuse_per_variation)

    def uv_mapped(self, variations: int) -> float:
        return self.normal + self.surface + self.uv + variations * self.diffuse_per_variation


def paper_map_bytes(assumptions: PaperAssumptions = PaperAssumptions()) -> MapBytes:
    """MapBytes under the paper's assumptions (compressed sizes, no mipmaps)."""
    a = assumptions
    map_texels = a.map_size * a.map_size
    rgba_map = map_texels * a.rgba_bytes_per_texel / a.rgba_compression
    rgb_map = map_texels * a.rgb_bytes_per_texel / a.rgb_compression
    diffuse = a.diffuse_size * a.diffuse_size * a.rgba_bytes_per_texel / a.rgba_compression
    return MapBytes(normal=a.frames * rgb_map, uv=a.frames * rgba_map, detail=a.frames * rgba_map, diffuse_per_variation=diffuse)


def series(map_bytes: MapBytes, max_variations: int) -> dict[str, list[float]]:
    """MiB for 1 .. max_variations variations: {"variations", "detail_mapped_mib", "uv_mapped_mib"}."""
    if max_variations < 1:
        raise ValueError(f"series: max_variations must be at least 1, got {max_variations}")
    counts = list(range(1, max_variations + 1))
    return {
        "variations": counts,
        "detail_mapped_mib": [map_bytes.detail_mapped(n) / MIB for n in counts],
        "uv_mapped_mib": [map_bytes.uv_mapped(n) / MIB for n in counts],
    }


def break_even_variations(map_bytes: MapBytes) -> float:
    """Variations at which both schemes cost the same: n = uv / detail (UV-mapped is cheaper above it)."""
    if map_bytes.detail <= 0:
        raise ValueError("break_even_variations: detail maps have no size")
    return map_bytes.uv / map_bytes.detail


def break_even_count(map_bytes: MapBytes, limit: int = 1 << 16) -> int | None:
    """The smallest variation count n >= 1 at which UV-mapped costs no more than detail-mapped (figure 4's
    crossing, as a count), or None when none up to `limit` does."""
    for n in range(1, limit + 1):
        if map_bytes.uv_mapped(n) <= map_bytes.detail_mapped(n):
            return n
    return None


def texture_memory_report(bundle: MapBytes, max_variations: int, bundle_variations: int) -> dict:
    """The figure-4 JSON: the paper's model and the bundle's bytes, side by side.

    bundle: MapBytes from the bundle's layer sizes; bundle_variations: diffuse variations it really holds
    (the series beyond it extrapolates with the same per-variation size).
    """
    paper = paper_map_bytes()
    return {
        "description": "Texture memory (MiB) for one clothed character, detail-mapped vs UV-mapped impostors "
        "plus the mesh's diffuse textures (Dobbyn et al. 2006, figure 4)",
        "paper": {
            "assumptions": asdict(PaperAssumptions()),
            "map_bytes": asdict(paper),
            "break_even_variations": break_even_variations(paper),
            **series(paper, max_variations),
        },
        "break_even_variations": break_even_count(bundle),
        "bundle": {
            "map_bytes": asdict(bundle),
            "variations_in_bundle": bundle_variations,
            "break_even_variations": break_even_variations(bundle),
            **series(bundle, max_variations),
        },
    }
