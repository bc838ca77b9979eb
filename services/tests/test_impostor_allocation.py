"""One impostor budget per character of several clips, split by measuring (crowdbake.bake.impostor_allocation)."""
from __future__ import annotations

import pytest

from crowdbake.bake import impostor_allocation as allocation
from crowdbake.formats.ranges import Clip, Ranges, Transition


def clip(name: str, first: int, frames: int) -> Clip:
    return Clip(name, first, frames, 0, frames, "crossfade", 0.0, 0.0)


# idle 40 frames, run 20, a 30-frame transition idle -> run (leaving idle at 0, arriving at run 0).
RANGES = Ranges(90, (clip("idle", 0, 40), clip("run", 40, 20)), (Transition(0, 1, 0, 0, 60, 30, 0, 30, 0.0, 0.0),))


def test_the_ladder_stops_at_the_range_and_the_frames_asked():
    idle, run, transition = RANGES.all()
    assert allocation.ladder(idle, 24) == [2, 3, 4, 5, 6, 8, 10, 12, 15, 18, 21, 24]
    assert allocation.ladder(run, 24)[-1] == 20
    assert allocation.ladder(transition, 7) == [2, 3, 4, 5, 6, 7]


def test_frames_at_keeps_switches_and_transition_ends():
    assert 0 in allocation.frames_at(RANGES, 0, 4) and len(allocation.frames_at(RANGES, 0, 4)) == 4
    transition = allocation.frames_at(RANGES, 2, 5)
    assert transition[0] == 60 and transition[-1] == 89 and len(transition) == 5


def test_gaps_are_scored_halfway_and_a_clip_wraps():
    idle = RANGES.clips[0]
    gaps = allocation.gaps_to_score(idle, [0, 10, 20, 30], 8)
    assert [(g.first, g.second, g.between) for g in gaps] == [(0, 10, 5), (10, 20, 15), (20, 30, 25), (30, 0, 35)]
    assert all(g.weight == pytest.approx(0.5) for g in gaps)
    assert len(allocation.gaps_to_score(idle, list(range(0, 40, 2)), 3)) == 3


def test_envelope_never_lets_more_frames_score_less():
    assert allocation.envelope({2: 0.5, 4: 0.8, 6: 0.7, 8: 0.9}) == {2: 0.5, 4: 0.8, 6: 0.8, 8: 0.9}


def scores_by(rate: float, counts: list[int]) -> dict[int, float]:
    """A range whose impostor improves by `rate` a frame up to 0.95."""
    return {n: min(0.95, 0.4 + rate * n) for n in counts}


def test_without_a_budget_each_range_takes_the_fewest_frames_near_its_best():
    tables = [scores_by(0.2, [2, 3, 4, 6, 8]), scores_by(0.03, [2, 4, 8, 12, 16, 20]), scores_by(0.1, [2, 4, 6, 8])]
    chosen = allocation.allocate(RANGES, tables, 1.0, None)
    # idle reaches 0.95 at 3 frames, run at 19 (probed 20), the transition at 6.
    assert chosen.counts == [3, 20, 6] and chosen.fits


def test_over_budget_every_range_reaches_the_same_score_before_any_gets_more():
    tables = [scores_by(0.2, [2, 3, 4, 6, 8]), scores_by(0.03, [2, 4, 8, 12, 16, 20]), scores_by(0.1, [2, 4, 6, 8])]
    budget_frames = 20
    chosen = allocation.allocate(RANGES, tables, 1000.0, budget_frames * 1000.0)
    assert chosen.fits and chosen.bytes <= budget_frames * 1000
    # The slow range (run) is the one left lowest; none is far below it.
    assert min(chosen.scores) == chosen.scores[1]
    assert max(chosen.scores) - min(chosen.scores) < 0.5
    # A budget that holds the answer without one changes nothing.
    assert allocation.allocate(RANGES, tables, 1000.0, 1e9).counts == [3, 20, 6]


def test_a_budget_below_every_floor_keeps_the_floors_and_says_it_does_not_fit():
    tables = [scores_by(0.2, [2, 4]), scores_by(0.03, [2, 4]), scores_by(0.1, [2, 4])]
    chosen = allocation.allocate(RANGES, tables, 1000.0, 3000.0)
    assert chosen.counts == [2, 2, 2] and not chosen.fits


def test_probes_skip_every_other_count_and_the_skipped_are_interpolated():
    ladder = [2, 3, 4, 5, 6, 8, 10, 12, 15, 18, 21, 24]
    assert allocation.probed_counts(ladder) == [2, 4, 6, 10, 15, 21, 24]
    assert allocation.probed_counts([2, 3]) == [2, 3]
    filled = allocation.interpolated({2: 0.5, 4: 0.7, 6: 0.8}, ladder)
    assert filled == {2: 0.5, 3: pytest.approx(0.6), 4: 0.7, 5: pytest.approx(0.75), 6: 0.8}
