"""Several clips in one bundle: which pose frames each clip loop and transition takes, which of them the
impostors bake, and where a baked layer's motion leads (shared_formats/SPEC.md, "Version 2").

Every pose cache of a bundle of several clips holds the clip loops one after another, then the
transitions: each a *range* of pose frames (crowdbake.formats.ranges.Ranges). The impostors bake, per
clip, the frame count its memory budget allows (crowdbake.bake.impostor_budget), spread evenly over the
clip's range as for one clip; per transition its first and last frame (so playback is exact where it
leaves and rejoins the loops) and evenly spaced frames between, about as far apart as the baked frames
of the finer of its two clips (so a transition does not look choppier than the clips it joins), but
never more frames than the larger of its two clips bakes: a simulated transition can be ten times a
walk cycle long (robot_clips' Idle -> Walking is 229 frames), and its maps would otherwise outweigh
the clips' budget several times over.

Pure functions; no I/O.
"""
from __future__ import annotations

import numpy as np

from crowdbake.bake.poses import impostor_frame_indices
from crowdbake.bake.timeline import Timeline
from crowdbake.formats.ranges import Clip, Ranges, Transition


def first_frames(frame_counts: list[int]) -> list[int]:
    """Each range's first pose frame when ranges of `frame_counts` (each >= 1) follow each other from 0."""
    counts = [int(n) for n in frame_counts]
    if any(n < 1 for n in counts):
        raise ValueError(f"first_frames: every range needs at least one frame, got {counts}")
    return [int(x) for x in np.concatenate([[0], np.cumsum(counts)[:-1]])] if counts else []


def clip_frames(clip: Clip, count: int, switches: tuple[int, ...] = ()) -> list[int]:
    """`count` baked pose frames of a clip (as one clip's crowdbake.bake.poses.impostor_frame_indices:
    spread evenly over its loop), with every loop frame in `switches` among them: the frames where a
    character enters or leaves a transition. The even spread starts at the first switch frame and the
    others take the place of grid frames, so the count stays `count` while it exceeds the switches.
    Why: at a switch crowdview shows the transition's first (or last) baked frame, exact; if the clip
    side of the switch were only a blend of the baked frames either side, the impostor would jump there
    by the blend's error, several times its motion from one frame to the next."""
    loop_frames = sorted({int(k) % clip.frames for k in switches})
    offset = loop_frames[0] if loop_frames else 0
    even = max(1, count - max(0, len(loop_frames) - 1))
    grid = {(offset + f) % clip.frames for f in impostor_frame_indices(clip.frames, even)}
    return sorted(clip.first_frame + f for f in grid | set(loop_frames))


def switch_frames(ranges: Ranges) -> list[tuple[int, ...]]:
    """Per clip, its loop frames where a character enters or leaves a transition: the leave_frame of
    each transition from it and the arrive_frame of each transition to it (SPEC.md "Version 2")."""
    switches: list[set[int]] = [set() for _ in ranges.clips]
    for transition in ranges.transitions:
        switches[transition.from_clip].add(transition.leave_frame)
        switches[transition.to_clip].add(transition.arrive_frame)
    return [tuple(sorted(frames)) for frames in switches]


def transition_frames(transition: Transition, spacing: float, max_frames: int | None = None) -> list[int]:
    """A transition's baked pose frames: its first and last, and evenly spaced ones between, the
    round((frames - 1) / spacing) gaps (at least 1) each about `spacing` (> 0) frames, rounded to whole
    frames, and at most `max_frames` (>= 2; None: no cap) frames in all. One frame for a 1-frame transition."""
    if spacing <= 0:
        raise ValueError(f"transition_frames: spacing must be > 0 frames, got {spacing}")
    if max_frames is not None and max_frames < 2:
        raise ValueError(f"transition_frames: max_frames must be at least 2 (its first and last frame), got {max_frames}")
    span = transition.frames - 1
    if span == 0:
        return [transition.first_frame]
    gaps = max(1, int(round(span / spacing)))
    if max_frames is not None:
        gaps = min(gaps, max_frames - 1)
    return sorted({transition.first_frame + int(np.floor(k * span / gaps + 0.5)) for k in range(gaps + 1)})


def clip_spacing(clip: Clip, count: int) -> float:
    """Pose frames between a clip's baked frames (its loop over how many it bakes)."""
    return clip.frames / max(1, min(count, clip.frames))


def baked_frames(ranges: Ranges, clip_counts: list[int]) -> list[int]:
    """Every baked pose frame of the bundle, ascending: clip_frames per clip with its switch frames
    (clip_counts: frames each clip bakes, one per clip), transition_frames per transition at the finer spacing of its two clips, at most
    as many as the larger of the two bakes (and at least its two ends)."""
    if len(clip_counts) != len(ranges.clips):
        raise ValueError(f"baked_frames: {len(clip_counts)} frame counts for {len(ranges.clips)} clips")
    frames: set[int] = set()
    for clip, count, switches in zip(ranges.clips, clip_counts, switch_frames(ranges)):
        frames.update(clip_frames(clip, count, switches))
    for transition in ranges.transitions:
        ends = (transition.from_clip, transition.to_clip)
        spacing = min(clip_spacing(ranges.clips[c], clip_counts[c]) for c in ends)
        frames.update(transition_frames(transition, spacing, max(2, *(clip_counts[c] for c in ends))))
    return sorted(frames)


def range_of(ranges: Ranges, frame: int) -> Clip | Transition:
    """The clip or transition that holds pose frame `frame`; ValueError outside the pose frames."""
    for item in ranges.all():
        if item.first_frame <= frame < item.first_frame + item.frames:
            return item
    raise ValueError(f"range_of: pose frame {frame} is outside the {ranges.pose_frames} pose frames")


def next_baked_frame(ranges: Ranges, frame: int, frame_indices: list[int]) -> int:
    """The baked frame a layer's surface-map motion leads to (SPEC.md "Version 2", Playback): the next
    baked frame of the same range; in a clip the last wraps to the clip's first; in a transition the last
    leads to itself (zero motion: playback leaves the transition there)."""
    item = range_of(ranges, frame)
    inside = [f for f in frame_indices if item.first_frame <= f < item.first_frame + item.frames]
    if frame not in inside:
        raise ValueError(f"next_baked_frame: {frame} is not a baked frame")
    later = [f for f in inside if f > frame]
    if later:
        return later[0]
    return inside[0] if isinstance(item, Clip) else frame


def frames_per_range(ranges: Ranges, frame_indices: list[int]) -> list[dict]:
    """For the report and texture_memory.json: per range its kind, name, pose frames [first, end) and
    baked frames."""
    out = []
    for item in ranges.all():
        end = item.first_frame + item.frames
        if isinstance(item, Clip):
            name, kind = item.name, "clip"
        else:
            name, kind = f"{ranges.clips[item.from_clip].name} -> {ranges.clips[item.to_clip].name}", "transition"
        out.append({"kind": kind, "name": name, "pose_frames": [item.first_frame, end],
                    "baked_frames": [f for f in frame_indices if item.first_frame <= f < end]})
    return out


def clip_body(posed: tuple[np.ndarray, np.ndarray], clip_phase: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """A clip loop's body: loop frame k shows clip frame (clip_phase + k) mod period.

    posed: ((P, V, 3) positions, (P, V, 3) normals) of the clip at each of its P clip frames.
    Returns (frames, V, 3) positions and normals."""
    positions, normals = posed
    index = (int(clip_phase) + np.arange(frames)) % len(positions)
    return positions[index], normals[index]


def body_at_cache_frames(posed: dict[str, tuple[np.ndarray, np.ndarray]], timeline: Timeline, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The body as the simulation saw it at cache frames `frames` (n,): the timeline's clip at its clip
    frame, and during an NLA blend (timeline.blends) the clip fading out too, by the row's weight.

    posed: {clip: ((P, V, 3) positions, (P, V, 3) normals)} at each of the clip's P clip frames.
    Returns (n, V, 3) float32 positions (metres) and normals (not unit during blends: the caller
    normalises). The blend mixes skinned vertex positions, where Blender's NLA mixes the bones' poses:
    the same at the blend's ends, and between them a straight line where the bones would turn (a limb
    swinging far within the 6-frame blend is drawn a little short of its arc).
    """
    frames = np.asarray(frames, dtype=np.int64)
    sample = next(iter(posed.values()))[0]
    positions = np.empty((len(frames), *sample.shape[1:]), dtype=np.float64)
    normals = np.empty_like(positions)
    blends = timeline.blends
    for row, f in enumerate(frames):
        clip = timeline.playing(int(f))
        clip_positions, clip_normals = posed[clip]
        k = int(timeline.clip_frame[f]) % len(clip_positions)
        positions[row], normals[row] = clip_positions[k], clip_normals[k]
        if blends is not None and blends.blend_from[f] is not None and blends.weight[f] < 1.0:
            weight = float(blends.weight[f])
            old_positions, old_normals = posed[blends.blend_from[f]]
            j = int(blends.blend_from_frame[f]) % len(old_positions)
            positions[row] = weight * positions[row] + (1.0 - weight) * old_positions[j]
            normals[row] = weight * normals[row] + (1.0 - weight) * old_normals[j]
    return positions.astype(np.float32), normals.astype(np.float32)


# A range's score uses at most this many azimuths a ring (spread evenly): a few seconds per range.
RANGE_SCORE_AZIMUTHS = 8


def scored_frames(ranges: Ranges, frame_indices: list[int]) -> list[dict]:
    """Where each clip and transition is scored (fidelity.json's `runtime.ranges`): its baked frame (a clip's
    first, a transition's middle one), the baked frame that follows it in the range (next_baked_frame),
    and the pose frame halfway between them with the blend weight crowdview gives the second there.

    Returns per range {"kind", "name", "frame", "next", "between_frame", "between_weight"}. A clip of one
    baked frame is scored halfway round its loop (both layers that frame's); a transition of one, at it."""
    out = []
    for entry, item in zip(frames_per_range(ranges, frame_indices), ranges.all()):
        baked = entry["baked_frames"]
        frame = baked[0] if isinstance(item, Clip) else baked[(len(baked) - 1) // 2]
        following = next_baked_frame(ranges, frame, frame_indices)
        if isinstance(item, Clip):  # a loop: the span wraps round the clip (one baked frame: the whole clip)
            span = (following - frame) % item.frames or item.frames
        else:  # a transition's last baked frame leads to itself: playback leaves the transition there
            span = following - frame
        step = span // 2
        between = item.first_frame + (frame - item.first_frame + step) % item.frames
        out.append({"kind": entry["kind"], "name": entry["name"], "frame": frame, "next": following,
                    "between_frame": between, "between_weight": step / span if span else 0.0})
    return out
