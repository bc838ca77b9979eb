"""Several clips in one bundle, the pure parts: which pose frames each range takes, which the impostors
bake, where a layer's motion leads, the body through an NLA blend, the budget per clip and a join's jump."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import pose_ranges
from crowdbake.bake.impostor_budget import FrameExtents, fit_budget, fit_budget_per_clip
from crowdbake.bake.timeline import FrameBlends, Segment, Timeline
from crowdbake.bake.transitions import join_jump_ratios
from crowdbake.formats.ranges import Clip, Ranges, Transition


def clip(name: str, first: int, frames: int) -> Clip:
    return Clip(name, first, frames, 0, frames, "crossfade", 0.0, 0.0)


def move(from_clip: int, to_clip: int, first: int, frames: int) -> Transition:
    return Transition(from_clip, to_clip, 0, 0, first, frames, 0, frames, 0.0, 0.0)


# Clips of 20 and 10 frames, then transitions of 31 and 1 frames: the pose frames are [0, 62).
RANGES = Ranges(62, (clip("idle", 0, 20), clip("walk", 20, 10)), (move(0, 1, 30, 31), move(1, 0, 61, 1)))


def test_ranges_follow_each_other_from_zero():
    assert pose_ranges.first_frames([20, 10, 31, 1]) == [0, 20, 30, 61]
    with pytest.raises(ValueError, match="at least one frame"):
        pose_ranges.first_frames([3, 0])


def test_each_clip_bakes_its_count_spread_over_its_own_range():
    assert pose_ranges.clip_frames(RANGES.clips[0], 4) == [0, 5, 10, 15]
    assert pose_ranges.clip_frames(RANGES.clips[1], 2) == [20, 25]
    assert pose_ranges.clip_frames(RANGES.clips[1], 50) == list(range(20, 30))  # never more than the loop has


def test_a_clip_bakes_the_frames_where_characters_switch():
    """idle (20 frames) is left at loop frame 7 and entered at 13; walk (10) entered at 3: those frames
    are baked, the even spread starts at the first and the count stays what the budget gave."""
    ranges = Ranges(62, RANGES.clips, (Transition(0, 1, 7, 3, 30, 31, 0, 31, 0.0, 0.0), Transition(1, 0, 3, 13, 61, 1, 0, 1, 0.0, 0.0)))
    assert pose_ranges.switch_frames(ranges) == [(7, 13), (3,)]
    assert pose_ranges.clip_frames(ranges.clips[0], 4, (7, 13)) == [0, 7, 13, 14]  # 7, 14, 0 evenly, and 13
    assert pose_ranges.clip_frames(ranges.clips[1], 2, (3,)) == [23, 28]
    frames = pose_ranges.baked_frames(ranges, [4, 2])
    assert {7, 13, 23}.issubset(frames) and len([f for f in frames if f < 20]) == 4
    # More switches than the budget's count: every switch is baked all the same.
    assert pose_ranges.clip_frames(ranges.clips[0], 1, (1, 5, 9)) == [1, 5, 9]


def test_a_transition_bakes_its_ends_and_frames_between_at_the_spacing():
    """31 frames at a spacing of 5: the 30 frames' span in 6 gaps of 5, both ends included."""
    assert pose_ranges.transition_frames(RANGES.transitions[0], 5.0) == [30, 35, 40, 45, 50, 55, 60]
    assert pose_ranges.transition_frames(RANGES.transitions[0], 100.0) == [30, 60]  # the ends at least
    assert pose_ranges.transition_frames(RANGES.transitions[1], 5.0) == [61]
    # At most max_frames in all, the ends kept: a long transition does not outweigh its clips.
    assert pose_ranges.transition_frames(RANGES.transitions[0], 5.0, max_frames=4) == [30, 40, 50, 60]
    assert pose_ranges.transition_frames(RANGES.transitions[0], 5.0, max_frames=2) == [30, 60]
    with pytest.raises(ValueError, match="at least 2"):
        pose_ranges.transition_frames(RANGES.transitions[0], 5.0, max_frames=1)


def test_the_bundle_bakes_every_clip_and_each_transition_at_its_finer_clip_up_to_the_larger_count():
    """idle bakes 4 (spacing 5), walk 2 (spacing 5): the 31-frame transition would take 7 frames at that
    spacing, and takes 4, idle's count, evenly over its span."""
    frames = pose_ranges.baked_frames(RANGES, [4, 2])
    assert frames == [0, 5, 10, 15, 20, 25, 30, 40, 50, 60, 61]
    # Coarser clips: idle 2, walk 1: the transition's two ends.
    assert pose_ranges.baked_frames(RANGES, [2, 1]) == [0, 10, 20, 30, 60, 61]
    # Every frame of idle (20) and walk (10): the 31-frame transition takes 20, the ends among them.
    in_transition = [f for f in pose_ranges.baked_frames(RANGES, [20, 10]) if 30 <= f <= 60]
    assert len(in_transition) == 20 and in_transition[0] == 30 and in_transition[-1] == 60


def test_motion_leads_to_the_next_baked_frame_of_the_same_range():
    frames = pose_ranges.baked_frames(RANGES, [4, 2])
    assert pose_ranges.next_baked_frame(RANGES, 5, frames) == 10
    assert pose_ranges.next_baked_frame(RANGES, 15, frames) == 0  # a clip wraps to its own first
    assert pose_ranges.next_baked_frame(RANGES, 25, frames) == 20  # not on to the transition at 30
    assert pose_ranges.next_baked_frame(RANGES, 50, frames) == 60
    assert pose_ranges.next_baked_frame(RANGES, 60, frames) == 60  # a transition's last: zero motion
    assert pose_ranges.next_baked_frame(RANGES, 61, frames) == 61
    with pytest.raises(ValueError, match="not a baked frame"):
        pose_ranges.next_baked_frame(RANGES, 7, frames)


def test_frames_per_range_names_each_range_and_its_baked_frames():
    listed = pose_ranges.frames_per_range(RANGES, pose_ranges.baked_frames(RANGES, [2, 1]))
    assert [(r["kind"], r["name"], r["pose_frames"], r["baked_frames"]) for r in listed] == [
        ("clip", "idle", [0, 20], [0, 10]), ("clip", "walk", [20, 30], [20]),
        ("transition", "idle -> walk", [30, 61], [30, 60]), ("transition", "walk -> idle", [61, 62], [61])]


def _posed(offset: float, period: int) -> tuple[np.ndarray, np.ndarray]:
    """A one-vertex 'body' at x = offset + clip frame, its normal along +Y: clip frame k is readable."""
    positions = np.zeros((period, 1, 3), np.float32)
    positions[:, 0, 0] = offset + np.arange(period)
    normals = np.tile(np.float32([0.0, 1.0, 0.0]), (period, 1, 1))
    return positions, normals


def test_a_clip_body_starts_at_its_phase_and_wraps_its_period():
    positions, _ = pose_ranges.clip_body(_posed(0.0, 5), 3, 7)
    assert positions[:, 0, 0].tolist() == [3, 4, 0, 1, 2, 3, 4]


def test_the_body_through_a_blend_mixes_both_clips_by_the_rows_weight():
    """Frames 0-3 play A alone; 4-5 blend B in at 0.25 and 0.75 over A's frames 4 and 5; B from 6."""
    clip_frame = np.array([0, 1, 2, 3, 0, 1, 2, 3])
    blends = FrameBlends(clip=("A",) * 4 + ("B",) * 4, weight=np.array([1, 1, 1, 1, 0.25, 0.75, 1, 1.0]),
                         blend_from=(None,) * 4 + ("A", "A", None, None), blend_from_frame=np.array([0, 0, 0, 0, 4, 5, 0, 0]))
    timeline = Timeline(24.0, 8, (Segment("A", 0, 5, 0, 3, 10), Segment("B", 4, 7, 6, 7, 10)), clip_frame, blends)
    posed = {"A": _posed(0.0, 10), "B": _posed(100.0, 10)}
    positions, normals = pose_ranges.body_at_cache_frames(posed, timeline, np.arange(2, 8))
    np.testing.assert_allclose(positions[:, 0, 0], [2, 3, 0.25 * 100 + 0.75 * 4, 0.75 * 101 + 0.25 * 5, 102, 103])
    np.testing.assert_allclose(normals[:, 0], np.tile([0.0, 1.0, 0.0], (6, 1)))
    # Without rows, the newest clip plays alone at its clip frame.
    bare = Timeline(24.0, 8, timeline.segments, clip_frame)
    positions, _ = pose_ranges.body_at_cache_frames(posed, bare, np.arange(3, 6))
    np.testing.assert_allclose(positions[:, 0, 0], [3, 100, 101])


def test_the_budget_holds_per_clip_with_one_azimuth_count_for_all():
    """Two clips of 12 frames, the second reaching twice as far: it needs fewer azimuths, and both get them."""
    reach = np.concatenate([np.full(12, 0.3), np.full(12, 0.6)])
    extents = FrameExtents(reach, np.full((24, 1), -0.9), np.full((24, 1), 0.9))
    args = (1.0, 64, 32, 1, 8)
    alone = [fit_budget(FrameExtents(reach[s], extents.low[s], extents.high[s]), *args, 12, 1.5, 500_000.0) for s in (slice(0, 12), slice(12, 24))]
    assert alone[0].azimuths > alone[1].azimuths
    choices = fit_budget_per_clip(extents, *args, [(0, 12), (12, 12)], 1.5, 500_000.0)
    assert {c.azimuths for c in choices} == {alone[1].azimuths}
    assert all(c.bytes <= 500_000 for c in choices) and choices[0].frames >= choices[1].frames


def test_a_join_that_continues_its_loop_has_no_jump():
    t = np.arange(12, dtype=np.float64)
    played = np.stack([t, np.zeros(12), np.zeros(12)], -1)[:, None, :]  # one point moving 1 per frame
    assert join_jump_ratios(played, 5, played[4:7]) == (0.0, 0.0)
    shifted = played[4:7] + np.array([0.0, 2.0, 0.0])  # the other loop 2 frame-steps aside
    position, velocity = join_jump_ratios(played, 5, shifted)
    assert position == pytest.approx(2.0) and velocity == pytest.approx(0.0)


def test_each_range_is_scored_at_a_baked_frame_and_halfway_to_the_next():
    scored = pose_ranges.scored_frames(RANGES, pose_ranges.baked_frames(RANGES, [4, 2]))
    assert [(r["name"], r["frame"], r["next"], r["between_frame"], r["between_weight"]) for r in scored] == [
        ("idle", 0, 5, 2, 0.4), ("walk", 20, 25, 22, 0.4), ("idle -> walk", 40, 50, 45, 0.5), ("walk -> idle", 61, 61, 61, 0.0)]
    # One baked frame: a clip is scored halfway round its loop, where its one picture is farthest from the pose.
    once = pose_ranges.scored_frames(RANGES, pose_ranges.baked_frames(RANGES, [2, 1]))
    assert [(r["name"], r["frame"], r["next"], r["between_frame"]) for r in once][1] == ("walk", 20, 20, 25)
