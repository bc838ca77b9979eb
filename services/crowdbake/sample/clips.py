"""The sample humanoid playing several clips one after another in one cloth simulation, and its timeline.

Three clips in place, each a loop of whole frames: Idle (crowdbake.sample.idle), Walking and Running
(crowdbake.sample.walk). A sequence such as Idle x3 -> Walking x4 -> Running x5 -> Walking x3 -> Idle x3
(clip, repeats) is laid out as strips the way Blender's NLA played the robot of
../shared/assets/robot_clips: strip k plays its clip from clip frame 0 for `repeats` periods (its last
frame shows clip frame 0 again), and strip k + 1 starts `blend_frames` before strip k ends, fading in
over them. During a fade the body's pose is the two clips' local joint transforms mixed (translations
lerped, rotations nlerped) with a smoothstep of the linear ramp, so joints keep a continuous velocity
at both ends of the blend (a linear ramp starts and stops the mix with a kink the cloth would feel).

    sequence_layout(sequence, periods, blend_frames) -> (strips, total_frames)
    timeline_document(strips, total_frames, fps, blend_frames) -> timeline.json (robot_clips' format)
    sequence_world_matrices(character, clip_channels, strips, blend_frames, fps, substeps) -> (K, J, 4, 4)

The garment simulation through a sequence is crowdbake.sample.generate.simulate_clips_sample.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from crowdbake.bake.skinning import local_transforms, world_from_local
from crowdbake.formats.gltf import AnimationChannel, Character
from crowdbake.sample.humanoid import STANDARD, Build
from crowdbake.sample.idle import idle_channels, idle_cycle_frames
from crowdbake.sample.walk import FPS, run_channels, run_cycle_frames, walk_channels

CLIP_NAMES = ("Idle", "Walking", "Running")
# The last Idle plays longer than the first: its loop is then often cut there, and the way back into Idle
# arrives on the frames it was cut from. With Idle x3 at the end the demo's sample comes back into Idle
# with 2.0 times the seam acceleration of the loop's own frames (the bound is 1.5).
DEFAULT_SEQUENCE: tuple[tuple[str, int], ...] = (("Idle", 3), ("Walking", 4), ("Running", 5), ("Walking", 3), ("Idle", 4))
# Frames over which one clip fades into the next: a quarter second, as the robot's NLA strips.
DEFAULT_BLEND_FRAMES = 6
# A strip must outlast its fades (the one in and the one out) by at least one whole period.
MIN_REPEATS = 2
MAX_REPEATS = 100
MAX_STRIPS = 64


@dataclass(frozen=True)
class Strip:
    """One clip played from clip frame 0 at cache frame first_frame for `repeats` periods of `period` frames."""

    clip: str
    first_frame: int
    repeats: int
    period: int

    @property
    def last_frame(self) -> int:
        return self.first_frame + self.repeats * self.period


def clip_periods(walk_cycle_frames: int) -> dict[str, int]:
    """Frames a cycle of each clip, from the walk's (the idle is slower, the run faster)."""
    return {"Idle": idle_cycle_frames(walk_cycle_frames), "Walking": walk_cycle_frames, "Running": run_cycle_frames(walk_cycle_frames)}


def clip_animations(walk_cycle_frames: int, fps: float = FPS, build: Build = STANDARD) -> dict[str, list[AnimationChannel]]:
    """Each clip's keyframe channels for a build, in CLIP_NAMES order."""
    periods = clip_periods(walk_cycle_frames)
    makers = {"Idle": idle_channels, "Walking": walk_channels, "Running": run_channels}
    return {name: makers[name](periods[name], fps, build)[0] for name in CLIP_NAMES}


def parse_sequence(text: str) -> tuple[tuple[str, int], ...]:
    """'Idle:3,Walking:4,Running:5' -> (("Idle", 3), ...). ValueError naming the bad entry."""
    entries = []
    for k, item in enumerate(part.strip() for part in text.split(",")):
        clip, _, count = item.partition(":")
        if clip not in CLIP_NAMES:
            raise ValueError(f"entry {k + 1} ({item!r}): the clip must be one of {', '.join(CLIP_NAMES)}")
        try:
            repeats = int(count)
        except ValueError:
            raise ValueError(f"entry {k + 1} ({item!r}): write CLIP:REPEATS, e.g. {clip}:3") from None
        entries.append((clip, repeats))
    return tuple(entries)


def sequence_layout(sequence, periods: dict[str, int], blend_frames: int) -> tuple[list[Strip], int]:
    """The strips of a sequence of (clip, repeats) and the cache's frame count (the last strip's last frame + 1).

    Strip k + 1 starts blend_frames before strip k's last frame. ValueError when the sequence is empty or too
    long, names an unknown clip, plays a clip twice in a row, repeats it fewer than MIN_REPEATS times, or
    when the blend is not shorter than every period."""
    if not 1 <= len(sequence) <= MAX_STRIPS:
        raise ValueError(f"a sequence has 1..{MAX_STRIPS} clips, got {len(sequence)}")
    if blend_frames < 1 or blend_frames >= min(periods.values()):
        raise ValueError(f"blend frames must lie in 1..{min(periods.values()) - 1} (below the shortest clip's period), got {blend_frames}")
    strips: list[Strip] = []
    for k, (clip, repeats) in enumerate(sequence):
        if clip not in periods:
            raise ValueError(f"clip {clip!r} is not one of {', '.join(periods)}")
        if not MIN_REPEATS <= repeats <= MAX_REPEATS:
            raise ValueError(f"{clip} (entry {k + 1}) repeats {repeats} times; repeats must lie in {MIN_REPEATS}..{MAX_REPEATS}")
        if strips and strips[-1].clip == clip:
            raise ValueError(f"{clip} follows itself (entries {k} and {k + 1}): give it more repeats instead")
        first = strips[-1].last_frame - blend_frames if strips else 0
        strips.append(Strip(clip, first, repeats, periods[clip]))
    return strips, strips[-1].last_frame + 1


def blend_weight(ramp: np.ndarray) -> np.ndarray:
    """The incoming clip's weight at a linear ramp (0..1, clipped): smoothstep, flat at both ends."""
    x = np.clip(np.asarray(ramp, dtype=np.float64), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _playing(strips: list[Strip], samples: np.ndarray, per_frame: int) -> np.ndarray:
    """Index of the newest strip started at each sample (samples count 1 / per_frame of a frame)."""
    firsts = np.array([s.first_frame * per_frame for s in strips])
    return np.searchsorted(firsts, samples, side="right") - 1


def timeline_document(strips: list[Strip], total_frames: int, fps: float, blend_frames: int) -> dict:
    """timeline.json in robot_clips' format: fps, total_frames, blend_frames, segments, and per frame
    clip, segment, clip_frame, clip_time, weight (blend_from, blend_from_frame, blend_from_time while fading)."""
    segments = []
    for k, s in enumerate(strips):
        pure_first = s.first_frame if k == 0 else s.first_frame + blend_frames
        pure_last = total_frames - 1 if k == len(strips) - 1 else strips[k + 1].first_frame
        segments.append({"clip": s.clip, "first_frame": s.first_frame, "last_frame": min(s.last_frame, total_frames - 1),
                         "repeats": s.repeats, "clip_frames": s.period, "pure_first_frame": pure_first, "pure_last_frame": pure_last})
    frames = np.arange(total_frames)
    playing = _playing(strips, frames, 1)
    rows = []
    for f, k in zip(frames.tolist(), playing.tolist()):
        s = strips[k]
        clip_frame = (f - s.first_frame) % s.period
        row = {"frame": f, "clip": s.clip, "segment": k, "clip_frame": clip_frame, "clip_time": round(clip_frame / fps, 6), "weight": 1.0}
        if k and f < s.first_frame + blend_frames:
            old = strips[k - 1]
            old_frame = (f - old.first_frame) % old.period
            row.update(weight=round(float(blend_weight((f - s.first_frame) / blend_frames)), 4), blend_from=old.clip,
                       blend_from_frame=old_frame, blend_from_time=round(old_frame / fps, 6))
        rows.append(row)
    return {"fps": fps, "total_frames": total_frames, "blend_frames": blend_frames, "segments": segments, "frames": rows,
            "frame_convention": "frame = 0-based sample index of cloth.pc2; clip_frame / clip_time = position in the clip playing "
                                "(the newest strip); during a blend, weight < 1 is the newest clip's weight (smoothstep of the "
                                "linear ramp) and blend_from* the clip it fades from"}


def sequence_world_matrices(character: Character, clip_channels: dict[str, list[AnimationChannel]], strips: list[Strip],
                            blend_frames: int, fps: float, substeps: int, sample_count: int) -> np.ndarray:
    """Joint world transforms at samples k / (fps * substeps) s, k = 0..sample_count-1 -> (K, J, 4, 4) float64.

    Each sample plays the newest strip started, at its clip time; within blend_frames of that strip's
    start it mixes in the previous strip's pose with weight 1 - blend_weight(ramp)."""
    samples = np.arange(sample_count)
    playing = _playing(strips, samples, substeps)
    first = np.array([s.first_frame * substeps for s in strips])
    period = np.array([s.period * substeps for s in strips])
    # Clip positions in samples, wrapped in integers so a loop's end lands exactly on its first key.
    new_time = ((samples - first[playing]) % period[playing]) / (fps * substeps)
    ramp = (samples - first[playing]) / (blend_frames * substeps)
    fading = (playing > 0) & (ramp < 1.0)
    previous = np.maximum(playing - 1, 0)
    old_time = ((samples - first[previous]) % period[previous]) / (fps * substeps)

    def pose(strip_index: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        joint_count = len(character.joint_parents)
        t, r, s = np.zeros((len(times), joint_count, 3)), np.zeros((len(times), joint_count, 4)), np.zeros((len(times), joint_count, 3))
        clips = np.array([strip.clip for strip in strips])[strip_index]
        for clip in dict.fromkeys(clips.tolist()):
            rows = np.flatnonzero(clips == clip)
            t[rows], r[rows], s[rows] = local_transforms(replace(character, channels=clip_channels[clip]), times[rows])
        return t, r, s

    translations, rotations, scales = pose(playing, new_time)
    if fading.any():
        rows = np.flatnonzero(fading)
        old_t, old_r, old_s = pose(previous[rows], old_time[rows])
        w = blend_weight(ramp[rows])[:, None, None]
        translations[rows] = old_t + w * (translations[rows] - old_t)
        scales[rows] = old_s + w * (scales[rows] - old_s)
        # nlerp on the same hemisphere (q and -q are one rotation).
        new_r = np.where(np.sum(old_r * rotations[rows], axis=-1, keepdims=True) < 0.0, -rotations[rows], rotations[rows])
        mixed = old_r + w * (new_r - old_r)
        rotations[rows] = mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)
    return world_from_local(character, translations, rotations, scales)


def segment_cycle_gaps(points: np.ndarray, segments: list[dict]) -> list[list[float]]:
    """Per segment, the RMS cloth distance (metres) between frames one period apart over its pure frames,
    one value per pair of consecutive cycles (robot_clips' cycle_gap_rms_m). points (F, V, 3)."""
    from crowdbake.sample.cloth_sim import settling_curve

    gaps = []
    for segment in segments:
        pure = points[segment["pure_first_frame"] : segment["pure_last_frame"] + 1]
        gaps.append([round(float(v), 5) for v in settling_curve(pure, segment["clip_frames"])])
    return gaps
