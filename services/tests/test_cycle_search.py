"""The cycle search (crowdbake.bake.cycle_search pass 1, crowdbake.bake.cycle end to end) on synthetic caches
whose best seam is known by construction."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import cycle_search as cs
from crowdbake.bake.cycle import CycleParams, find_cycle


def brute_force_distance(points, start, gap, window, velocity_weight):
    """D(start) straight from the definition in the module docstring, one frame at a time."""
    weights = cs.binomial_weights(window)
    half = window // 2
    total = 0.0
    for j, w in zip(range(-half, half + 1), weights):
        f = start + j
        position = np.mean(np.sum((points[f] - points[f + gap]) ** 2, axis=-1))
        velocity_f = 0.5 * (points[f + 1] - points[f - 1])
        velocity_g = 0.5 * (points[f + gap + 1] - points[f + gap - 1])
        velocity = np.mean(np.sum((velocity_f - velocity_g) ** 2, axis=-1))
        total += w * (position + velocity_weight**2 * velocity)
    return np.sqrt(total)


def smooth_noise(frames: int, vertices: int, rng, modes: int = 4, amplitude: float = 0.05) -> np.ndarray:
    """(frames, vertices, 3) slow random motion with no period related to the walk."""
    f = np.arange(frames)[:, None, None]
    noise = np.zeros((frames, vertices, 3))
    for _ in range(modes):
        frequency = rng.uniform(0.05, 0.2)
        noise += amplitude * rng.normal(size=(1, vertices, 3)) * np.sin(frequency * f + rng.uniform(0, 2 * np.pi))
    return noise


def quiet_near(frames: int, centres, radius: float) -> np.ndarray:
    """(frames,) envelope: 0 at each centre, rising as ((f - c) / radius)^2, capped at 1."""
    f = np.arange(frames)
    distance = np.min(np.abs(f[:, None] - np.asarray(centres)[None, :]), axis=1)
    return np.minimum(1.0, (distance / radius) ** 2)


def cache_with_seam_at(target: int, cycle: int = 24, frames: int = 200, vertices: int = 60, seed: int = 0):
    """A periodic motion plus non-periodic noise that vanishes (with its velocity) only at `target`
    and `target + cycle`: the one seam where x(Fs) = x(Fe) and x'(Fs) = x'(Fe)."""
    rng = np.random.default_rng(seed)
    f = np.arange(frames)[:, None, None]
    periodic = rng.normal(size=(1, vertices, 3)) * np.sin(2 * np.pi * f / cycle) + 0.5 * rng.normal(
        size=(1, vertices, 3)
    ) * np.cos(4 * np.pi * f / cycle + 1.0)
    envelope = quiet_near(frames, [target, target + cycle], radius=8.0)[:, None, None]
    return (periodic + envelope * smooth_noise(frames, vertices, rng)).astype(np.float32)


class TestWeightsAndEnergies:
    def test_binomial_weights(self):
        np.testing.assert_allclose(cs.binomial_weights(5), np.array([1, 4, 6, 4, 1]) / 16)
        np.testing.assert_allclose(cs.binomial_weights(1), [1.0])
        with pytest.raises(ValueError, match="odd"):
            cs.binomial_weights(4)

    def test_energies_match_the_definition(self):
        rng = np.random.default_rng(1)
        points = rng.normal(size=(130, 7, 3)).astype(np.float32)  # > one chunk of frames
        gap = 11
        position, velocity = cs.seam_error_energies(points, gap)
        x = points.astype(np.float64)
        for f in [0, 1, 47, 48, 49, 95, 117, 118]:
            assert position[f] == pytest.approx(np.mean(np.sum((x[f] - x[f + gap]) ** 2, -1)), rel=1e-5)
        for f in [1, 47, 48, 49, 96, 117]:
            expected = np.mean(np.sum((0.5 * (x[f + 1] - x[f - 1]) - 0.5 * (x[f + gap + 1] - x[f + gap - 1])) ** 2, -1))
            assert velocity[f] == pytest.approx(expected, rel=1e-5)
        assert np.isnan(velocity[0]) and np.isnan(velocity[-1])

    def test_curve_matches_the_brute_force_distance(self):
        rng = np.random.default_rng(2)
        points = rng.normal(size=(80, 9, 3))
        curve = cs.vertex_distance_curve(points, gap=20, window=5, velocity_weight=2.0, settle_frames=10)
        assert curve.start_frames[0] == 10 and curve.start_frames[-1] == 80 - 20 - 2 - 2
        for i in [0, 7, len(curve.start_frames) - 1]:
            s = int(curve.start_frames[i])
            assert curve.distances[i] == pytest.approx(brute_force_distance(points, s, 20, 5, 2.0), rel=1e-9)

    def test_root_offsets_put_a_travelling_cache_back_on_the_spot(self):
        points = cache_with_seam_at(80).astype(np.float64)
        root = np.zeros((len(points), 3))
        root[:, 2] = 0.05 * np.arange(len(points))  # walking forward
        travelling = points + root[:, None, :]
        on_the_spot = cs.vertex_distance_curve(points, 24)
        blind = cs.vertex_distance_curve(travelling, 24)
        in_root_frame = cs.vertex_distance_curve(travelling, 24, root_offsets=root)
        np.testing.assert_allclose(in_root_frame.distances, on_the_spot.distances, rtol=1e-9, atol=1e-12)
        assert blind.distances.min() > 1.0  # 24 frames of travel = 1.2 units of "mismatch"

    def test_too_few_frames_says_how_many_are_needed(self):
        with pytest.raises(ValueError, match=r"needs at least \d+ frames, the cache has 50"):
            cs.vertex_distance_curve(np.zeros((50, 3, 3)), gap=24, settle_frames=24)

    def test_shape_is_checked(self):
        with pytest.raises(ValueError, match=r"\(frames, vertices, 3\)"):
            cs.vertex_distance_curve(np.zeros((50, 3)), gap=10)


class TestCandidates:
    def test_local_minima_with_plateaus_boundaries_and_nan(self):
        values = np.array([1.0, 2.0, 0.5, 0.5, 0.5, 3.0, 2.5, np.nan, 4.0, 1.0])
        assert cs.local_minima(values).tolist() == [0, 2, 9]
        assert cs.local_minima(np.array([3.0, 2.0, 1.0])).tolist() == [2]

    def test_candidates_are_separated_minima_under_the_threshold(self):
        starts = np.arange(100, 200)
        distances = 1.0 + np.cos(2 * np.pi * (starts - 100) / 10.0) + 0.001 * (starts - 100)
        picked = cs.pick_candidates(starts, distances, min_separation=10, max_candidates=5)
        assert len(picked) == 5
        frames = starts[picked]
        assert frames.tolist() == [105, 115, 125, 135, 145]  # best first: the tilt favours early frames
        # A separation of 15 keeps every other valley.
        wide = starts[cs.pick_candidates(starts, distances, min_separation=15, max_candidates=10)]
        assert np.all(np.diff(np.sort(wide)) >= 15)
        # The threshold keeps only valleys at or below it.
        under = cs.pick_candidates(starts, distances, min_separation=10, max_candidates=10, threshold=0.02)
        assert starts[under].tolist() == [105, 115]

    def test_the_known_seam_is_found(self):
        for target in (70, 113):
            candidates, curves = cs.search_vertex_candidates(cache_with_seam_at(target), 24, settle_frames=24)
            assert candidates[0].start_frame == target
            assert candidates[0].vertex_distance < 0.25 * candidates[1].vertex_distance
            assert len(candidates) <= cs.DEFAULT_MAX_CANDIDATES
            starts = sorted(c.start_frame for c in candidates)
            assert np.all(np.diff(starts) >= 12), "candidates are at least half a cycle apart"
            assert all(c.start_frame >= 24 for c in candidates), "nothing inside the settle-in period"

    def test_a_two_cycle_period_is_found_with_multiples(self):
        # The cloth alternates between two shapes on successive walk cycles (a period doubling that
        # loose cloth can show): no single-cycle seam exists, a two-cycle one does.
        cycle, frames = 20, 160
        rng = np.random.default_rng(4)
        f = np.arange(frames)[:, None, None]
        shape = rng.normal(size=(1, 40, 3))
        points = shape * np.sin(2 * np.pi * f / cycle) + 0.3 * shape[:, ::-1] * np.sin(np.pi * f / cycle)
        single, _ = cs.search_vertex_candidates(points, cycle, settle_frames=cycle)
        both, curves = cs.search_vertex_candidates(points, cycle, settle_frames=cycle, max_cycle_count=2)
        assert [c.cycle_count for c in curves] == [1, 2]
        assert both[0].cycle_count == 2 and both[0].gap == 40
        assert both[0].vertex_distance < 1e-9 < single[0].vertex_distance


def cone_skirt(rings: int = 12, segments: int = 64):
    """Rest geometry of a cone skirt: (rings, segments) heights/angles, and triangles."""
    t = np.linspace(0.0, 1.0, rings)[:, None] * np.ones((1, segments))
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :] * np.ones((rings, 1))
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return t, angle, faces


def skirt_points(t, angle, radial, lift=0.0, swing=0.0):
    radius = 0.15 + 0.15 * t + radial
    turned = angle + swing * t
    return np.stack([radius * np.sin(turned), 1.0 - 0.6 * t + lift, radius * np.cos(turned)], -1).reshape(-1, 3)


def equal_pass1_skirt(smooth_at: int, folds_at: int, cycle: int = 20, frames: int = 120, seed: int = 5):
    """A swinging skirt whose only good seams are at `smooth_at` and `folds_at`, equally good for pass 1.

    Around Fe = s + l of the first seam the whole skirt is lifted by a constant amount; around the second,
    the same RMS displacement is spent on twelve narrow folds. Elsewhere, large non-periodic noise. A lift
    barely moves any edge of a (mostly vertical) skirt; new folds put edges where there were none.
    """
    rng = np.random.default_rng(seed)
    t, angle, faces = cone_skirt()
    amplitude = 0.012
    # Same RMS over vertices by construction: a lift of A vs radial folds A*sqrt(2)*sin(12 angle),
    # whose mean square over 64 equally spaced angles is exactly A^2.
    fold_shape = amplitude * np.sqrt(2.0) * np.sin(12 * angle)
    f = np.arange(frames)
    centres = [smooth_at, smooth_at + cycle, folds_at, folds_at + cycle]
    noise_envelope = np.clip((np.min(np.abs(f[:, None] - np.array(centres)[None]), axis=1) - 5) / 3.0, 0.0, 1.0)
    lift_weight = np.clip(1.0 - (np.abs(f - smooth_at - cycle) - 5) / 3.0, 0.0, 1.0)
    fold_weight = np.clip(1.0 - (np.abs(f - folds_at - cycle) - 5) / 3.0, 0.0, 1.0)
    noise_modes = rng.normal(size=(3, *t.shape))
    cache = []
    for k in range(frames):
        walk = 2 * np.pi * k / cycle
        noise = 0.03 * t * sum(noise_modes[m] * np.sin(0.13 * (m + 1) * k + m) for m in range(3))
        radial = t * 0.01 * np.sin(5 * angle + 0.5 * np.sin(walk)) + noise_envelope[k] * noise + fold_weight[k] * fold_shape
        cache.append(skirt_points(t, angle, radial, lift=lift_weight[k] * amplitude, swing=0.2 * np.sin(walk)))
    return np.asarray(cache, dtype=np.float32), faces


class TestEdgePassSettlesATie:
    def run(self, smooth_at, folds_at):
        from crowdbake.render.cloth_views import ClothViewRenderer

        cloth, faces = equal_pass1_skirt(smooth_at, folds_at)
        params = CycleParams(settle_frames=10, views=5, image_size=160, close="none")
        renderer = ClothViewRenderer(faces, None, params.views, params.image_size, params.elevation_deg)
        return find_cycle(cloth, faces, None, None, 20, params, renderer)

    @pytest.mark.parametrize("smooth_at, folds_at", [(30, 70), (70, 30)])
    def test_folds_decide_between_equal_vertex_distances(self, smooth_at, folds_at):
        result = self.run(smooth_at, folds_at)
        by_start = {c.start_frame: c for c in result.candidates}
        # Each designed seam is a flat valley of pass 1; its first frame is the candidate.
        smooth = next(c for s, c in by_start.items() if abs(s - smooth_at) <= 3)
        folds = next(c for s, c in by_start.items() if abs(s - folds_at) <= 3)
        # Pass 1 cannot tell them apart ...
        assert smooth.vertex_distance == pytest.approx(folds.vertex_distance, rel=1e-3)
        # ... pass 2 can, and ranks first the seam whose folds match: the first closed (the quality bounds,
        # which no unclosed seam of this noisy cache keeps, then decide among them all).
        assert smooth.edge_distance < 0.5 * folds.edge_distance
        assert result.closing_attempts[0].start_frame == smooth.start_frame
        assert result.winner_images.shape == (2, 5, 160, 160)
        assert result.to_dict()["selected_by"] == "edge_distance"


class TestFindCycle:
    def test_without_pass_2_the_best_vertex_distance_wins(self):
        cloth = cache_with_seam_at(90)
        faces = np.array([[0, 1, 2]])
        result = find_cycle(cloth, faces, None, None, 24, CycleParams(close="hermite"))
        assert result.start_frame == 90 and result.end_frame == 114
        assert result.looped.shape == (24, cloth.shape[1], 3)
        document = result.to_dict()
        assert document["selected_by"] == "vertex_distance"
        assert document["candidates"][0]["edge_distance"] is None
        assert document["seam"]["position_jump_ratio"] <= 1e-6
        assert document["parameters"]["window"] == 5

    def test_a_travelling_body_is_followed_in_the_roots_frame(self):
        cloth = cache_with_seam_at(90).astype(np.float64)
        frames = len(cloth)
        rng = np.random.default_rng(9)
        body = rng.normal(size=(1, 30, 3)) * 0.1 + np.zeros((frames, 1, 1))
        root = np.zeros((frames, 3))
        root[:, 0] = 0.03 * np.arange(frames)
        faces = np.array([[0, 1, 2]])
        result = find_cycle(cloth + root[:, None], faces, body + root[:, None], faces, 24, CycleParams())
        assert result.start_frame == 90
        assert result.root_offsets is not None
        assert result.to_dict()["root_motion"]["offset_per_loop"][0] == pytest.approx(24 * 0.03)
        # The loop is the on-the-spot cloth, whatever the root's start position was.
        np.testing.assert_allclose(result.looped[0], cloth[90] - body[90].mean(axis=0) * [1, 0, 1], atol=1e-5)

    def test_exactly_two_cycles_still_loop_with_a_shorter_settle_in(self):
        cloth = cache_with_seam_at(90)[:48]  # two cycles of 24
        result = find_cycle(cloth, np.array([[0, 1, 2]]), None, None, 24)
        # The only start whose window and velocities fit: 48 - 24 - 2 - 2 = 20.
        assert result.settle_frames == 20 and result.start_frame == 20
        assert result.looped.shape == (24, cloth.shape[1], 3)

    def test_nothing_under_the_threshold_is_an_error_naming_the_best(self):
        with pytest.raises(ValueError, match=r"no candidate cycle under the threshold 1e-09: the lowest vertex distance is .* at cache frame 90"):
            find_cycle(cache_with_seam_at(90), np.array([[0, 1, 2]]), None, None, 24, CycleParams(threshold=1e-9))

    @pytest.mark.parametrize(
        "mutate, message",
        [
            (lambda c: c[:40], "too few frames for two cycles"),
            (lambda c: np.where(np.arange(len(c))[:, None, None] == 7, np.nan, c), "NaN"),
            (lambda c: c[..., :2], r"\(frames, vertices, 3\)"),
        ],
    )
    def test_bad_input(self, mutate, message):
        with pytest.raises(ValueError, match=message):
            find_cycle(mutate(cache_with_seam_at(90)), np.array([[0, 1, 2]]), None, None, 24)

    def test_body_frames_must_match(self):
        cloth = cache_with_seam_at(90)
        with pytest.raises(ValueError, match="body has 100 frames but the cloth has 200"):
            find_cycle(cloth, np.array([[0, 1, 2]]), np.zeros((100, 3, 3)), np.array([[0, 1, 2]]), 24)


class TestClosingQualityReport:
    """cycle.json and report.html carry the loop-quality ratios and say loudly when a closing breaks a bound."""

    @staticmethod
    def swinging_sheet():
        # Rows of a sheet swing rigidly about its top row, the swing's centre creeping: every seam is open by
        # about the same angle, and no edge of the simulation ever stretches.
        rows, columns = 6, 7
        r, c = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
        a = (r[:-1, :-1] * columns + c[:-1, :-1]).ravel()
        faces = np.concatenate([np.stack([a, a + columns, a + 1], 1), np.stack([a + 1, a + columns, a + columns + 1], 1)])
        f = np.arange(120)[:, None]
        angle = 0.6 * np.sin(2 * np.pi * f / 24) + 0.006 * f
        depth = 0.1 * r.ravel()[None, :]
        x = np.broadcast_to(0.1 * c.ravel(), (120, rows * columns))
        return np.stack([x, -depth * np.cos(angle), depth * np.sin(angle)], -1).astype(np.float32), faces

    @pytest.mark.parametrize("close, loud", [("hermite", True), ("crossfade", False)])
    def test_quality_in_cycle_json_and_the_report(self, close, loud, tmp_path, caplog):
        from crowdbake.stages.cycle_job import write_cycle_outputs

        cloth, faces = self.swinging_sheet()
        with caplog.at_level("DEBUG", logger="crowdbake.bake.cycle"):
            result = find_cycle(cloth, faces, None, None, 24, CycleParams(close=close, settle_frames=24))
        quality = result.to_dict()["closing"]["quality"]
        assert set(quality["bounds"]) == {"stretch_ratio", "deviation_ratio", "seam_acceleration_ratio"}
        assert quality["within_bounds"] is (not loud)
        # Out of bounds, every candidate was closed before giving up, each rejection logged below a warning (the
        # bake, not the search, decides whether a loop out of bounds may be published: crowdbake.bake.bounds).
        assert (len(result.closing_attempts) == len(result.candidates)) is loud
        assert ("candidate rejected" in caplog.text) is loud
        assert not [record for record in caplog.records if record.levelname == "WARNING"]
        paths = write_cycle_outputs(result, tmp_path)
        page = paths["report"].read_text(encoding="utf-8")
        assert ("WARNING: the hermite closing breaks its quality bounds" in page) is loud
        assert "stretch ratio" in page
