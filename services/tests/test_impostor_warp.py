"""Reprojection of impostor tiles to the camera and the cycle frame (crowdbake.reference.impostor_warp), on
surfaces whose answer is known by construction: a flat tilted plane seen from two angles, a uniform motion."""
from __future__ import annotations

import numpy as np
import pytest

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


def strip_before_a_wall() -> tuple[np.ndarray, np.ndarray]:
    """Depth (metres towards the camera of azimuth 0) of a wall at the centre plane with a strip 0.6 m before
    it over columns 12-19, every texel covered."""
    depth = np.zeros((SIZE, SIZE))
    depth[:, 12:20] = 0.6
    return depth, np.ones((SIZE, SIZE))


def first_surface_depth(source, target, depth, coverage, samples: int = 4000) -> np.ndarray:
    """(S, S) the source depth the first point behind the surface along each target pixel's ray holds,
    found by a fine march (the reference the shader's coarse one is held to); nan where none is."""
    scale = SIZE / (2 * RADIUS)
    rows, columns = np.mgrid[0:SIZE, 0:SIZE]
    plane = ((columns + 0.5) / scale - RADIUS)[..., None] * target.right + (RADIUS - (rows + 0.5) / scale)[..., None] * target.up
    found = np.full((SIZE, SIZE), np.nan)
    for d in np.linspace(RADIUS, -RADIUS, samples):
        points = plane + d * target.back
        x, y = impostor_warp.tile_points(source, points)
        inside = (x >= 0) & (x < SIZE) & (y >= 0) & (y < SIZE)
        surface = impostor_warp.bilinear(depth, np.stack([x, y], axis=-1))
        share = impostor_warp.bilinear(coverage, np.stack([x, y], axis=-1))
        hit = np.isnan(found) & inside & (share > 0.5) & (points @ source.back <= surface)
        found[hit] = surface[hit]
    return found


def test_the_march_starts_the_steps_on_the_surface_the_camera_sees_first():
    """At a depth jump the fixed-point steps converge to the surface nearest their start: from the centre
    plane, the wall behind the strip for pixels that see the strip. Marched from the camera's side first,
    they land on the strip wherever a fine march finds it first."""
    source, target = view(0.0), view(25.0)
    depth, coverage = strip_before_a_wall()
    expected = first_surface_depth(source, target, depth, coverage)
    sees_strip = np.isclose(expected, 0.6)
    assert sees_strip.sum() > 40
    marched, miss = impostor_warp.reproject(source, depth, target, coverage=coverage)
    landed = impostor_warp.bilinear(depth, marched)
    away_from_edges = sees_strip & (miss < 0.5)
    assert away_from_edges.sum() >= 0.8 * sees_strip.sum()
    np.testing.assert_allclose(landed[away_from_edges], 0.6, atol=0.02)
    # From the centre plane (no coverage given: the steps alone) many of them end on the wall.
    plain, _ = impostor_warp.reproject(source, depth, target)
    assert (impostor_warp.bilinear(depth, plain)[sees_strip] < 0.3).sum() > 10


def test_the_march_leaves_a_ray_that_meets_nothing_where_the_steps_start():
    source, target = view(0.0), view(25.0)
    depth = np.zeros((SIZE, SIZE))
    nothing = np.zeros((SIZE, SIZE))
    marched, _ = impostor_warp.reproject(source, depth, target, coverage=nothing)
    plain, _ = impostor_warp.reproject(source, depth, target)
    np.testing.assert_array_equal(marched, plain)


@pytest.mark.parametrize("azimuth, elevation", [(25.0, 0.0), (-40.0, 20.0), (10.0, 35.0), (0.0, 20.0)])
def test_the_march_span_holds_exactly_the_depths_whose_points_fall_in_the_crop(azimuth, elevation):
    source, target = view(0.0), view(azimuth, elevation)
    crop = (8, 4, 12, 20)
    rows, columns = np.mgrid[0:SIZE, 0:SIZE]
    scale = SIZE / (2 * RADIUS)
    plane = ((columns + 0.5) / scale - RADIUS)[..., None] * target.right + (RADIUS - (rows + 0.5) / scale)[..., None] * target.up
    lowest, highest = impostor_warp.march_span(source, target, plane, crop, RADIUS)
    assert (lowest <= highest).sum() > 50 and (lowest > highest).sum() > 50  # rays that cross the crop and rays that miss it
    for d in np.linspace(-RADIUS, RADIUS, 201):
        x, y = impostor_warp.tile_points(source, plane + d * target.back)
        inside = (x >= crop[0]) & (x < crop[0] + crop[2]) & (y >= crop[1]) & (y < crop[1] + crop[3])
        in_span = (lowest <= d) & (d <= highest)
        # Equal but for points on the crop's edge (within rounding).
        on_edge = np.isclose(d, lowest, atol=1e-9) | np.isclose(d, highest, atol=1e-9)
        assert not (inside & ~in_span & ~on_edge).any()
        assert not (in_span & ~inside & ~on_edge).any()


def every_step_march(source, target, plane, depth, coverage, crop) -> tuple[np.ndarray, np.ndarray]:
    """first_hit's march without skipping a step: each of its evenly spaced depths tried for every pixel,
    then the same halvings; (x, y) of the last point in front, nan where no step passes behind."""
    low, high = np.array(crop[:2], float), np.array(crop[:2], float) + np.array(crop[2:], float)

    def behind(d):
        points = plane + d[..., None] * target.back
        x, y = impostor_warp.tile_points(source, points)
        inside = (x >= low[0]) & (y >= low[1]) & (x < high[0]) & (y < high[1])
        xy = np.stack([np.clip(x, low[0] + 0.5, high[0] - 0.5), np.clip(y, low[1] + 0.5, high[1] - 0.5)], axis=-1)
        return inside & (impostor_warp.bilinear(coverage, xy) > 0.5) & (points @ source.back <= impostor_warp.bilinear(depth, xy))

    steps = int(np.clip(np.ceil(SIZE * np.linalg.norm(np.cross(source.back, target.back))), 1, impostor_warp.MARCH_STEPS))
    depths = RADIUS - 2 * RADIUS * np.arange(steps + 1) / steps
    found = np.zeros((SIZE, SIZE), dtype=bool)
    front, back = np.full((SIZE, SIZE), RADIUS), np.full((SIZE, SIZE), RADIUS)
    for n in range(1, steps + 1):
        hit = ~found & behind(np.full((SIZE, SIZE), depths[n]))
        front[hit], back[hit] = depths[n - 1], depths[n]
        found |= hit
    for _ in range(impostor_warp.MARCH_REFINE):
        middle = 0.5 * (front + back)
        passed = behind(middle)
        back, front = np.where(passed, middle, back), np.where(passed, front, middle)
    x, y = impostor_warp.tile_points(source, plane + front[..., None] * target.back)
    return np.where(found, x, np.nan), np.where(found, y, np.nan)


@pytest.mark.parametrize("azimuth, elevation, crop", [(25.0, 0.0, (4, 0, 24, SIZE)), (-40.0, 20.0, (8, 4, 16, 24)), (15.0, 30.0, (6, 6, 20, 20))])
def test_skipping_the_steps_outside_the_crop_changes_no_hit(azimuth, elevation, crop):
    """The march only steps where the ray projects into the crop (march_span): every other step could not
    pass behind a covered texel, so it finds what trying every step finds."""
    source, target = view(0.0), view(azimuth, elevation)
    depth, coverage = strip_before_a_wall()
    scale = SIZE / (2 * RADIUS)
    rows, columns = np.mgrid[0:SIZE, 0:SIZE]
    plane = ((columns + 0.5) / scale - RADIUS)[..., None] * target.right + (RADIUS - (rows + 0.5) / scale)[..., None] * target.up
    planes = impostor_warp.field_planes(np.stack([depth, coverage], axis=-1))
    nowhere = (np.full((SIZE, SIZE), np.nan), np.full((SIZE, SIZE), np.nan))
    marched = impostor_warp.first_hit(source, target, plane, planes, SIZE, crop, nowhere)
    expected = every_step_march(source, target, plane, depth, coverage, crop)
    hits = ~np.isnan(expected[0])
    assert 100 < hits.sum() < SIZE * SIZE - 100  # rays that pass behind the surface and rays that miss the crop
    np.testing.assert_allclose(marched[0], expected[0], atol=1e-9)
    np.testing.assert_allclose(marched[1], expected[1], atol=1e-9)


def test_bilinear_taps_weigh_the_four_texels_round_a_point_within_the_crop():
    covered = np.ones((4, 4), dtype=bool)
    uv = np.arange(32, dtype=np.float64).reshape(4, 4, 2) / 32
    tile = DecodedTile(uv, np.zeros((4, 4), dtype=np.int64), covered, np.tile([0.0, 0.0, 1.0], (4, 4, 1)))
    xy = np.array([[[1.75, 1.5]]])  # a quarter of the way from texel (1, 1)'s centre to (2, 1)'s
    (w00, t00), (w10, t10), (w01, t01), (w11, t11) = impostor_warp.bilinear_taps(tile, xy, (0, 0, 4, 4))
    assert (w00[0, 0], w10[0, 0], w01[0, 0], w11[0, 0]) == pytest.approx((0.75, 0.25, 0.0, 0.0))
    np.testing.assert_array_equal(t00.uv[0, 0], uv[1, 1])
    np.testing.assert_array_equal(t10.uv[0, 0], uv[1, 2])
    # Beyond the crop's last column the taps read its edge texel, as crowdview clamps to the cell.
    taps = impostor_warp.bilinear_taps(tile, np.array([[[3.9, 1.5]]]), (0, 0, 3, 4))
    np.testing.assert_array_equal(taps[1][1].uv[0, 0], uv[1, 2])
