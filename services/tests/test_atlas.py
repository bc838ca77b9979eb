"""Impostor atlases (crowdbake.bake.atlas): SPEC.md's tile grid, column = azimuth, row = elevation."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake.atlas import AtlasLayout, assemble, nearest_view, tile_of


def test_rings_of_views_and_sizes():
    layout = AtlasLayout.rings(128, 16, (0, 20, 40))
    assert layout.azimuths_deg[:3] == (0.0, 22.5, 45.0) and len(layout.azimuths_deg) == 16
    assert (layout.width, layout.height) == (2048, 384)
    assert layout.views[0] == (0, 0) and layout.views[16] == (0, 1) and len(layout.views) == 48
    assert layout.to_manifest() == {"tile_size": 128, "azimuths_deg": list(layout.azimuths_deg), "elevations_deg": [0.0, 20.0, 40.0]}


def test_tiles_land_where_the_spec_says_and_come_back():
    layout = AtlasLayout.rings(8, 4, (0, 30))
    tiles = {(a, e): np.full((8, 8, 4), 10 * a + e, dtype=np.uint16) for a, e in layout.views}
    atlas = assemble(layout, tiles)
    assert atlas.shape == (16, 32, 4) and atlas.dtype == np.uint16
    # Tile (a, e) covers texels [a*t, (a+1)*t) x [e*t, (e+1)*t): columns by azimuth, rows by elevation.
    assert atlas[8, 24, 0] == 31 and atlas[7, 24, 0] == 30 and atlas[0, 0, 0] == 0
    for view, tile in tiles.items():
        np.testing.assert_array_equal(tile_of(layout, atlas, *view), tile)


def test_missing_or_mismatched_tiles_are_refused():
    layout = AtlasLayout.rings(4, 2, (0,))
    with pytest.raises(ValueError, match="no tile"):
        assemble(layout, {(0, 0): np.zeros((4, 4, 4), np.uint8)})
    with pytest.raises(ValueError, match="expected"):
        assemble(layout, {(0, 0): np.zeros((4, 4, 4), np.uint8), (1, 0): np.zeros((4, 4, 4), np.uint16)})
    with pytest.raises(ValueError, match="multiple of 4"):
        AtlasLayout.rings(6, 2, (0,))
    with pytest.raises(ValueError, match="elevations"):
        AtlasLayout(4, (0.0,), (95.0,))
    with pytest.raises(IndexError):
        layout.tile_slices(2, 0)


def test_nearest_view_by_angle():
    layout = AtlasLayout.rings(4, 8, (0, 40))
    assert nearest_view(layout, 44.0, 5.0) == (1, 0)
    assert nearest_view(layout, 350.0, 30.0) == (0, 1)  # wraps around 360
    assert nearest_view(layout, 22.5, 0.0) == (0, 0)  # a tie goes to the lower index
    assert nearest_view(layout, 180.0, 90.0)[1] == 1  # straight down: the highest ring
