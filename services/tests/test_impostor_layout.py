"""The impostor's tile and azimuth count chosen with its frames by measuring (crowdbake.bake.impostor_layout)."""
from __future__ import annotations

import pytest

from crowdbake.bake import impostor_layout as layout
from crowdbake.formats.ranges import Clip, Ranges

ONE_CLIP = Ranges(24, (Clip("cycle", 0, 24, 0, 24, "", 0.0, 0.0),), ())
FRAMES = [2, 3, 4, 6, 8, 12, 24]


def frame_table(rate: float, best: float = 0.96) -> dict[int, float]:
    """A clip whose impostor between baked frames improves by `rate` a frame up to `best`."""
    return {n: min(best, 0.5 + rate * n) for n in FRAMES}


def bytes_by(tile: int, azimuths: int) -> float:
    """One baked frame's maps: 3 rings of square tiles at 3.5 bytes a texel."""
    return azimuths * 3 * tile * tile * 3.5


def test_the_tile_ladder_never_goes_below_the_tile_asked():
    assert layout.tile_ladder(88, 1024) == [88, 100, 112, 132]
    assert layout.tile_ladder(88, 104) == [88, 100]
    assert layout.tile_ladder(88, 64) == [88]


def test_the_azimuth_ladder_falls_in_steps_to_the_floor_then_to_the_measured_floor():
    assert layout.azimuth_ladder(32) == [8, 12, 16, 20, 24, 28, 32]
    assert layout.azimuth_ladder(14) == [8, 12, 14]
    assert layout.azimuth_ladder(8) == [8]
    assert layout.azimuth_ladder(6) == [6]


def test_the_layout_probe_draws_the_rungs_from_the_rule_floor_up_as_before_and_the_measured_floor():
    # From 12 up, every other rung and the top (what the probe drew when 12 was the floor), then 8 below.
    assert layout.probed_azimuths(32) == [8, 12, 20, 28, 32]
    assert layout.probed_azimuths(14) == [8, 12, 14]
    assert layout.probed_azimuths(10) == [8, 10]
    assert layout.probed_azimuths(8) == [8]


def choose(at_views, azimuth_scores, table, budget_mib, elevation_loss=0.0):
    candidates = layout.options(ONE_CLIP, [table], at_views, azimuth_scores, elevation_loss, 88, bytes_by,
                                None if budget_mib is None else budget_mib * 1024 * 1024)
    return layout.choose_layout(candidates), candidates


def test_the_shortlist_measures_the_best_prediction_then_what_the_choice_would_take_by_its_predictions():
    """Margins a few ten-thousandths apart: the cheap options within the tolerance of the best are measured
    (the choice keeps the fewest bytes near the best), not the larger tiles that predict a hair better."""
    from crowdbake.bake import impostor_allocation

    def option(tile, azimuths, mib, margin):
        allocation = impostor_allocation.Allocation([15], [list(range(15))], int(mib * 1024 * 1024), True, [0.9])
        return layout.LayoutOption(tile, azimuths, allocation, 0.98, [0.93], margin)

    best, hair, cheap, cheapest, poor = (option(112, 16, 13.5, 0.0324), option(100, 16, 11.0, 0.0300), option(88, 16, 9.2, 0.0299),
                                         option(88, 12, 6.9, 0.0241), option(88, 8, 4.6, -0.0036))
    picked = layout.shortlist([hair, poor, cheap, best, cheapest], 3)
    assert picked == [best, cheapest, cheap]
    assert layout.choose_layout(picked) is cheapest  # as predicted; the plan measures them first
    # Nothing near the best: the rest by margin.
    far = option(88, 12, 6.9, 0.01)
    assert layout.shortlist([far, poor, best], 3) == [best, far, poor]
    assert layout.shortlist([], 3) == []


def test_a_blurry_character_gets_a_larger_tile_when_the_budget_allows():
    at_views = {88: 0.937, 100: 0.948, 112: 0.956, 132: 0.958}
    chosen, _ = choose(at_views, {12: 0.93, 32: 0.935}, frame_table(0.05), 64.0)
    # 112 is the first tile over the 0.95 target; 132 gains less than the tolerance for more bytes.
    assert chosen.tile == 112
    assert chosen.at_views == pytest.approx(0.956)


def test_a_sharp_character_keeps_the_tile_asked_and_saves_bytes_within_the_tolerance():
    at_views = {88: 0.978, 100: 0.979, 112: 0.98, 132: 0.981}
    scores = {12: 0.94, 16: 0.95, 20: 0.963, 24: 0.966, 28: 0.97, 32: 0.971}
    chosen, candidates = choose(at_views, scores, frame_table(0.05), 16.0)
    assert chosen.tile == 88
    best = max(option.margin for option in candidates)
    assert chosen.margin >= best - 0.01
    # Nothing cheaper is within the tolerance.
    assert all(option.bytes >= chosen.bytes for option in candidates if option.margin >= best - 0.01)


def test_a_tight_budget_spends_on_what_the_probes_say_is_worth_more():
    at_views = {88: 0.96}
    # Views matter little, frames much: fewer azimuths, more frames.
    views_cheap, _ = choose(at_views, {12: 0.955, 16: 0.957, 24: 0.958, 32: 0.96}, frame_table(0.02), 6.0)
    # Views matter much, frames little: more azimuths, fewer frames.
    views_dear, _ = choose(at_views, {12: 0.85, 16: 0.9, 24: 0.95, 32: 0.96}, frame_table(0.2), 6.0)
    assert views_cheap.azimuths < views_dear.azimuths
    assert views_cheap.allocation.counts[0] > views_dear.allocation.counts[0]


def test_a_budget_too_tight_for_twelve_views_and_the_frames_a_fast_clip_needs_takes_eight():
    """Several clips in one budget: where a fast clip loses more between frames than 8 views lose between
    views, the choice goes below the rule's floor of 12 azimuths and spends the bytes on frames."""
    at_views = {88: 0.96}
    fast = {n: min(0.96, 0.3 + 0.04 * n) for n in FRAMES}
    chosen, candidates = choose(at_views, {8: 0.88, 12: 0.9, 20: 0.93, 32: 0.95}, fast, 3.0)
    assert chosen.azimuths == 8
    twelve = max((o for o in candidates if o.azimuths == 12 and o.tile == 88), key=lambda o: o.margin)
    assert chosen.allocation.counts[0] > twelve.allocation.counts[0] and chosen.margin > twelve.margin
    # Where frames are cheap to do without, 8 views are never worth it.
    slow, _ = choose(at_views, {8: 0.88, 12: 0.9, 20: 0.93, 32: 0.95}, frame_table(0.2), 3.0)
    assert slow.azimuths > 8


def test_the_losses_add_to_the_frames_score():
    chosen, candidates = choose({88: 0.97, 100: 0.98}, {12: 0.9, 32: 0.95}, {24: 0.93}, None, elevation_loss=0.01)
    option = next(o for o in candidates if (o.tile, o.azimuths) == (100, 12))
    # 0.93 at 88 and 32 azimuths' views... + (0.98 - 0.97) for the tile - (0.97 - 0.90) for 12 azimuths - 0.01 between rings.
    assert option.between[0] == pytest.approx(0.93 + 0.01 - 0.07 - 0.01)
    assert option.margin == pytest.approx(min(0.98 - 0.95, option.between[0] - 0.90))


def test_a_pair_over_the_budget_at_its_floors_never_wins():
    # At 4 MiB, 132² tiles at 32 azimuths are over the budget even at 2 frames; 88² at 12 azimuths fit.
    chosen, candidates = choose({88: 0.95, 132: 0.99}, {12: 0.9, 32: 0.94}, frame_table(0.05), 4.0)
    over = [option for option in candidates if not option.allocation.fits]
    assert (132, 32) in {(option.tile, option.azimuths) for option in over}
    assert chosen.allocation.fits
    assert all(option.margin < -0.5 for option in over)


def test_noisy_probes_are_made_rising():
    assert layout.rising({88: 0.95, 100: 0.94, 112: 0.96}) == {88: 0.95, 100: 0.95, 112: 0.96}


def test_the_asked_tile_must_have_been_probed():
    with pytest.raises(ValueError, match="asked tile"):
        layout.options(ONE_CLIP, [frame_table(0.05)], {100: 0.9}, {32: 0.9}, 0.0, 88, bytes_by, None)


@pytest.mark.parametrize("count", [12, 20, 32])
def test_an_azimuth_probe_holds_the_two_views_its_camera_blends_at_a_half_each(count):
    """A probe atlas holds only some of a ring's azimuths; crowdview's blend must still take, for each
    camera, the two baked azimuths either side of it in the full ring, half and half."""
    from crowdbake.bake import view_blend
    from crowdbake.stages.impostor_probe import azimuth_gap_probe

    probe, cameras = azimuth_gap_probe(88, count, 20.0, None)
    step = 360.0 / count
    assert len(cameras) == 4 and len(probe.azimuths_deg) <= 8
    for azimuth, elevation in cameras:
        weights = view_blend.blend_view_weights(azimuth, elevation, probe.azimuths_deg, probe.elevations_deg)
        used = sorted(probe.azimuths_deg[tile % len(probe.azimuths_deg)] for tile, w in zip(weights.tiles, weights.weights) if w > 0)
        assert used == sorted({(azimuth - step / 2) % 360.0, (azimuth + step / 2) % 360.0})
        assert max(weights.weights) == pytest.approx(0.5)


def test_a_ring_probe_sits_halfway_between_two_rings():
    from crowdbake.bake.atlas import AtlasLayout
    from crowdbake.bake import view_blend
    from crowdbake.stages.impostor_probe import elevation_gap_probe

    probe, cameras = elevation_gap_probe(AtlasLayout.rings(88, 32, (0.0, 20.0, 40.0)))
    assert probe.elevations_deg == (0.0, 20.0) and {e for _, e in cameras} == {10.0}
    for azimuth, elevation in cameras:
        weights = view_blend.blend_view_weights(azimuth, elevation, probe.azimuths_deg, probe.elevations_deg)
        assert sorted(w for w in weights.weights if w > 0) == pytest.approx([0.5, 0.5])
    assert elevation_gap_probe(AtlasLayout.rings(88, 32, (0.0,))) is None


@pytest.mark.parametrize("cycle_frames", [7, 24, 47])
def test_one_clip_as_a_range_bakes_the_frames_the_rule_would(cycle_frames):
    """The measured choice treats one clip as a bundle of one looping range: at any count its baked frames
    are the ones a one-clip bake spreads over its cycle (poses.impostor_frame_indices)."""
    from types import SimpleNamespace

    from crowdbake.bake import impostor_allocation
    from crowdbake.bake.poses import impostor_frame_indices
    from crowdbake.stages.impostor_plan import one_clip_ranges

    ranges = one_clip_ranges(SimpleNamespace(cycle_frames=cycle_frames))
    for count in impostor_allocation.ladder(ranges.clips[0], 24):
        assert impostor_allocation.frames_at(ranges, 0, count) == impostor_frame_indices(cycle_frames, count)


def test_a_probers_meshes_are_drawn_once_and_kept_within_their_bytes(monkeypatch):
    """Prober.mesh draws a frame's probe views once for its reference and its maps' coverage, and keeps the
    most recently used frames within MESH_CACHE_BYTES (a long range at a large tile would hold gigabytes)."""
    import numpy as np

    from crowdbake.bake.atlas import AtlasLayout
    from crowdbake.stages import impostor_probe

    drawn = []

    def fake_references(scene, plan, angles, with_coverage=False):
        drawn.append(scene)
        return np.full((len(angles), 8, 8, 4 if with_coverage else 3), float(scene), dtype=np.float32)

    def fake_footprints(scene, plan, angles):
        return np.full((len(angles), 8, 8, 4), -float(scene), dtype=np.float32)

    monkeypatch.setattr(impostor_probe, "mesh_references", fake_references)
    monkeypatch.setattr(impostor_probe, "mesh_footprints", fake_footprints)
    monkeypatch.setattr(impostor_probe, "MESH_CACHE_BYTES", 3 * 4 * 8 * 8 * 7 * 4)  # three frames of 4 views
    prober = impostor_probe.Prober.__new__(impostor_probe.Prober)
    prober.layout, prober.plan, prober.scene_at = AtlasLayout(8, (0.0, 90.0, 180.0, 270.0), (20.0,)), None, lambda frame: frame
    prober._meshes = impostor_probe.OrderedDict()
    assert prober.references(5).shape == (4, 8, 8, 3) and float(prober.references(5)[0, 0, 0, 0]) == 5.0
    assert float(prober.mesh(5)[0, 0, 0, 6]) == -5.0  # the footprints beside the reference
    assert drawn == [5]  # the reference and the footprints are drawn once
    for frame in (6, 7, 5, 8):  # 5 used again: 6 is the least recently used when 8 comes
        prober.mesh(frame)
    assert drawn == [5, 6, 7, 8] and list(prober._meshes) == [7, 5, 8]
    prober.mesh(6)
    assert drawn == [5, 6, 7, 8, 6]
