"""Transitions leave and arrive at slow phases of their loops (crowdbake.bake.transitions.switch_is_slow).

At a switch crowdview steps from a loop frame to the transition's first frame (or from its last to a loop
frame) as the loop itself steps at that phase. A walk's steps vary round the loop (robot_clips' Walking:
0.3 to 1.9 times its median), so a switch at a fast phase reads as a jump of up to twice the motion inside
the clips, though nothing pops. Small inputs whose answer is known by construction, and the synthetic
skirt of clip_caches (Walk 12 frames, Run 8, its hem swinging as a sine: slow at the ends of the swing).
"""
from __future__ import annotations

import numpy as np
import pytest

from clip_caches import multi_clip_cache, timeline_document
from crowdbake.bake.clips import ClipLoop, find_clip_loops
from crowdbake.bake.cycle_search import DEFAULT_VELOCITY_WEIGHT
from crowdbake.bake.transitions import (
    SLOW_SWITCH_RATIO, _candidates, body_loop, find_transitions, loop_steps, reference_step, switch_is_slow)
from crowdbake.ingest.timeline import timeline_fields


def test_a_loop_step_is_the_rms_over_cloth_and_body_wrapping_round():
    """One cloth vertex moving 1, 2, 3 then 6 back to the start along x; a still body vertex halves the square."""
    cloth = np.zeros((4, 1, 3))
    cloth[:, 0, 0] = [0.0, 1.0, 3.0, 6.0]
    np.testing.assert_allclose(loop_steps(cloth), [1, 2, 3, 6])
    np.testing.assert_allclose(loop_steps(cloth, np.zeros((4, 1, 3))), np.array([1, 2, 3, 6]) / np.sqrt(2))
    with pytest.raises(ValueError, match="a 4-frame cloth loop with a 3-frame body"):
        loop_steps(cloth, np.zeros((3, 1, 3)))


def test_the_reference_is_the_larger_median_of_the_steps_that_move():
    assert reference_step(np.array([0.0, 0.0, 1.0, 2.0, 3.0]), np.array([0.5, 0.5, 0.7])) == 2.0
    assert reference_step(np.zeros(4), np.array([0.1, 0.3])) == pytest.approx(0.2)  # a still idle leads into a walk
    assert reference_step(np.zeros(4), np.zeros(3)) == 0.0


def test_a_switch_is_slow_where_the_step_at_it_is_within_the_ratio():
    steps = np.array([0.2, 0.8, 1.0, 1.9])
    np.testing.assert_array_equal(switch_is_slow(steps, np.array([0, 1, 2, 3, -1, 5]), 1.0, 0.8), [True, True, False, False, False, True])
    np.testing.assert_array_equal(switch_is_slow(steps, np.array([2, 3]), 0.0), [True, True])  # still loops: nothing can pop


def test_the_body_of_a_loop_frame_is_the_body_at_its_clip_frame():
    """Loop frame k shows clip frame (clip_phase + k) mod period: cache frame start + (k mod period) shows it too."""
    body = np.arange(40, dtype=np.float64)[:, None, None] * np.ones((1, 2, 3))  # each frame holds its number
    loop = ClipLoop(clip="Walk", period=4, segment=0, offset=10, result=_Result(start_frame=3, looped=np.zeros((8, 5, 3))), clip_phase=1)
    np.testing.assert_array_equal(body_loop(body, loop)[:, 0, 0], [13, 14, 15, 16, 13, 14, 15, 16])


class _Result:
    """The two fields of a CycleResult that ClipLoop.start_frame and .looped read."""

    def __init__(self, start_frame: int, looped: np.ndarray):
        self.start_frame, self.looped = start_frame, looped


@pytest.fixture(scope="module")
def skirt():
    cloth, faces = multi_clip_cache()
    timeline = timeline_fields(timeline_document(with_rows=True))
    return cloth, faces, timeline, find_clip_loops(cloth, faces, timeline)


def test_joins_whose_switch_is_slow_are_tried_first(skirt):
    """Slow ones nearest the change first, for the shortest transition, then the plain search's fast ones."""
    cloth, _, timeline, loops = skirt
    run = loops[1]
    steps = loop_steps(run.looped)
    slow = lambda j: switch_is_slow(steps, j + 1, float(np.median(steps)))  # noqa: E731 (arriving, h = 2)
    frames, loop_frames, _ = _candidates(run, cloth, timeline, 1, 2, 5, DEFAULT_VELOCITY_WEIGHT, latest_first=False, slow_at=slow)
    flags = slow(loop_frames)
    assert flags[0] and not flags.all(), flags  # both kinds among the candidates
    first_fast = int(np.argmin(flags))
    assert flags[:first_fast].all() and not flags[first_fast:].any(), flags  # every slow one before any fast one
    assert np.all(np.diff(frames[:first_fast]) > 0), frames  # nearest the change (arriving: the earliest) first
    plain = _candidates(run, cloth, timeline, 1, 2, 5, DEFAULT_VELOCITY_WEIGHT, latest_first=False)[0]
    assert set(plain) <= set(frames)  # the plain order's candidates all stay, after the slow ones


def test_every_switch_is_at_a_slow_phase_within_the_bounds(skirt):
    """Regression: chosen nearest the change of clip alone, Walk -> Run arrived where Run steps 1.41 times
    the median (on robot_clips, Idle -> Walking arrived where Walking steps 1.46 times its median:
    crowdview's switch figure read 1.70 on meshes and 1.82 on impostors against a target of 1.5)."""
    cloth, faces, timeline, loops = skirt
    by_clip = {loop.clip: loop.looped for loop in loops}

    def switch_steps(transitions):
        """Per transition (leaving, arriving): the loop's step at the switch over the reference step."""
        out = []
        for t in transitions:
            steps_a, steps_b = loop_steps(by_clip[t.from_clip]), loop_steps(by_clip[t.to_clip])
            reference = reference_step(steps_a, steps_b)
            out.append((steps_a[(t.leave_loop_frame - 1) % len(steps_a)] / reference,
                        steps_b[(t.arrive_loop_frame - 1) % len(steps_b)] / reference))
        return np.array(out)

    plain = find_transitions(cloth, faces, timeline, loops, slow_switch_ratio=None)
    assert switch_steps(plain).max() > 1.3  # what the rule is for
    transitions = find_transitions(cloth, faces, timeline, loops)
    assert switch_steps(transitions).max() <= SLOW_SWITCH_RATIO, switch_steps(transitions)
    # Each join reports its switch's step (cycle.json's switch_step_ratio), as measured here.
    np.testing.assert_allclose([(t.leave.switch_step_ratio, t.arrive.switch_step_ratio) for t in transitions], switch_steps(transitions))
    for t in transitions:
        assert t.within_bounds, (t.leave.quality, t.arrive.quality)
        # The switch itself is the loop's step: the transition's first frame is the loop frame it replaces.
        loop_a = by_clip[t.from_clip]
        assert np.sqrt(np.mean(np.sum(np.square(t.frames[0] - loop_a[t.leave_loop_frame % len(loop_a)]), -1))) < 1e-3
