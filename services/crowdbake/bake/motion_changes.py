"""Does the cloth move one way all along a cache? Pure numpy, no I/O.

A cache searched as one clip (no timeline) is taken to be one motion repeated: its loop may be cut
anywhere after the settle-in and is played on the body's one clip. A cache simulated across several
clips (Idle, then Walking, then Running) breaks that: the search finds its best loop where the cloth
barely moves (inside Idle) and plays it on the running body. A change of clip changes how fast the
cloth moves, so the check compares the cloth's speed over consecutive cycles of the clip's length:

    motion_changes(cloth, cycle_frames, first_frame) -> [MotionChange(frame, factor), ...]

The statistic, per cache frame f: the mean over the l frames f..f+l-1 of the RMS step of the cloth's
shape (each frame's vertices minus their mean, so a character walking forward does not count), l the
cycle length. Averaged over a whole cycle, the speed of one periodic motion is the same whatever the
phase f starts at, so along a cache of one clip it stays flat but for the cloth's own cycle-to-cycle
variation; a change of clip changes it by the ratio of the clips' speeds. `factor` compares the cycle
after f with the cycle before it (the faster over the slower).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Consecutive cycles whose mean speeds differ by more than this factor play different motions. Measured
# (largest factor after the settle-in, cycles of the clip's length):
#   one motion repeated:  long_skirt on CesiumMan 1.13, the sample's loose / tight garment 1.06 / 1.04,
#                         robot_clips' Walking stretch alone 1.30
#   a change of clip:     robot_clips Walking -> Running 1.97, Running -> Walking 2.62, Idle -> Walking 10.7;
#                         the sample's clips Walking <-> Running 2.1, Idle <-> Walking 3.4 to 6.1
# 1.6 is the geometric middle of the largest repeat (1.30) and the smallest change (1.97): the same
# margin, as a ratio, on either side.
CHANGE_FACTOR = 1.6
# At most this many changes are returned, the largest first: enough to locate the clips in a message.
MAX_CHANGES = 5


@dataclass(frozen=True)
class MotionChange:
    """frame: the first cache frame of the cycle after the change; factor: the faster of the cycles
    before and after it over the slower, by mean cloth speed (>= CHANGE_FACTOR; inf from stillness)."""

    frame: int
    factor: float


def cycle_speeds(cloth: np.ndarray, cycle_frames: int) -> np.ndarray:
    """(F - l,) float64: at f, the mean over the l steps f -> f + 1 .. f + l - 1 -> f + l of the RMS step of
    the cloth's shape (vertices minus their mean), cache units a frame. cloth: (F, V, 3) float, F > l >= 1."""
    frames = np.asarray(cloth, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[2] != 3:
        raise ValueError(f"cycle_speeds: cloth must be (F, V, 3), got {frames.shape}")
    if not 1 <= cycle_frames < frames.shape[0]:
        raise ValueError(f"cycle_speeds: cycle_frames {cycle_frames} must lie in 1..{frames.shape[0] - 1}")
    shape = frames - frames.mean(axis=1, keepdims=True)
    steps = np.sqrt(np.mean(np.sum(np.square(np.diff(shape, axis=0)), axis=-1), axis=-1))
    # A sliding sum, not differences of a running total: a still stretch stays exactly 0.
    return np.convolve(steps, np.full(cycle_frames, 1.0 / cycle_frames), mode="valid")


def _speed_factor(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """The faster of two speeds over the slower, elementwise: 1 when both are still, inf from stillness."""
    low, high = np.minimum(before, after), np.maximum(before, after)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(high == 0, 1.0, high / low)


def motion_changes(cloth: np.ndarray, cycle_frames: int, first_frame: int = 0, factor: float = CHANGE_FACTOR) -> list[MotionChange]:
    """Where the cloth's speed over a cycle changes by more than `factor` from the cycle before, looking
    only at cycles from first_frame on (the settle-in before it is the search's to skip).

    cloth: (F, V, 3); cycle_frames: l. Each run of consecutive frames over `factor` is one change, at its
    largest factor. Returns at most MAX_CHANGES changes, the largest first; none when the cache holds no
    two whole cycles from first_frame."""
    speeds = cycle_speeds(cloth, cycle_frames)
    frames = np.arange(max(first_frame, 0) + cycle_frames, len(speeds))
    if len(frames) == 0:
        return []
    factors = _speed_factor(speeds[frames - cycle_frames], speeds[frames])
    over = factors > factor
    changes = []
    start = 0
    while start < len(frames):
        if not over[start]:
            start += 1
            continue
        end = start
        while end + 1 < len(frames) and over[end + 1]:
            end += 1
        peak = start + int(np.argmax(factors[start : end + 1]))
        changes.append(MotionChange(int(frames[peak]), float(factors[peak])))
        start = end + 1
    return sorted(changes, key=lambda change: -change.factor)[:MAX_CHANGES]
