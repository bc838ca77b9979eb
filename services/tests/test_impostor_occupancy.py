"""services/benchmarks/bench_impostor_occupancy.py: the shares of an impostor atlas the character covers and
that tighter rectangles would store, on hand-made coverage and on a baked bundle."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_impostor_occupancy as occupancy_bench  # noqa: E402


def test_rectangles_are_counted_on_blocks_per_cell_per_view_and_for_all():
    coverage = np.zeros((2, 2, 16, 16), dtype=bool)
    coverage[0, 0, 1:3, 1:3] = True    # one block: 16 texels
    coverage[1, 0, 9:11, 9:11] = True  # another block of the same view: the view's rectangle spans 3 x 3 blocks
    coverage[0, 1, 4:8, 0:8] = True    # 4 x 8 texels on blocks: 32
    shares = occupancy_bench.occupancy(coverage)
    stored = 2 * 2 * 16 * 16
    assert shares["covered"] == pytest.approx((4 + 4 + 32) / stored)
    assert shares["cell_boxes"] == pytest.approx((16 + 16 + 32) / stored)  # frame 1 of view 1 is empty: nothing stored
    assert shares["view_boxes"] == pytest.approx((12 * 12 + 4 * 8) * 2 / stored)
    # Everything fits in rows 0-12 and columns 0-12 (blocks 0-2): one 12 x 12 rectangle a cell.
    assert shares["union_box"] == pytest.approx(12 * 12 * 4 / stored)
    assert shares["covered"] <= shares["cell_boxes"] <= shares["view_boxes"] <= shares["union_box"] <= 1.0
    # A block of margin, clipped to the cell: view 0's 12 x 12 grows to 16 x 16, view 1's 4 x 8 to 12 x 12.
    assert shares["view_boxes_margin"] == pytest.approx((16 * 16 + 12 * 12) * 2 / stored)
    # Per cell, clipped at the cell's edge: block 0 grows to 0..8 (8 x 8), block 2 to 4..16 (12 x 12), the 4 x 8
    # (rows 4..8, columns 0..8) to rows 0..12 and columns 0..12.
    assert shares["cell_boxes_margin"] == pytest.approx((8 * 8 + 12 * 12 + 12 * 12) / stored)


def test_a_baked_bundles_cells_are_read_as_the_atlas_lays_them_out(small_bake):
    coverage, impostor = occupancy_bench.bundle_coverage(small_bake[0])
    crop = impostor["crop"]
    assert coverage.shape == (len(impostor["frame_indices"]), len(impostor["azimuths_deg"]) * len(impostor["elevations_deg"]),
                              crop["height"], crop["width"])
    shares = occupancy_bench.occupancy(coverage)
    # Every cell holds the character (the crop holds it in every view and frame), and a character covers
    # far less than its crop: a figure is not a rectangle.
    assert all(coverage[f, v].any() for f in range(coverage.shape[0]) for v in range(coverage.shape[1]))
    assert 0.05 < shares["covered"] < shares["cell_boxes"] < shares["view_boxes"] <= shares["union_box"] <= 1.0
