"""The impostor surface map (crowdbake.bake.surface_maps; its exact fields, crowdbake.reference.impostor_maps.
surface_fields) and the reprojection of a stored sample (crowdbake.reference.impostor_warp.warp_tile,
motion_fraction), on geometry whose answer is known by construction."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import impostor_views, surface_maps
from crowdbake.reference import impostor_warp
from crowdbake.reference.coverage import Coverage
from crowdbake.reference.impostor_blend import DecodedTile
from crowdbake.reference.impostor_maps import surface_fields
from crowdbake.bake.view_blend import FrameWeights
from crowdbake.formats.ranges import Clip, Ranges, Transition

SIZE = 16
CENTER = np.array([0.0, 1.0, 0.0])
RADIUS = 1.0


def square_coverage(view: impostor_views.OrthoView, depth: float, rows: slice, columns: slice):
    """A two-triangle square facing `view` at `depth` along view.back, covering texels [rows, columns]
    exactly, with its Coverage (triangle and barycentrics of every covered texel centre)."""
    scale = SIZE / (2 * RADIUS)
    corners_xy = [(columns.start, rows.start), (columns.stop, rows.start), (columns.stop, rows.stop), (columns.start, rows.stop)]
    positions = np.array([view.center + (x / scale - RADIUS) * view.right + (RADIUS - y / scale) * view.up + depth * view.back
                          for x, y in corners_xy])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    triangle = np.full((SIZE, SIZE), -1, dtype=np.int64)
    barycentric = np.zeros((SIZE, SIZE, 3))
    for r in range(rows.start, rows.stop):
        for c in range(columns.start, columns.stop):
            point = view.center + ((c + 0.5) / scale - RADIUS) * view.right + (RADIUS - (r + 0.5) / scale) * view.up + depth * view.back
            for t, face in enumerate(faces):
                a, b, d = positions[face]
                matrix = np.stack([b - a, d - a], axis=1)
                (u, v), *_ = np.linalg.lstsq(matrix, point - a, rcond=None)
                if u >= -1e-9 and v >= -1e-9 and u + v <= 1 + 1e-9:
                    triangle[r, c], barycentric[r, c] = t, (1 - u - v, u, v)
                    break
    return positions, faces, Coverage(triangle, barycentric, 0)


def test_depth_and_motion_of_a_moving_square_and_the_background_takes_the_nearest_inside_texel():
    view = impostor_views.ortho_view(CENTER, RADIUS, 30.0, 20.0, SIZE)
    positions, faces, coverage = square_coverage(view, 0.25, slice(4, 10), slice(6, 12))
    shift = 0.1 * view.right - 0.05 * view.up + 0.3 * view.back  # the part along back is not stored
    depth, motion = surface_fields(view, coverage, positions, positions + shift, faces)
    assert coverage.mask.sum() == 36
    np.testing.assert_allclose(depth, 0.25, atol=1e-9)  # inside, and dilated into the background
    np.testing.assert_allclose(motion[..., 0], 0.1, atol=1e-9)
    np.testing.assert_allclose(motion[..., 1], -0.05, atol=1e-9)


def test_codes_round_trip_within_half_a_step_and_clamp_at_the_range():
    rng = np.random.default_rng(3)
    depth = rng.uniform(-RADIUS, RADIUS, (SIZE, SIZE))
    motion = rng.uniform(-0.5 * RADIUS, 0.5 * RADIUS, (SIZE, SIZE, 2))
    texels = surface_maps.encode_surface(depth, motion, RADIUS)
    assert texels.dtype == np.uint8 and texels.shape == (SIZE, SIZE, 4) and (texels[..., 3] == 255).all()
    back_depth, back_motion = surface_maps.decode_surface(texels, RADIUS)
    assert np.abs(back_depth - depth).max() <= RADIUS / 255 + 1e-12
    assert np.abs(back_motion - motion).max() <= 0.5 * RADIUS / 255 + 1e-12
    far = surface_maps.decode_surface(surface_maps.encode_surface(np.full((1, 1), 5.0), np.full((1, 1, 2), -5.0), RADIUS), RADIUS)
    assert far[0][0, 0] == RADIUS and (far[1][0, 0] == -0.5 * RADIUS).all()


def test_the_next_baked_frame_wraps_round_the_cycle():
    assert surface_maps.next_baked_frame(8, [0, 8, 16]) == 16
    assert surface_maps.next_baked_frame(16, [0, 8, 16]) == 0
    assert surface_maps.next_baked_frame(5, [5]) == 5


def test_the_previous_baked_frame_wraps_round_the_cycle_or_its_own_range():
    assert surface_maps.previous_baked_frame(8, [0, 8, 16]) == 0
    assert surface_maps.previous_baked_frame(0, [0, 8, 16]) == 16
    assert surface_maps.previous_baked_frame(5, [5]) == 5
    # Clips of 20 and 10 pose frames, then transitions of 31 and 1 (as test_pose_ranges).
    ranges = Ranges(62, (Clip("idle", 0, 20, 0, 20, "crossfade", 0.0, 0.0), Clip("walk", 20, 10, 0, 10, "crossfade", 0.0, 0.0)),
                    (Transition(0, 1, 0, 0, 30, 31, 0, 31, 0.0, 0.0), Transition(1, 0, 0, 0, 61, 1, 0, 1, 0.0, 0.0)))
    frames = [0, 5, 10, 15, 20, 25, 30, 40, 50, 60, 61]
    assert surface_maps.previous_baked_frame_in_range(ranges, 5, frames) == 0
    assert surface_maps.previous_baked_frame_in_range(ranges, 0, frames) == 15  # a clip wraps to its own last
    assert surface_maps.previous_baked_frame_in_range(ranges, 20, frames) == 25  # not back into idle
    assert surface_maps.previous_baked_frame_in_range(ranges, 30, frames) == 30  # a transition's first: itself
    assert surface_maps.previous_baked_frame_in_range(ranges, 60, frames) == 50
    with pytest.raises(ValueError, match="not a baked frame"):
        surface_maps.previous_baked_frame_in_range(ranges, 7, frames)


def test_motion_is_the_velocity_at_the_frame_central_where_both_neighbours_are_baked():
    """A vertex on a parabola p(t) = t² at t = -1, 0, 1: the central difference is its velocity at 0 (zero
    here), where the move to the next frame (1) would be off by the acceleration's half step."""
    at = lambda t: np.array([[t * t, 2.0 * t, 0.0]])  # noqa: E731
    np.testing.assert_allclose(surface_maps.motion_positions(at(0), at(-1), at(1)) - at(0), [[0.0, 2.0, 0.0]])
    np.testing.assert_allclose(surface_maps.motion_positions(at(0), None, at(1)), at(1))  # a range's first: the move on
    np.testing.assert_allclose(surface_maps.motion_positions(at(0), at(-1), None) - at(0), [[-1.0, 2.0, 0.0]])  # its last
    np.testing.assert_allclose(surface_maps.motion_positions(at(0), None, None), at(0))


def test_motion_is_taken_between_the_neighbours_a_frame_has():
    assert surface_maps.motion_sides(8, 0, 16) == (0, 16)
    assert surface_maps.motion_sides(30, 30, 40) == (None, 40)  # a transition's first
    assert surface_maps.motion_sides(60, 50, 60) == (50, None)  # its last
    assert surface_maps.motion_sides(5, 5, 5) == (None, None)  # one baked frame
    assert surface_maps.motion_sides(0, 8, 8) == (None, 8)  # two: the move to the other, not a zero difference


def test_motion_fraction_moves_the_earlier_frame_forward_and_the_later_back():
    frames = FrameWeights((2, 3), 0.25)
    assert impostor_warp.motion_fraction(2, frames) == 0.25
    assert impostor_warp.motion_fraction(3, frames) == -0.75
    assert impostor_warp.motion_fraction(2, FrameWeights((2, 2), 0.0)) == 0.0


def test_a_sample_moved_a_quarter_of_the_way_shows_its_texels_a_quarter_of_the_motion_along():
    """A flat surface at the centre plane moving 8 texels right between baked frames: at fraction 0.25 each
    pixel reads the texel 2 to its left; at its own view and frame the tile comes back unchanged."""
    view = impostor_views.ortho_view(CENTER, RADIUS, 0.0, 0.0, SIZE)
    rows, columns = np.mgrid[0:SIZE, 0:SIZE]
    tile = DecodedTile(np.stack([columns, rows], axis=-1) / SIZE, np.zeros((SIZE, SIZE), dtype=np.int64),
                       np.ones((SIZE, SIZE), dtype=bool), np.tile([0.0, 0.0, 1.0], (SIZE, SIZE, 1)))
    motion = np.zeros((SIZE, SIZE, 2))
    motion[..., 0] = 8 * (2 * RADIUS / SIZE)
    surface = (np.zeros((SIZE, SIZE)), motion)
    assert impostor_warp.warp_tile(tile, view, surface, view, 0.0) is tile
    moved = impostor_warp.warp_tile(tile, view, surface, view, 0.25)
    np.testing.assert_allclose(moved.uv[:, 2:, 0], tile.uv[:, :-2, 0])
    assert not moved.covered[:, :2].any() and moved.covered[:, 2:].all()


def test_bc5_decoder_matches_quicktex_and_two_channel_normals_round_trip():
    """The numpy BC5 decoder against quicktex's on random blocks (both endpoint orders), and normals stored as
    two in-view components (map_codecs) come back within a BC5 step of the original, z rebuilt."""
    from quicktex.s3tc.bc5 import BC5Decoder, BC5Texture

    from crowdbake.bake import compression, map_codecs
    from crowdbake.bake.atlas import AtlasLayout

    rng = np.random.default_rng(5)
    blocks = rng.integers(0, 256, (8 * 8, 16), dtype=np.uint8)
    ours = compression.decode_bc5(blocks.tobytes(), 32, 32)
    texture = BC5Texture.from_bytes(blocks.tobytes(), 32, 32)
    theirs = np.frombuffer(BC5Decoder(0, 1).decode(texture).tobytes(), dtype=np.uint8).reshape(32, 32, 4)
    assert np.abs(ours[..., :2].astype(int) - theirs[..., :2]).max() <= 1

    layout = AtlasLayout(16, (0.0, 90.0, 200.0), (0.0, 40.0))
    normals = np.empty((layout.height, layout.width, 3))
    for e, elevation in enumerate(layout.elevations_deg):
        for a, azimuth in enumerate(layout.azimuths_deg):
            view = impostor_views.ortho_view(np.zeros(3), 1.0, azimuth, elevation, 16)
            # A smooth bulge facing the tile's camera, as a visible surface does, tilted differently per tile.
            rows, columns = np.mgrid[0:16, 0:16] / 16.0 - 0.5
            local = np.stack([1.5 * columns + 0.2 * a, -1.5 * rows - 0.1 * e, np.ones((16, 16))], axis=-1)
            local /= np.linalg.norm(local, axis=-1, keepdims=True)
            normals[e * 16:(e + 1) * 16, a * 16:(a + 1) * 16] = local @ np.stack([view.right, view.up, view.back])
    stored = map_codecs.normal_atlas_to_view_xy(map_codecs.model_normals_to_codes(normals), layout)
    back = map_codecs.view_xy_to_model_normals(compression.decode_bc5(compression.encode_bc5(stored), layout.width, layout.height), layout)
    angle = np.degrees(np.arccos(np.clip((back * normals).sum(axis=-1), -1, 1)))
    assert np.median(angle) < 1.0 and angle.max() < 3.0, (np.median(angle), np.percentile(angle, 99))
