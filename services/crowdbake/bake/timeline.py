"""The clip timeline as the bake reads it: which clip, at which clip frame, plays at each cache frame.

crowdbake.ingest.timeline reads and checks timeline.json into these; crowdbake.bake.clips and
crowdbake.bake.transitions use them. A cache of one clip is a timeline too (one_clip_timeline): one
segment, pure over every frame, so the search of one clip is the search of several.
Plain data (numpy only), light enough for the API to import.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Segment:
    """One strip of the timeline: `clip` plays over cache frames first_frame..last_frame (inclusive), alone
    over pure_first_frame..pure_last_frame (the rest blends with the strip before or after); clip_frames:
    the clip's period in cache frames; new_simulation: the cloth here was simulated apart from the segment
    before (one cache per clip, crowdbake.ingest.clip_caches), so no transition joins the two."""

    clip: str
    first_frame: int
    last_frame: int
    pure_first_frame: int
    pure_last_frame: int
    clip_frames: int
    new_simulation: bool = False

    @property
    def pure_frames(self) -> int:
        return self.pure_last_frame - self.pure_first_frame + 1


@dataclass(frozen=True)
class FrameBlends:
    """What the timeline's per-frame rows say of every cache frame (F of them): `clip` (F,) the newest clip
    playing, `weight` (F,) float64 its weight in 0..1, `blend_from` (F,) the clip fading out (None outside
    blends) and `blend_from_frame` (F,) int64 that clip's frame (0 outside blends)."""

    clip: tuple[str, ...]
    weight: np.ndarray
    blend_from: tuple[str | None, ...]
    blend_from_frame: np.ndarray


@dataclass(frozen=True)
class Timeline:
    """Which clip plays at each cache frame.

    fps: the cache's frame rate; total_frames: F; segments: in playing order, pure stretches disjoint;
    clip_frame: (F,) int64, the playing clip's frame at each cache frame (the newest clip during a blend).
    blends: the per-frame rows' NLA blends (FrameBlends) or None (no rows: the newest clip alone plays).
    """

    fps: float
    total_frames: int
    segments: tuple[Segment, ...]
    clip_frame: np.ndarray = field(repr=False)
    blends: FrameBlends | None = field(default=None, repr=False)

    def playing(self, frame: int) -> str:
        """The clip the timeline plays at cache frame `frame` (the newest during a blend)."""
        if self.blends is not None:
            return self.blends.clip[frame]
        return self.segments[bisect.bisect_right(self.segments, frame, key=lambda s: s.first_frame) - 1].clip

    @cached_property
    def periods(self) -> dict[str, int]:
        """{clip: its period in cache frames}, clips in order of first appearance (made once: a timeline
        may have thousands of segments, and callers ask per clip)."""
        periods: dict[str, int] = {}
        for s in self.segments:
            periods.setdefault(s.clip, s.clip_frames)
        return periods

    def clips(self) -> list[str]:
        """Clip names in order of first appearance."""
        return list(self.periods)

    def period(self, clip: str) -> int:
        return self.periods[clip]

    def changes(self) -> list[tuple[int, int]]:
        """(segment index A, segment index B = A + 1) for every change of clip the simulation made: not
        between segments simulated apart (new_simulation), where no cloth carried over."""
        return [(k, k + 1) for k in range(len(self.segments) - 1)
                if self.segments[k].clip != self.segments[k + 1].clip and not self.segments[k + 1].new_simulation]


def one_clip_timeline(clip: str, fps: float, total_frames: int, clip_frames: int) -> Timeline:
    """A cache that plays `clip` alone from its first frame to its last: one segment, every frame pure,
    cache frame f at clip frame f mod clip_frames."""
    segment = Segment(clip, 0, total_frames - 1, 0, total_frames - 1, clip_frames)
    return Timeline(fps, total_frames, (segment,), np.arange(total_frames, dtype=np.int64) % clip_frames)


def primary_clip(timeline: Timeline, animation: int | str | None) -> str:
    """The clip a bundle carries: `animation` when it names a clip of the timeline, else the first clip.
    ValueError when `animation` names a clip the timeline does not play."""
    clips = timeline.clips()
    if animation is None:
        return clips[0]
    if isinstance(animation, str) and animation in clips:
        return animation
    raise ValueError(f"animation {animation!r} is not a clip of the timeline (it plays {', '.join(clips)}): name one of them")
