"""Reprojection of impostor tiles to the camera and the cycle frame (crowdbake.reference.impostor_warp), on
surfaces whose answer is known by construction: a flat tilted plane seen from two angles, a uniform motion."""
from __future__ import annotations

import numpy as np

from crowdbake.bake import impostor_views
from crowdbake.reference import impostor_warp
from crowdbake.reference.impostor_blend import DecodedTile

SIZE = 32
CENTER = np.array([0.0, 1.0, 0.0])
RADIUS = 1.0


def view(azimuth: float, elevation: float = 0.0) -> impostor_views.OrthoView:
    return impostor_views.ortho_view(CENTER, RADIUS, azimuth, elevation, SIZE)


def pixel_centres() -> np.ndarray:
    rows, columns = np.mgrid[0:SIZE, 0:SIZE]
    return np.stack([columns + 0.5, rows + 0.5], axis=-1).astype(np.float64)


def test_at_the_baked_view_and_frame_every_pixel_reads_its_own_texel():
    rng = np.random.default_rng(1)
    depth = rng.uniform(-0.5, 0.5, (SIZE, SIZE))
    xy, miss = impostor_warp.reproject(view(30.0), depth, view(30.0))
    np.testing.assert_allclose(xy, pixel_centres(), atol=1e-9)
    assert miss.max() < 1e-9


def test_a_tilted_plane_lands_on_the_pixel_it_is_seen_at_from_another_angle():
    """The plane z = 0.6 + 0.3 x (relative to the centre) seen from azimuth 0 has that depth along +Z; from
    azimuth 10° and elevation 10° each pixel must find the tile texel whose surface point projects onto it."""
    source, target = view(0.0), view(10.0, 10.0)
    texels = pixel_centres()
    world_x = texels[..., 0] / (SIZE / (2 * RADIUS)) - RADIUS
    depth = 0.6 + 0.3 * world_x  # bilinear reads of a linear field are exact away from the clamped border
    xy, miss = impostor_warp.reproject(source, depth, target, iterations=6)
    inside = (xy[..., 0] > 1) & (xy[..., 0] < SIZE - 1) & (xy[..., 1] > 1) & (xy[..., 1] < SIZE - 1)
    assert inside.sum() > SIZE * SIZE // 2
    landed = impostor_warp.to_texels(target, impostor_warp.surface_points(source, xy, impostor_warp.bilinear(depth, xy)))
    np.testing.assert_allclose(landed[inside], texels[inside], atol=1e-3)
    assert miss[inside].max() < 1e-3
    # Without the depth the plane would be read where the centre plane is: the correction is real.
    flat, _ = impostor_warp.reproject(source, np.zeros_like(depth), target)
    assert np.abs(flat - xy)[inside].max() > 1.0


def test_a_uniform_motion_shifts_the_lookup_back_by_the_fraction_moved():
    """Every surface point moves 0.1 m to the view's right by the next baked frame; a quarter of the way
    there, a pixel shows what the tile holds 0.025 m (0.4 texels at 16 texels a metre) to its left."""
    here = view(0.0)
    motion = np.broadcast_to(0.1 * here.right, (SIZE, SIZE, 3)).copy()
    xy, miss = impostor_warp.reproject(here, np.zeros((SIZE, SIZE)), here, motion, 0.25)
    expected = pixel_centres() - [0.025 * SIZE / (2 * RADIUS), 0.0]
    np.testing.assert_allclose(xy, expected, atol=1e-9)
    assert miss.max() < 1e-9


def test_gather_reads_nearest_texels_and_leaves_the_outside_uncovered():
    covered = np.zeros((4, 4), dtype=bool)
    covered[1:3, 1:3] = True
    uv = np.arange(32, dtype=np.float64).reshape(4, 4, 2) / 32
    tile = DecodedTile(uv, np.zeros((4, 4), dtype=np.int64), covered, np.tile([0.0, 0.0, 1.0], (4, 4, 1)))
    xy = np.array([[[1.9, 2.1], [-0.5, 1.5]], [[2.5, 2.5], [1.5, 1.5]]])
    gathered = impostor_warp.gather(tile, xy, valid=np.array([[True, True], [True, False]]))
    assert gathered.covered.tolist() == [[True, False], [True, False]]
    np.testing.assert_array_equal(gathered.uv[0, 0], uv[2, 1])
    np.testing.assert_array_equal(gathered.uv[0, 1], [0.0, 0.0])  # outside the tile: no coordinate
