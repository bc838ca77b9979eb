"""Which loops and transition joins break a quality bound (crowdbake.bake.loop_quality.QUALITY_BOUNDS),
named the way a user finds them: the clip, or the transition from -> to, and cache frames.

    out_of_bounds(loops, transitions) -> [OutOfBounds, ...]
    bounds_message(breaks) -> one line for the error that stops a bake

The cycle job (crowdbake.stages.cycle_job) fails on any of them unless the bake accepts them
(accept_out_of_bounds); what was accepted goes to cycle.json and the bundle's manifest.
Plain data; no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from crowdbake.bake.clips import ClipLoop
from crowdbake.bake.loop_quality import QUALITY_BOUNDS, LoopQuality
from crowdbake.bake.transitions import Join, Transition


@dataclass(frozen=True)
class OutOfBounds:
    """One figure over its bound. where: the loop or join, named with its clip(s) and cache frames;
    cache_frames: [first, end) of the frames the closing changed (a loop: Fs..Fe; a join: its crossfade)."""

    where: str
    cache_frames: tuple[int, int]
    figure: str
    value: float
    bound: float

    def text(self) -> str:
        return f"{self.where}: {self.figure} {self.value:.3g} > {self.bound:g}"

    def to_dict(self) -> dict:
        """JSON-ready; value None where the ratio is not finite (cloth that does not move, a seam that does)."""
        return {"where": self.where, "cache_frames": list(self.cache_frames), "figure": self.figure,
                "value": float(self.value) if math.isfinite(self.value) else None, "bound": float(self.bound)}


def quality_breaks(quality: LoopQuality | None, where: str, cache_frames: tuple[int, int]) -> list[OutOfBounds]:
    """An OutOfBounds for each ratio of `quality` over its bound (none for None: no figures measured)."""
    if quality is None:
        return []
    return [OutOfBounds(where, cache_frames, name, float(getattr(quality, name)), QUALITY_BOUNDS[name]) for name in quality.exceeded]


def loop_where(clip: str, start_frame: int, end_frame: int) -> str:
    """'the loop of clip 'Idle' (cache frames [871, 951))'."""
    return f"the loop of clip {clip!r} (cache frames [{start_frame}, {end_frame}))"


def join_where(from_clip: str, to_clip: str, leaving: bool, join: Join) -> str:
    """'the transition 'Idle' -> 'Walking' where it leaves 'Idle' (crossfade over cache frames [205, 231))'."""
    first, end = join_frames(join)
    side = f"leaves {from_clip!r}" if leaving else f"arrives in {to_clip!r}"
    return f"the transition {from_clip!r} -> {to_clip!r} where it {side} (crossfade over cache frames [{first}, {end}))"


def join_frames(join: Join) -> tuple[int, int]:
    """[first, end) cache frames of a join's crossfade."""
    return join.cache_frame - join.half_width, join.cache_frame + join.half_width


def out_of_bounds(loops: list[ClipLoop], transitions: list[Transition]) -> list[OutOfBounds]:
    """Every figure of the loops and the transitions' joins over its bound, loops first, in order."""
    breaks = []
    for loop in loops:
        breaks += quality_breaks(loop.result.closing.quality, loop_where(loop.clip, loop.start_frame, loop.end_frame),
                                 (loop.start_frame, loop.end_frame))
    for transition in transitions:
        for leaving, join in ((True, transition.leave), (False, transition.arrive)):
            breaks += quality_breaks(join.quality, join_where(transition.from_clip, transition.to_clip, leaving, join), join_frames(join))
    return breaks


def bounds_message(breaks: list[OutOfBounds]) -> str:
    """One line for a bake stopped by `breaks` (at least one): the first, how many more, and how to accept them."""
    more = f" (and {len(breaks) - 1} more figures out of bounds, listed in cycle.json's out_of_bounds)" if len(breaks) > 1 else ""
    return (f"{breaks[0].text()}{more}: no candidate loop or join keeps its quality bounds; to publish it anyway, "
            "bake with accept_out_of_bounds (--accept-out-of-bounds)")
