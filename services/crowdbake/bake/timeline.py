"""The clip timeline as the bake reads it: which clip, at which clip frame, plays at each cache frame.

crowdbake.ingest.timeline reads and checks timeline.json into these; crowdbake.bake.clips and
crowdbake.bake.transitions use them. Plain data (numpy only), light enough for the API to import.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Segment:
    """One strip of the timeline: `clip` plays over cache frames first_frame..last_frame (inclusive), alone
    over pure_first_frame..pure_last_frame (the rest blends with the strip before or after); clip_frames:
    the clip's period in cache frames."""

    clip: str
    first_frame: int
    last_frame: int
    pure_first_frame: int
    pure_last_frame: int
    clip_frames: int

    @property
    def pure_frames(self) -> int:
        return self.pure_last_frame - self.pure_first_frame + 1


@dataclass(frozen=True)
class Timeline:
    """Which clip plays at each cache frame.

    fps: the cache's frame rate; total_frames: F; segments: in playing order, pure stretches disjoint;
    clip_frame: (F,) int64, the playing clip's frame at each cache frame (the newest clip during a blend).
    """

    fps: float
    total_frames: int
    segments: tuple[Segment, ...]
    clip_frame: np.ndarray = field(repr=False)

    def clips(self) -> list[str]:
        """Clip names in order of first appearance."""
        return list(dict.fromkeys(s.clip for s in self.segments))

    def period(self, clip: str) -> int:
        return next(s.clip_frames for s in self.segments if s.clip == clip)

    def changes(self) -> list[tuple[int, int]]:
        """(segment index A, segment index B = A + 1) for every change of clip the simulation made."""
        return [(k, k + 1) for k in range(len(self.segments) - 1) if self.segments[k].clip != self.segments[k + 1].clip]
