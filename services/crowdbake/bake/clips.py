"""Several clips in one cloth simulation: the timeline, and a loop per clip (paper section 3, per clip).

A cloth cache simulated while the character plays clip after clip (Idle, then Walking, then Running...)
holds, for each clip, stretches of frames driven by that clip alone (the *pure* frames: between the blends
where one clip fades into the next). The timeline says which clip, at which clip frame, plays at each
cache frame (crowdbake.ingest.timeline reads and checks it).

    find_clip_loops(cloth, cloth_faces, timeline, params, ...) -> list[ClipLoop]

runs the single-clip cycle search (crowdbake.bake.cycle.find_cycle: pass 1, pass 2, closing, quality) on
each pure stretch of a clip, with the cycle length = that clip's period, and keeps the best loop of each
clip. A clip met twice (Walking before and after Running) competes over both stretches; the loop never
spans a blend, so its frames are the clip's motion only. The transitions between the loops are
crowdbake.bake.transitions.

Pure numpy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from crowdbake.bake.cycle import CycleParams, CycleResult, RenderViews, find_cycle
from crowdbake.bake.timeline import Timeline

Progress = Callable[[str, int, int], None]


@dataclass
class ClipLoop:
    """The loop of one clip: the cycle search's result on one pure stretch of it.

    segment: index of the timeline segment the loop was cut from; offset: that stretch's first cache frame
    (result's frames count from it); start_frame/end_frame: Fs and Fe in cache frames; clip_phase: the
    clip frame at Fs (loop frame k shows clip frame (clip_phase + k) mod period).
    """

    clip: str
    period: int
    segment: int
    offset: int
    result: CycleResult
    clip_phase: int

    @property
    def start_frame(self) -> int:
        return self.offset + self.result.start_frame

    @property
    def end_frame(self) -> int:
        return self.offset + self.result.end_frame

    @property
    def looped(self) -> np.ndarray:
        """(L, V, 3) float32: the closed loop."""
        return self.result.looped

    def cache_result(self, cache_frames: int) -> CycleResult:
        """The search's result with cache frame numbers (its own count from the stretch's first frame);
        cache_frames: the whole cache's length, recorded as input.frame_count."""
        shift = self.offset
        result = self.result
        return replace(
            result,
            start_frame=result.start_frame + shift,
            end_frame=result.end_frame + shift,
            candidates=[replace(c, start_frame=c.start_frame + shift, end_frame=c.end_frame + shift) for c in result.candidates],
            closing_attempts=[replace(a, start_frame=a.start_frame + shift, end_frame=a.end_frame + shift) for a in result.closing_attempts],
            curves=[replace(curve, start_frames=curve.start_frames + shift) for curve in result.curves],
            settle_frames=result.settle_frames + shift,
            frame_count=cache_frames,
            # Root positions are indexed by frame: the stretch's own, after `shift` unused rows.
            root_offsets=None if result.root_offsets is None else np.concatenate([np.zeros((shift, 3)), result.root_offsets]),
        )

    def to_dict(self, cache_frames: int) -> dict:
        """This clip's entry of cycle.json's `clips`: the single-clip document in cache frame numbers,
        without what every clip shares (schema_version, parameters: the top level's)."""
        document = self.cache_result(cache_frames).to_dict()
        document.pop("schema_version", None)
        document.pop("parameters", None)
        first, last = self.offset, self.offset + self.result.frame_count - 1
        return {"clip": self.clip, "period": self.period, "segment": self.segment, "clip_phase": self.clip_phase,
                "searched_frames": [first, last], **document}


def clip_stretches(timeline: Timeline, clip: str) -> list[tuple[int, int, int]]:
    """(segment index, first, last) pure cache frames (inclusive) of every segment of `clip`, in order."""
    return [(k, s.pure_first_frame, s.pure_last_frame) for k, s in enumerate(timeline.segments) if s.clip == clip]


def _loop_rank(result: CycleResult) -> tuple:
    """Order of loops cut from different stretches: within the quality bounds first, then by the score
    the search itself ranks by (pass-2 edge distance when it ran, else the pass-1 distance)."""
    winner = result.candidates[result.chosen]
    quality = result.closing.quality
    score = winner.edge_distance if winner.edge_distance is not None else winner.vertex_distance
    return (quality is not None and not quality.within_bounds, score)


def find_clip_loop(
    cloth: np.ndarray,
    cloth_faces: np.ndarray,
    timeline: Timeline,
    clip: str,
    params: CycleParams = CycleParams(),
    render_views: RenderViews | None = None,
    body: np.ndarray | None = None,
    body_faces: np.ndarray | None = None,
    body_normals: np.ndarray | None = None,
    progress: Progress | None = None,
) -> ClipLoop:
    """The best closed loop of `clip` over its pure stretches.

    cloth: (F, V, 3) float cache (F = timeline.total_frames); cloth_faces: (T, 3) int; body: (F, Vb, 3)
    posed at the timeline's clip frames (only the clip's pure frames are read) or None; body_normals:
    (F, Vb, 3) or None (find_cycle derives them from body_faces). Stretch ratios use the cache's first
    frame as the rest shape. progress: each stretch's find_cycle progress. Raises ValueError naming the
    clip when none of its stretches holds two periods plus the search's window.
    """
    period = timeline.period(clip)
    rest = np.asarray(cloth[0], dtype=np.float64)
    found: list[tuple[int, int, CycleResult]] = []
    reasons: list[str] = []
    for segment, first, last in clip_stretches(timeline, clip):
        rows = slice(first, last + 1)
        try:
            result = find_cycle(
                cloth[rows], cloth_faces, None if body is None else body[rows], body_faces, period, params, render_views,
                body_normals=None if body_normals is None else body_normals[rows], progress=progress,
                # A stretch from frame 0 holds the rest shape itself: find_cycle takes it in the frame it searches
                # in (the root's, when the body travels), as it does for a cache of one clip.
                rest_positions=None if first == 0 else rest, clip=clip, frame_offset=first,
            )
        except ValueError as error:
            reasons.append(f"cache frames {first}..{last}: {error}")
            continue
        found.append((segment, first, result))
    if not found:
        raise ValueError(f"clip {clip!r} ({period} frames): no pure stretch holds a loop ({'; '.join(reasons)})")
    segment, first, result = min(found, key=lambda item: _loop_rank(item[2]))
    phase = int(timeline.clip_frame[first + result.start_frame]) % period
    return ClipLoop(clip, period, segment, first, result, phase)


def find_clip_loops(
    cloth: np.ndarray,
    cloth_faces: np.ndarray,
    timeline: Timeline,
    params: CycleParams = CycleParams(),
    render_views: RenderViews | None = None,
    body: np.ndarray | None = None,
    body_faces: np.ndarray | None = None,
    body_normals: np.ndarray | None = None,
    progress: Progress | None = None,
) -> list[ClipLoop]:
    """find_clip_loop for every clip of the timeline, in order of first appearance."""
    cloth = np.asarray(cloth)
    if cloth.ndim != 3 or cloth.shape[0] != timeline.total_frames:
        raise ValueError(f"the timeline covers {timeline.total_frames} frames, the cloth cache has shape {cloth.shape}")
    return [find_clip_loop(cloth, cloth_faces, timeline, clip, params, render_views, body, body_faces, body_normals, progress)
            for clip in timeline.clips()]
