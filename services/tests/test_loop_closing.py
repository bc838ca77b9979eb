"""Loop closing, seam figures and penetration (crowdbake.bake.loop_closing) on caches built to a known answer."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import loop_closing as lc


def drifting_cache(frames: int = 90, vertices: int = 30, cycle: int = 20, seed: int = 0) -> np.ndarray:
    """(frames, vertices, 3): a periodic motion (period `cycle`) plus a slow non-periodic drift.

    The drift makes x(f + cycle) != x(f) in position and velocity, so every seam is open.
    """
    rng = np.random.default_rng(seed)
    f = np.arange(frames)[:, None, None]
    base = rng.normal(size=(1, vertices, 3))
    periodic = rng.normal(size=(1, vertices, 3)) * np.sin(2 * np.pi * f / cycle)
    drift = rng.normal(size=(1, vertices, 3)) * 0.02 * f + rng.normal(size=(1, vertices, 3)) * 0.3 * np.sin(0.07 * f)
    return base + periodic + drift


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(a), axis=-1))))


class TestCloseLoop:
    def test_none_is_the_simulators_frames(self):
        cache = drifting_cache()
        trajectory = lc.close_loop(cache, 30, 20, "none")
        assert trajectory.shape == (23, 30, 3)
        np.testing.assert_array_equal(lc.looped_frames(trajectory), cache[30:50])
        np.testing.assert_array_equal(trajectory, cache[29:52])

    def test_hermite_closes_position_and_velocity_and_leaves_fs_alone(self):
        cache = drifting_cache()
        start, cycle = 30, 20
        trajectory = lc.close_loop(cache, start, cycle, "hermite")
        looped = lc.looped_frames(trajectory)
        # Zero correction at Fs (value and slope), so the loop starts on the simulator's own frame.
        np.testing.assert_allclose(looped[0], cache[start], atol=1e-12)
        # Closed Fe equals Fs; the velocity leaving Fe equals the velocity leaving Fs.
        np.testing.assert_allclose(trajectory[-2], trajectory[1], atol=1e-12)
        velocity_end = 0.5 * (trajectory[-1] - trajectory[-3])
        velocity_start = 0.5 * (trajectory[2] - trajectory[0])
        np.testing.assert_allclose(velocity_end, velocity_start, atol=1e-9)
        figures = lc.seam_figures(trajectory)
        assert figures.position_jump_ratio < 1e-9
        assert figures.velocity_jump_ratio < 1e-6
        # The raw seam was open: the test would mean nothing otherwise.
        raw = lc.seam_figures(lc.close_loop(cache, start, cycle, "none"))
        assert raw.position_jump_ratio > 1.0

    def test_hermite_spreads_the_correction_over_the_cycle(self):
        cache = drifting_cache()
        start, cycle = 30, 20
        correction = lc.looped_frames(lc.close_loop(cache, start, cycle, "none")) - lc.looped_frames(
            lc.close_loop(cache, start, cycle, "hermite")
        )
        per_frame = np.sqrt(np.mean(np.sum(correction**2, axis=-1), axis=-1))
        # Monotone growth of a cubic ease, not a few frames carrying it all.
        assert per_frame[cycle // 2] > 0.2 * per_frame[-1]

    def test_linear_blend_ends_on_the_frame_before_fs(self):
        cache = drifting_cache()
        start, cycle, blend = 30, 20, 5
        trajectory = lc.close_loop(cache, start, cycle, "linear", blend_frames=blend)
        looped = lc.looped_frames(trajectory)
        # Frames before the blend are untouched; the last looped frame is x(Fs - 1): a real step into Fs.
        np.testing.assert_array_equal(looped[: cycle - blend], cache[start : start + cycle - blend])
        np.testing.assert_allclose(looped[-1], cache[start - 1], atol=1e-12)
        # Halfway through the ramp the frame is a mix of its own frame and the previous cycle's.
        i = cycle - blend + 2
        weight = 3 / blend
        np.testing.assert_allclose(looped[i], (1 - weight) * cache[start + i] + weight * cache[start + i - cycle], atol=1e-12)
        figures = lc.seam_figures(trajectory)
        assert figures.position_jump_ratio < 1e-9
        assert figures.velocity_jump_ratio < 1e-9

    @pytest.mark.parametrize(
        "start, method, blend, message",
        [
            (0, "none", None, "does not fit"),
            (70, "hermite", None, "does not fit"),
            (3, "linear", 5, "needs Fs >= 5"),
            (30, "cubic", None, "method must be one of"),
            (30, "linear", 40, "blend_frames must be in"),
        ],
    )
    def test_rejects_what_cannot_be_closed(self, start, method, blend, message):
        with pytest.raises(ValueError, match=message):
            lc.close_loop(drifting_cache(), start, 20, method, blend)


class TestSeamFigures:
    def test_known_ratios_on_a_constant_velocity_motion(self):
        # x(i) = i * v for every vertex: steps are |v|; a jump J added from Fe on gives |J| / |v|.
        v = np.array([0.0, 0.0, 0.5])
        frames = np.arange(-1, 12)[:, None, None] * v[None, None, :] * np.ones((1, 4, 1))
        jump = np.array([0.3, 0.4, 0.0])  # |J| = 0.5
        frames[-2:] += jump
        figures = lc.seam_figures(frames)
        assert figures.median_step == pytest.approx(0.5)
        # x(Fe) - x(Fs) = 10 v + J.
        assert figures.position_jump_ratio == pytest.approx(np.linalg.norm(10 * v + jump) / 0.5)
        # Central velocity at Fe: ((Fe+1 + J) - (Fe-1)) / 2 = v + J / 2, so the jump is |J| / 2.
        assert figures.velocity_jump_ratio == pytest.approx(0.25 / 0.5)

    def test_periodic_motion_has_a_seamless_loop(self):
        f = np.arange(-1, 22)[:, None, None]
        rng = np.random.default_rng(3)
        frames = rng.normal(size=(1, 10, 3)) * np.sin(2 * np.pi * f / 20) + rng.normal(size=(1, 10, 3)) * np.cos(4 * np.pi * f / 20)
        figures = lc.seam_figures(frames)
        assert figures.position_jump_ratio < 1e-9
        assert figures.velocity_jump_ratio < 1e-9
        assert figures.max_step_ratio < 2.5  # the wrap step is an ordinary step

    def test_still_cloth_gives_zero_not_nan(self):
        figures = lc.seam_figures(np.zeros((10, 3, 3)))
        assert figures.position_jump_ratio == 0.0 and figures.velocity_jump_ratio == 0.0


def cylinder(radius: float = 0.1, height: float = 1.0, rings: int = 41, segments: int = 96):
    """An open upright cylinder: (V, 3) points and (T, 3) outward-facing triangles."""
    t = np.linspace(0.0, 1.0, rings)[:, None]
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    points = np.stack(
        [radius * np.sin(angle) + 0 * t, np.broadcast_to(height * (1 - t), (rings, segments)), radius * np.cos(angle) + 0 * t], -1
    ).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return points, faces


class TestNormalsAndPenetration:
    def test_vertex_normals_point_out_of_a_cylinder(self):
        points, faces = cylinder()
        normals = lc.vertex_normals(points, faces)
        radial = points * np.array([1.0, 0.0, 1.0])
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        assert np.all(np.einsum("ij,ij->i", normals, radial) > 0.99)
        # Batched over frames gives the same answer per frame.
        batched = lc.vertex_normals(np.stack([points, points + 1.0]), faces)
        np.testing.assert_allclose(batched[1], normals, atol=1e-12)

    def test_vertex_normals_of_a_flat_square_and_an_unused_vertex(self):
        points = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 5]], dtype=float)
        faces = np.array([[0, 1, 2], [0, 2, 3]])
        normals = lc.vertex_normals(points, faces)
        np.testing.assert_allclose(normals[:4], [[0, 0, 1]] * 4)
        np.testing.assert_array_equal(normals[4], [0, 0, 0])

    def test_inside_outside_and_far_points(self):
        points, faces = cylinder()
        body = lc.BodyFrames(points[None], lc.vertex_normals(points, faces)[None])
        settings = lc.PenetrationSettings(tolerance=1e-3, max_depth=0.3)
        angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
        ring = lambda r, y: np.stack([r * np.sin(angles), np.full(12, y), r * np.cos(angles)], -1)
        cloth = np.concatenate([ring(0.08, 0.5), ring(0.12, 0.5), ring(0.1005, 0.5), ring(2.0, 0.5)])[None]
        mask = lc.penetration_mask(cloth, body, settings)[0]
        assert mask[:12].all(), "2 cm inside a 10 cm cylinder is inside"
        assert not mask[12:24].any(), "outside is outside"
        assert not mask[24:36].any(), "within the tolerance of the surface is contact, not penetration"
        assert not mask[36:].any()

    def test_push_out_moves_inside_vertices_just_outside(self):
        points, faces = cylinder()
        body = lc.BodyFrames(points[None], lc.vertex_normals(points, faces)[None])
        settings = lc.PenetrationSettings(tolerance=1e-3, max_depth=0.3)
        angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        cloth = np.stack([0.09 * np.sin(angles), np.full(16, 0.4), 0.09 * np.cos(angles)], -1)[None]
        pushed, moved = lc.push_out(cloth, body, settings)
        assert moved.all()
        assert not lc.penetration_mask(pushed, body, settings).any()
        radius = np.hypot(pushed[0, :, 0], pushed[0, :, 2])
        # Just outside: the faceted cylinder's vertex radius plus the tolerance, give or take the facets.
        assert np.all(radius > 0.1) and np.all(radius < 0.1 + 5e-3)
        # `only` restricts the push to the chosen vertices.
        only = np.zeros((1, 16), dtype=bool)
        only[0, :4] = True
        pushed, moved = lc.push_out(cloth, body, settings, only=only)
        assert moved[0, :4].all() and not moved[0, 4:].any()
        np.testing.assert_array_equal(pushed[0, 4:], cloth[0, 4:])

    def test_tolerances_scale_with_the_body(self):
        points, _ = cylinder(height=1.0)
        small = lc.PenetrationSettings.for_body(points[None])
        large = lc.PenetrationSettings.for_body(100 * points[None])
        assert large.tolerance == pytest.approx(100 * small.tolerance)
        assert large.max_depth == pytest.approx(100 * small.max_depth)


def twisting_skirt(frames: int, cycle: int, body_radius: float = 0.1, cloth_radius: float = 0.125):
    """Cloth rings hugging a cylinder body and turning around it, faster than the walk repeats.

    After one cycle the cloth has turned by 100 degrees more than it should: a blend between two such
    frames runs along the chord of the circle, straight through the body (the paper's warning).
    """
    body_points, body_faces = cylinder(body_radius)
    segments = 36
    angles = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    heights = np.linspace(0.3, 0.7, 5)
    f = np.arange(frames)[:, None, None]
    turn = np.radians(100.0) / cycle * f + 0.3 * np.sin(2 * np.pi * f / cycle)
    angle = angles[None, None, :] + turn + 0.0 * heights[None, :, None]
    cloth = np.stack(
        [cloth_radius * np.sin(angle), np.broadcast_to(heights[None, :, None], angle.shape), cloth_radius * np.cos(angle)], -1
    ).reshape(frames, -1, 3)
    body = np.broadcast_to(body_points, (frames, *body_points.shape))
    return cloth, body, body_faces


class TestCloseCycle:
    @pytest.mark.parametrize("method", ["linear", "hermite"])
    def test_closing_closes_the_seam_without_raising_penetration(self, method):
        cycle = 20
        cloth, body, body_faces = twisting_skirt(100, cycle)
        result = lc.close_cycle(cloth, 40, cycle, method, body=body, body_faces=body_faces)
        assert result.seam_before.position_jump_ratio > 1.0
        assert result.seam_after.position_jump_ratio <= 0.25
        assert result.looped.shape == (cycle, cloth.shape[1], 3) and result.looped.dtype == np.float32
        # The raw cloth never touches the body; closing cuts through it, the push-out takes it back out.
        assert result.penetrating_before.sum() == 0
        assert result.penetrating_closed.sum() > 0, "the test needs a closing that does push cloth in"
        assert np.all(result.penetrating_after <= result.penetrating_before)
        assert result.pushed_vertices > 0

    def test_push_out_none_keeps_the_penetration_and_all_clears_it(self):
        cycle = 20
        cloth, body, body_faces = twisting_skirt(100, cycle)
        kept = lc.close_cycle(cloth, 40, cycle, "linear", body=body, body_faces=body_faces, push_out_mode="none")
        np.testing.assert_array_equal(kept.penetrating_after, kept.penetrating_closed)
        assert kept.pushed_vertices == 0
        # Sink a few raw vertices into the body: "new" leaves them, "all" pushes them out.
        sunk = cloth.copy()
        sunk[:, :3] *= np.array([0.5, 1.0, 0.5])
        new = lc.close_cycle(sunk, 40, cycle, "none", body=body, body_faces=body_faces, push_out_mode="new")
        assert np.all(new.penetrating_before == 3) and np.all(new.penetrating_after == 3)
        np.testing.assert_array_equal(new.looped, sunk[40:60].astype(np.float32))
        cleared = lc.close_cycle(sunk, 40, cycle, "none", body=body, body_faces=body_faces, push_out_mode="all")
        assert cleared.penetrating_after.sum() == 0

    def test_without_a_body_there_is_nothing_to_count(self):
        cloth, _, _ = twisting_skirt(100, 20)
        result = lc.close_cycle(cloth, 40, 20, "hermite")
        assert result.penetrating_before.sum() == 0 and result.pushed_vertices == 0
        assert result.seam_after.position_jump_ratio < 1e-9

    def test_a_body_needs_normals_or_faces(self):
        cloth, body, _ = twisting_skirt(100, 20)
        with pytest.raises(ValueError, match="body_normals or body_faces"):
            lc.close_cycle(cloth, 40, 20, "hermite", body=body)
