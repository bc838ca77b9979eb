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


def grid_sheet(rows: int = 6, columns: int = 7, spacing: float = 0.1):
    """A flat sheet in the x-y plane: (V, 3) points, (T, 3) triangles."""
    r, c = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    points = np.stack([c * spacing, -r * spacing, 0.0 * r], -1).reshape(-1, 3).astype(np.float64)
    a = (r[:-1, :-1] * columns + c[:-1, :-1]).ravel()
    faces = np.concatenate([np.stack([a, a + columns, a + 1], 1), np.stack([a + 1, a + columns, a + columns + 1], 1)])
    return points, faces


def waving_sheet(frames: int, cycle: int, phase_drift: float = 0.0):
    """A sheet whose rows swing about the top row, rigidly per row (so every edge keeps its length).

    Row r turns about the x axis by angle(f) = 0.6 sin(2 pi f / cycle + phase_drift * f) at radius r * spacing:
    a periodic swing whose phase creeps by `phase_drift` per frame, so frames one cycle apart differ.
    """
    points, faces = grid_sheet()
    f = np.arange(frames)[:, None]
    angle = 0.6 * np.sin(2 * np.pi * f / cycle + phase_drift * f)  # (F, 1)
    depth = -points[None, :, 1]  # distance below the top row
    cloth = np.stack(
        [np.broadcast_to(points[:, 0], (frames, len(points))), -depth * np.cos(angle), depth * np.sin(angle)], -1
    )
    return cloth, faces


class TestCrossfade:
    def test_is_the_default_and_closes_the_seam_inside_its_window(self):
        assert lc.DEFAULT_CLOSE_METHOD == "crossfade" and "crossfade" in lc.CLOSE_METHODS
        cache = drifting_cache()
        start, cycle, half = 30, 20, 4
        trajectory = lc.close_loop(cache, start, cycle, "crossfade", half)
        looped = lc.looped_frames(trajectory)
        # Outside the 2h frames around the seam the loop is the simulator's, bit for bit.
        np.testing.assert_array_equal(looped[half : cycle - half + 1], cache[start + half : start + cycle - half + 1])
        # Mid-window the two sides weigh one half each: frame Fs is halfway between x(Fs) and x(Fe).
        np.testing.assert_allclose(looped[0], 0.5 * (cache[start] + cache[start + cycle]), atol=1e-12)
        # The trajectory is periodic, so the seam figures read a closed seam.
        figures = lc.seam_figures(trajectory)
        assert figures.position_jump_ratio < 1e-9 and figures.velocity_jump_ratio < 1e-9
        assert lc.seam_figures(lc.close_loop(cache, start, cycle, "none")).position_jump_ratio > 1.0

    def test_weights_are_smooth_and_symmetric(self):
        offsets, weight = lc.crossfade_weights(5)
        np.testing.assert_array_equal(offsets, np.arange(-5, 5))
        assert weight[0] == 0.0 and weight[5] == 0.5
        np.testing.assert_allclose(weight[1:] + weight[1:][::-1], 1.0, atol=1e-12)  # s(t) + s(-t) = 1
        assert np.all(np.diff(weight) > 0)

    def test_edge_restoration_gives_back_the_lengths_a_blend_shortens(self):
        cloth, faces = waving_sheet(120, 24, phase_drift=0.05)
        edges = lc.unique_edges(faces)
        rest = lc.edge_lengths(cloth[0], edges)
        start, cycle = 48, 24
        plain = lc.looped_frames(lc.close_loop(cloth, start, cycle, "crossfade"))
        restored = lc.looped_frames(lc.close_loop(cloth, start, cycle, "crossfade", edges=edges))
        strain = lambda loop: lc.mean_edge_strain(loop, edges, rest)  # noqa: E731
        # The sheet is rigid per row: the simulation has no strain at all, a plain blend does (it cuts
        # the chord of every row's arc), and the restoration takes at least half of it away. (A swing
        # this wide needs the whole sheet to move, the slowest case for Jacobi sweeps; folds of real
        # cloth are local: see bench_closing.py.)
        assert strain(cloth[start : start + cycle]) < 1e-12
        assert strain(plain) > 1e-3
        assert strain(restored) < 0.5 * strain(plain)
        # The top row is pinned (A and B agree there): it does not move.
        np.testing.assert_allclose(restored[:, :7], cloth[start : start + cycle, :7], atol=1e-12)

    def test_restore_edge_lengths_keeps_fixed_vertices_and_reaches_the_target(self):
        points = np.array([[[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]])
        edges = np.array([[0, 1]])
        moved = lc.restore_edge_lengths(points, edges, np.array([[1.0]]), np.array([[False, True]]), iterations=20, relaxation=1.0)
        np.testing.assert_allclose(moved[0, 0], [0.0, 0.0, 0.0])
        np.testing.assert_allclose(moved[0, 1], [1.0, 0.0, 0.0], atol=1e-9)

    def test_default_window_shrinks_near_the_end_of_the_cache_and_a_chosen_one_is_refused(self):
        cache = drifting_cache(frames=54)
        trajectory = lc.close_loop(cache, 30, 20, "crossfade")  # Fe = 50: three frames left after Fe
        assert lc.seam_figures(trajectory).position_jump_ratio < 1e-9
        with pytest.raises(ValueError, match="crossfade of 5 frames"):
            lc.close_loop(cache, 30, 20, "crossfade", 5)
        with pytest.raises(ValueError, match="half-width must be in"):
            lc.close_loop(drifting_cache(), 30, 20, "crossfade", 11)


class TestLoopQuality:
    def test_ratios_of_known_loops(self):
        cloth, faces = waving_sheet(120, 24, phase_drift=0.05)
        edges = lc.unique_edges(faces)
        rest = lc.edge_lengths(cloth[0], edges)
        start, cycle = 48, 24
        raw = lc.close_loop(cloth, start, cycle, "none")
        # The simulator's own frames: nothing stretched, nothing moved; only the seam kinks.
        own = lc.loop_quality(raw, lc.looped_frames(raw), edges, rest)
        assert own.deviation_ratio == 0.0
        assert own.seam_acceleration_ratio > 1.5 and own.exceeded == ("seam_acceleration_ratio",)
        # A loop moved everywhere by one seam jump: deviation ratio exactly 1.
        shifted = lc.looped_frames(raw) + (raw[-2] - raw[1])[None]
        assert lc.loop_quality(raw, shifted, edges, rest).deviation_ratio == pytest.approx(1.0)
        # Without edges there is no stretch figure, and no bound is judged on it.
        assert lc.loop_quality(raw, lc.looped_frames(raw)).stretch_ratio is None

    def test_hermite_breaks_the_bounds_the_crossfade_keeps(self):
        """Hermite spreads the seam's velocity mismatch over the whole cycle: on a swinging sheet whose
        phase creeps, the correction bends the rows off their arcs (stretch) far from the seam."""
        cloth, faces = waving_sheet(120, 24, phase_drift=0.02)
        start, cycle = 48, 24
        hermite = lc.close_cycle(cloth, start, cycle, "hermite", cloth_faces=faces)
        crossfade = lc.close_cycle(cloth, start, cycle, "crossfade", cloth_faces=faces)
        assert "stretch_ratio" in hermite.quality.exceeded
        assert crossfade.quality.within_bounds, crossfade.quality
        assert crossfade.quality.deviation_ratio < hermite.quality.deviation_ratio
        assert crossfade.blend_frames == lc.default_crossfade_frames(cycle)


class TestSmoothPushOut:
    def test_every_penetrating_frame_gets_its_whole_push_and_its_neighbours_part_of_it(self):
        points, faces = cylinder()
        frames = 12
        body = lc.BodyFrames(np.repeat(points[None], frames, 0), np.repeat(lc.vertex_normals(points, faces)[None], frames, 0))
        settings = lc.PenetrationSettings(tolerance=1e-3, max_depth=0.3)
        angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        radius = np.full(frames, 0.12)
        radius[6] = 0.09  # one frame dips 1 cm into the body
        loop = np.stack([radius[:, None] * np.sin(angles), np.full((frames, 8), 0.5), radius[:, None] * np.cos(angles)], -1)
        pushed, moved = lc.smooth_push_out(loop, body, settings, reach=2)
        assert not lc.penetration_mask(pushed, body, settings).any()
        ring_radius = np.hypot(pushed[..., 0], pushed[..., 2]).mean(axis=1)
        # Frames next to the dip moved out too (an ease, not a one-frame jump); frames beyond the reach did not.
        assert moved[5].all() and moved[7].all() and not moved[3].any() and not moved[9].any()
        np.testing.assert_allclose(pushed[:4], loop[:4])
        # The ease: the step into and out of the dip frame is smaller than the dip's own push.
        push = np.linalg.norm(pushed - loop, axis=-1).mean(axis=1)
        assert push[6] > 0.005 and np.abs(np.diff(push)).max() < push[6]
        assert ring_radius[6] > 0.1


class TestPushOutKeepsTheSimulatorsContact:
    def test_a_vertex_the_simulation_left_inside_is_not_pushed_by_new(self):
        """push_out 'new' leaves alone a vertex that sits behind the body's surface in some raw frame of the
        cycle (cloth resting behind an open shell), but pushes one the closing moved inside from outside."""
        points, faces = cylinder()
        frames, cycle, start = 40, 12, 10
        angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        radius = np.full((frames, 8), 0.12)
        radius[start + 3, 0] = 0.08  # vertex 0: inside in one raw frame of the cycle...
        radius[start - 3:start, 0] = 0.02  # ...and drawn inside by the blend in others
        radius[start - 3:start, 1] = 0.02  # vertex 1: outside throughout the cycle, deep inside in the blend's lead-in
        cloth = np.stack([radius * np.sin(angles), np.full((frames, 8), 0.5), radius * np.cos(angles)], -1)
        body = np.repeat(points[None], frames, 0)
        closed = lc.close_cycle(cloth, start, cycle, "linear", body=body, body_faces=faces, blend_frames=cycle // 2)
        raw = lc.looped_frames(lc.close_loop(cloth, start, cycle, "none"))
        blended = lc.looped_frames(lc.close_loop(cloth, start, cycle, "linear", cycle // 2))
        looped = np.asarray(closed.looped, dtype=np.float64)
        assert np.hypot(blended[:, 1, 0], blended[:, 1, 2]).min() < 0.1  # the blend drew vertex 1 inside...
        assert np.hypot(looped[:, 1, 0], looped[:, 1, 2]).min() > 0.099  # ...and it was pushed back out
        assert np.hypot(blended[:, 0, 0], blended[:, 0, 2]).min() < 0.1
        np.testing.assert_allclose(looped[:, 0], blended[:, 0], atol=1e-6)  # vertex 0 stays where the blend put it
        assert raw[3, 0, 2] < 0.1 * np.cos(angles[0])

    def test_the_neighbours_of_a_pushed_vertex_keep_its_edges_lengths(self):
        """A push lifts a patch: the pushed vertex stays put, its neighbours within the rings follow so the
        edges round it get their lengths back; vertices beyond the rings do not move."""
        row = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], -1)[None]  # a line of 10 vertices, 1 apart
        edges = np.stack([np.arange(9), np.arange(1, 10)], -1)
        pushed = row.copy()
        pushed[0, 0, 1] = 0.5  # vertex 0 pushed up by half an edge
        moved = np.zeros((1, 10), dtype=bool)
        moved[0, 0] = True
        carried = lc.carry_push_to_neighbours(row, pushed, moved, edges)
        lengths = np.linalg.norm(np.diff(carried[0], axis=0), axis=1)
        np.testing.assert_allclose(carried[0, 0], pushed[0, 0])
        assert abs(lengths[0] - 1.0) < 0.02 < abs(np.linalg.norm(pushed[0, 1] - pushed[0, 0]) - 1.0)
        assert carried[0, 1, 1] > 0.05  # the neighbour rose with it
        np.testing.assert_array_equal(carried[0, lc.PUSH_NEIGHBOUR_RINGS + 1:], row[0, lc.PUSH_NEIGHBOUR_RINGS + 1:])
