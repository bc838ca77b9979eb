"""The cyclical-cloth search (Dobbyn et al. 2006, section 3) from arrays to a closed loop.

    find_cycle(cloth, cloth_faces, body, body_faces, cycle_frames, params, render_views) -> CycleResult

1. Pass 1 (crowdbake.bake.cycle_search): a windowed position + velocity distance over all cloth vertices
   between frames one walk cycle apart; the best local minima become candidates.
2. Pass 2 (crowdbake.bake.edge_metric): each candidate's Fs and Fe are pictured from several viewpoints by
   the `render_views` callable (crowdbake.render.cloth_views.ClothViewRenderer in production, so this
   module stays free of GL and files); the summed edge distance picks the winner.
3. Closing (crowdbake.bake.loop_closing): none, the paper's linear blend, a Hermite correction, or (the
   default) a crossfade confined to the seam that restores edge lengths; penetration into the body is
   measured before and after, and what closing pushed in is pushed back out, smoothly in time. The loop's
   quality against the simulation (stretch, deviation, seam acceleration ratios) is measured; the candidates
   are closed best first, at wider crossfades and then further down pass 1's list, until a closing keeps
   loop_closing.QUALITY_BOUNDS. Where none does, the first closing tried is returned, flagged in
   cycle.json; whether a bake may keep it is the caller's decision (crowdbake.bake.bounds).

The result serialises to the cycle.json dictionary with `CycleResult.to_dict()`.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from crowdbake.bake import cycle_search, edge_metric, loop_closing

logger = logging.getLogger(__name__)

# The body's horizontal centroid moving by more than this fraction of the body's size between frames one
# cycle apart means the character travels (root motion): the search then works in the root's frame. A
# walk on the spot returns to the same pose each cycle, so its centroid moves by float noise only.
ROOT_MOTION_FRACTION = 0.01
ROOT_MOTION_MODES = ("auto", "remove", "keep")

# render_views(cloth_frames (N, V, 3), body_frames (N, Vb, 3) | None) -> (N, views, H, W) uint8
RenderViews = Callable[[np.ndarray, "np.ndarray | None"], np.ndarray]
# progress(stage, done, total): called as the search advances; for progress bars.
Progress = Callable[[str, int, int], None]

SCHEMA_VERSION = 1

# When no closing of the K best candidates keeps loop_closing.QUALITY_BOUNDS, the search looks this many
# times as far down pass 1's list (the next local minima, scored by pass 2 like the first K).
MORE_CANDIDATES_FACTOR = 3
# Crossfade half-widths tried, as multiples of the default (l / 6), where the default breaks a bound: a
# wider blend spreads the seam's correction over more frames (the blend's own acceleration falls with the
# square of its width) but moves frames further from the seam pass 1 judged. The widest stays within l / 2
# and within the frames searched either side of the cycle.
CROSSFADE_WIDTH_FACTORS = (1.0, 1.5, 2.0)


@dataclass(frozen=True)
class CycleParams:
    """Every knob of the search, recorded in cycle.json.

    settle_frames: first start frame considered; None = one walk cycle (shortened, with a warning, when
        the cache is too short for that).
    window, velocity_weight: pass-1 window k (odd, frames) and lambda (frames).
    max_candidates, threshold, min_separation: candidate picking (threshold in cache units; None = no
        threshold; min_separation None = half a cycle).
    max_cycle_count: also try gaps of 2 .. N walk cycles (1 = the paper's single cycle).
    views, image_size, elevation_deg: pass-2 pictures (used by whoever builds `render_views`).
    canny_low, canny_high, truncation_px: pass-2 edge metric.
    close, blend_frames, push_out: closing (see crowdbake.bake.loop_closing).
    root_motion: "auto" (remove it when the body travels), "remove", or "keep".
    """

    settle_frames: int | None = None
    window: int = cycle_search.DEFAULT_WINDOW
    velocity_weight: float = cycle_search.DEFAULT_VELOCITY_WEIGHT
    max_candidates: int = cycle_search.DEFAULT_MAX_CANDIDATES
    threshold: float | None = None
    min_separation: int | None = None
    max_cycle_count: int = 1
    views: int = 5
    image_size: int = 256
    elevation_deg: float = 15.0
    canny_low: float = edge_metric.DEFAULT_CANNY_LOW
    canny_high: float = edge_metric.DEFAULT_CANNY_HIGH
    truncation_px: float = edge_metric.DEFAULT_TRUNCATION_PX
    close: str = loop_closing.DEFAULT_CLOSE_METHOD
    blend_frames: int | None = None
    push_out: str = "new"
    root_motion: str = "auto"

    def validate(self) -> None:
        if self.close not in loop_closing.CLOSE_METHODS:
            raise ValueError(f"close must be one of {loop_closing.CLOSE_METHODS}, got {self.close!r}")
        if self.push_out not in loop_closing.PUSH_OUT_MODES:
            raise ValueError(f"push_out must be one of {loop_closing.PUSH_OUT_MODES}, got {self.push_out!r}")
        if self.root_motion not in ROOT_MOTION_MODES:
            raise ValueError(f"root_motion must be one of {ROOT_MOTION_MODES}, got {self.root_motion!r}")
        if self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"window must be a positive odd number of frames, got {self.window}")
        if self.max_candidates < 1:
            raise ValueError(f"max_candidates must be at least 1, got {self.max_candidates}")
        if self.views < 1 or self.image_size < 16:
            raise ValueError(f"need at least 1 view of at least 16 px, got {self.views} views of {self.image_size} px")
        if self.settle_frames is not None and self.settle_frames < 0:
            raise ValueError(f"settle_frames must be >= 0, got {self.settle_frames}")


@dataclass(frozen=True)
class Candidate:
    """One candidate cycle [start_frame, end_frame) with its pass-1 and pass-2 scores.

    vertex_distance: pass-1 D (cache units); edge_distance: pass-2 sum over views (pixels), None when
    pass 2 did not run; edge_distance_per_view: (views,) pixels.
    """

    start_frame: int
    end_frame: int
    cycle_count: int
    vertex_distance: float
    edge_distance: float | None = None
    edge_distance_per_view: tuple[float, ...] | None = None


@dataclass(frozen=True)
class ClosingAttempt:
    """One closing the search tried: the candidate [start_frame, end_frame), its blend width (the closing's
    blend_frames) and the quality bounds it broke (empty: kept them all)."""

    start_frame: int
    end_frame: int
    blend_frames: int | None
    exceeded: tuple[str, ...]


@dataclass
class CycleResult:
    """What the search found. `to_dict()` is the cycle.json content; arrays stay here for the report.

    start_frame, end_frame: the chosen Fs and Fe = Fs + cycle_frames (frames of the input cache).
    cycle_frames: frames in the loop; walk_cycle_frames: l; cycle_count = cycle_frames / l.
    candidates: best pass-1 first; chosen: index into candidates.
    curves: the pass-1 distance curves (one per gap).
    closing: the closed loop, its seam figures and penetration counts (closing.looped is the loop).
    winner_images: (2, views, H, W) uint8 pictures at Fs and Fe of the winner, None without pass 2.
    winner_edges: its edge comparison (edge images at Fs and Fe), None without pass 2.
    root_offsets: (F, 3) root positions removed before the search, None when the root stayed.
    timings: seconds per stage.
    closing_attempts: every closing tried, in order, until one kept the quality bounds (where none kept
        them, the first tried is the one chosen).
    """

    start_frame: int
    end_frame: int
    cycle_frames: int
    walk_cycle_frames: int
    cycle_count: int
    candidates: list[Candidate]
    chosen: int
    curves: list[cycle_search.DistanceCurve]
    closing: loop_closing.ClosedLoop
    params: CycleParams
    settle_frames: int
    frame_count: int
    vertex_count: int
    body_vertex_count: int | None
    winner_images: np.ndarray | None = None
    winner_edges: edge_metric.EdgeComparison | None = None
    root_offsets: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    closing_attempts: list[ClosingAttempt] = field(default_factory=list)

    @property
    def looped(self) -> np.ndarray:
        """(cycle_frames, V, 3) float32: the frames to play in a loop."""
        return self.closing.looped

    def to_dict(self) -> dict:
        """The cycle.json dictionary (JSON-ready: plain numbers and lists; non-finite numbers become None)."""
        closing = self.closing
        root = None
        if self.root_offsets is not None:
            per_cycle = self.root_offsets[self.end_frame] - self.root_offsets[self.start_frame]
            root = {"removed": True, "offset_per_loop": _floats(per_cycle)}
        return {
            "schema_version": SCHEMA_VERSION,
            "start_frame": self.start_frame,
            "end_frame": self.end_frame,
            "cycle_frames": self.cycle_frames,
            "walk_cycle_frames": self.walk_cycle_frames,
            "cycle_count": self.cycle_count,
            "input": {
                "frame_count": self.frame_count,
                "vertex_count": self.vertex_count,
                "body_vertex_count": self.body_vertex_count,
                "settle_frames": self.settle_frames,
            },
            "root_motion": root,
            "chosen_candidate": self.chosen,
            "selected_by": "edge_distance" if self.candidates[self.chosen].edge_distance is not None else "vertex_distance",
            "candidates": [
                {
                    "start_frame": c.start_frame,
                    "end_frame": c.end_frame,
                    "cycle_count": c.cycle_count,
                    "vertex_distance": _float(c.vertex_distance),
                    "edge_distance": _float(c.edge_distance),
                    "edge_distance_per_view": None if c.edge_distance_per_view is None else _floats(c.edge_distance_per_view),
                }
                for c in self.candidates
            ],
            "closing_attempts": [
                {"start_frame": a.start_frame, "end_frame": a.end_frame, "blend_frames": a.blend_frames, "exceeded": list(a.exceeded)}
                for a in self.closing_attempts
            ],
            "closing": {
                "method": closing.method,
                "blend_frames": closing.blend_frames,
                "push_out": closing.push_out,
                "pushed_vertices": closing.pushed_vertices,
                "quality": _quality_dict(closing.quality),
            },
            "seam": {
                "before": _seam_dict(closing.seam_before),
                "after": _seam_dict(closing.seam_after),
                "position_jump_ratio": _float(closing.seam_after.position_jump_ratio),
                "velocity_jump_ratio": _float(closing.seam_after.velocity_jump_ratio),
            },
            "penetration": {
                "per_frame_before": closing.penetrating_before.tolist(),
                "per_frame_closed": closing.penetrating_closed.tolist(),
                "per_frame_after": closing.penetrating_after.tolist(),
                "total_before": int(closing.penetrating_before.sum()),
                "total_after": int(closing.penetrating_after.sum()),
            },
            "vertex_distance_curves": [
                {
                    "cycle_count": curve.cycle_count,
                    "gap": curve.gap,
                    "first_start_frame": int(curve.start_frames[0]),
                    "distances": _floats(curve.distances),
                }
                for curve in self.curves
            ],
            "parameters": asdict(self.params),
            "timings_s": {name: round(seconds, 4) for name, seconds in self.timings.items()},
        }


def _float(value: float | None) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return float(value)


def _floats(values) -> list[float | None]:
    return [_float(float(v)) for v in np.asarray(values, dtype=np.float64).ravel()]


def _bounds_text(quality: loop_closing.LoopQuality) -> str:
    """'stretch_ratio 9.41 > 1.1, ...' for the ratios a closing broke."""
    return ", ".join(f"{name} {getattr(quality, name):.3g} > {loop_closing.QUALITY_BOUNDS[name]:g}" for name in quality.exceeded)


def _quality_dict(quality: loop_closing.LoopQuality | None) -> dict | None:
    """cycle.json's closing.quality: the three bounded ratios, their bounds, whether all hold, and the figures behind them."""
    if quality is None:
        return None
    figures = {name: _float(value) if isinstance(value, float) else value for name, value in asdict(quality).items()}
    figures["exceeded"] = list(quality.exceeded)
    figures["within_bounds"] = quality.within_bounds
    figures["bounds"] = dict(loop_closing.QUALITY_BOUNDS)
    # Both seam ratios: the bounded one divides by the larger reference (seam_acceleration_judged_against).
    figures["seam_acceleration_vs_median"] = _float(quality.seam_acceleration_vs_median)
    figures["seam_acceleration_vs_simulation"] = _float(quality.seam_acceleration_vs_simulation)
    figures["seam_acceleration_judged_against"] = quality.seam_acceleration_judged_against
    figures["seam_acceleration_note"] = quality.seam_acceleration_note()
    return figures


def _seam_dict(seam: loop_closing.SeamFigures) -> dict:
    return {name: _float(value) for name, value in asdict(seam).items()}


def _clip_name(clip: str | None) -> str:
    return f"clip {clip!r}" if clip is not None else "the cache"


def _loop_name(clip: str | None, frame_offset: int, start: int, end: int) -> str:
    """A candidate loop for messages: its clip and its frames counted in the whole cache."""
    return f"{_clip_name(clip)}, loop at cache frames [{start + frame_offset}, {end + frame_offset})"


def _best_first(candidates: list[Candidate], indices: range) -> list[int]:
    """Indices of candidates in the order the search closes them: the smallest edge distance first when pass 2
    ran, pass 1's order (the list's) breaking ties and ordering them without pass 2."""
    return sorted(indices, key=lambda i: (candidates[i].edge_distance or 0.0, i))


def _blend_widths(params: CycleParams, start: int, gap: int, frame_count: int) -> list[int | None]:
    """The blend widths to close the cycle [start, start + gap) with, in the order tried: the caller's
    (params.blend_frames, or None: the method's default) for every method but a crossfade of default width,
    which tries CROSSFADE_WIDTH_FACTORS times l / 6 within what the frames either side of the cycle allow."""
    if params.close != "crossfade" or params.blend_frames is not None:
        return [params.blend_frames]
    room = min(start, frame_count - 1 - (start + gap), gap // 2)
    default = loop_closing.default_crossfade_frames(gap)
    widths: list[int | None] = []
    for factor in CROSSFADE_WIDTH_FACTORS:
        width = max(1, min(int(round(default * factor)), room))
        if width not in widths:
            widths.append(width)
    return widths


def _first_within_bounds(candidates, indices, params, frame_count, close, where, attempts, closings):
    """Close candidates[i] for i in `indices` (best first) at each of its blend widths, narrowest first for
    every candidate before a wider one, until a closing keeps the quality bounds: (i, ClosedLoop), or None.
    Every closing tried goes to `attempts` (ClosingAttempt) and `closings` ((i, ClosedLoop)); a rejected
    one is logged at debug level (only the loop kept is the bake's business)."""
    widths = {i: _blend_widths(params, candidates[i].start_frame, candidates[i].end_frame - candidates[i].start_frame, frame_count)
              for i in indices}
    for rank in range(max(len(w) for w in widths.values())):
        for i in indices:
            if rank >= len(widths[i]):
                continue
            candidate = candidates[i]
            closing = close(candidate, widths[i][rank])
            exceeded = () if closing.quality is None else closing.quality.exceeded
            attempts.append(ClosingAttempt(candidate.start_frame, candidate.end_frame, closing.blend_frames, exceeded))
            closings.append((i, closing))
            if not exceeded:
                return i, closing
            logger.debug("%s: candidate rejected, its '%s' closing (blend %s frames) breaks %s",
                         where(candidate), params.close, closing.blend_frames, _bounds_text(closing.quality))
    return None


class _EdgePass:
    """Pass 2 for lists of candidates: each scored by the edge distance between its Fs and Fe pictures,
    the pictures kept for the winner's report."""

    def __init__(self, cloth, body, render_views: RenderViews, params: CycleParams, report: Progress):
        self.cloth, self.body, self.render_views, self.params, self.report = cloth, body, render_views, params, report
        self.images: dict[int, np.ndarray] = {}
        self.comparisons: dict[tuple[int, int], edge_metric.EdgeComparison] = {}

    def score(self, candidates: list[Candidate]) -> list[Candidate]:
        """The candidates with their edge distances, in their order."""
        frames = sorted(({c.start_frame for c in candidates} | {c.end_frame for c in candidates}) - set(self.images))
        self.report("pass 2", 0, len(candidates))
        if frames:
            images = np.asarray(self.render_views(self.cloth[frames], None if self.body is None else self.body[frames]))
            if images.ndim != 4 or images.shape[0] != len(frames) or images.dtype != np.uint8:
                raise ValueError(f"render_views returned {images.shape} {images.dtype}, expected ({len(frames)}, views, H, W) uint8")
            self.images.update(zip(frames, images))
        scored = []
        for i, c in enumerate(candidates):
            comparison = edge_metric.compare_views(self.images[c.start_frame], self.images[c.end_frame], self.params.canny_low,
                                                   self.params.canny_high, self.params.truncation_px)
            self.comparisons[(c.start_frame, c.end_frame)] = comparison
            scored.append(Candidate(c.start_frame, c.end_frame, c.cycle_count, c.vertex_distance, comparison.total,
                                    tuple(float(v) for v in comparison.per_view)))
            self.report("pass 2", i + 1, len(candidates))
        return scored

    def pictures(self, winner: Candidate) -> tuple[np.ndarray, edge_metric.EdgeComparison]:
        """(2, views, H, W) uint8 pictures at the winner's Fs and Fe, and its edge comparison."""
        return (np.stack([self.images[winner.start_frame], self.images[winner.end_frame]]),
                self.comparisons[(winner.start_frame, winner.end_frame)])


def estimate_root_offsets(body: np.ndarray) -> np.ndarray:
    """(F, 3) float64 root position per frame from the body: its horizontal (x, z) vertex centroid, y = 0.

    Y is up (glTF). Only translation is estimated: a character that turns is out of scope.
    """
    body = np.asarray(body, dtype=np.float64)
    offsets = body.mean(axis=1)
    offsets[:, 1] = 0.0
    return offsets


def has_root_motion(root_offsets: np.ndarray, cycle_frames: int, body_size: float) -> bool:
    """True when the root moves more than ROOT_MOTION_FRACTION of the body's size between frames a cycle apart."""
    if len(root_offsets) <= cycle_frames:
        return False
    travel = np.linalg.norm(root_offsets[cycle_frames:] - root_offsets[:-cycle_frames], axis=1)
    return bool(travel.max() > ROOT_MOTION_FRACTION * body_size)


def _validate_inputs(cloth, cloth_faces, body, body_faces, body_normals, cycle_frames):
    cloth = np.asarray(cloth)
    if cloth.ndim != 3 or cloth.shape[2] != 3 or cloth.shape[1] == 0:
        raise ValueError(f"cloth must be a (frames, vertices, 3) cache, got shape {cloth.shape}")
    if not np.isfinite(cloth).all():
        frame, vertex = np.argwhere(~np.isfinite(cloth))[0][:2]
        raise ValueError(f"cloth has NaN or infinity (frame {frame}, vertex {vertex})")
    cloth_faces = np.asarray(cloth_faces, dtype=np.int64)
    if cloth_faces.ndim != 2 or cloth_faces.shape[1] != 3:
        raise ValueError(f"cloth_faces must be (T, 3), got shape {cloth_faces.shape}")
    if cloth_faces.size and (cloth_faces.min() < 0 or cloth_faces.max() >= cloth.shape[1]):
        raise ValueError(f"cloth_faces index vertices outside the cache's {cloth.shape[1]} points")
    if int(cycle_frames) != cycle_frames or cycle_frames < 2:
        raise ValueError(f"cycle_frames must be an integer >= 2, got {cycle_frames}")
    if cloth.shape[0] < 2 * cycle_frames:
        raise ValueError(
            f"too few frames for two cycles: the cache has {cloth.shape[0]} frames, two cycles of {cycle_frames} need {2 * cycle_frames}"
        )
    if body is not None:
        body = np.asarray(body)
        if body.ndim != 3 or body.shape[2] != 3 or body.shape[1] == 0:
            raise ValueError(f"body must be a (frames, vertices, 3) cache, got shape {body.shape}")
        if body.shape[0] != cloth.shape[0]:
            raise ValueError(f"body has {body.shape[0]} frames but the cloth has {cloth.shape[0]}")
        if not np.isfinite(body).all():
            raise ValueError("body has NaN or infinity")
        if body_faces is None:
            raise ValueError("body_faces are required with a body")
        body_faces = np.asarray(body_faces, dtype=np.int64)
        if body_faces.ndim != 2 or body_faces.shape[1] != 3 or len(body_faces) == 0:
            raise ValueError(f"body_faces must be a non-empty (T, 3) array, got shape {body_faces.shape}")
        if body_faces.min() < 0 or body_faces.max() >= body.shape[1]:
            raise ValueError(f"body_faces index vertices outside the body's {body.shape[1]} points")
        if body_normals is not None and np.shape(body_normals) != body.shape:
            raise ValueError(f"body_normals must have the body's shape {body.shape}, got {np.shape(body_normals)}")
    return cloth, cloth_faces, body, body_faces


def find_cycle(
    cloth: np.ndarray,
    cloth_faces: np.ndarray,
    body: np.ndarray | None,
    body_faces: np.ndarray | None,
    cycle_frames: int,
    params: CycleParams = CycleParams(),
    render_views: RenderViews | None = None,
    body_normals: np.ndarray | None = None,
    progress: Progress | None = None,
    rest_positions: np.ndarray | None = None,
    clip: str | None = None,
    frame_offset: int = 0,
) -> CycleResult:
    """Search a long cloth cache for its best cycle and close it.

    cloth: (F, V, 3) float positions (cache units, Y up); cloth_faces: (T, 3) int into the V points.
    body, body_faces: the body over the same F frames, (F, Vb, 3) and (Tb, 3), or None (then no
        penetration figures and no root-motion estimate).
    cycle_frames: l, the walk cycle's length in frames; F must hold at least two cycles.
    render_views: pictures for pass 2 (see RenderViews); None skips pass 2 and the winner is the best
        pass-1 candidate.
    body_normals: (F, Vb, 3) unit outward normals; computed from body_faces when None.
    rest_positions: (V, 3) rest shape for the stretch ratio, default the cache's first frame (a part of a
        longer cache passes the whole cache's first frame).
    clip, frame_offset: for messages only, the clip searched and the cache frame of `cloth`'s first frame
        (a stretch of a longer cache), so that logs and errors name the clip and cache frames.
    The candidates are closed best first, each at the default blend and then wider crossfades, then
    MORE_CANDIDATES_FACTOR times as many candidates, until a closing keeps loop_closing.QUALITY_BOUNDS;
    where none does, the first closing tried is returned (its quality.exceeded says which bounds it breaks).
    Raises ValueError on bad shapes, NaN, too few frames, or when no candidate passes the threshold.
    """
    params.validate()
    cloth, cloth_faces, body, body_faces = _validate_inputs(cloth, cloth_faces, body, body_faces, body_normals, cycle_frames)
    cycle_frames = int(cycle_frames)
    frame_count = cloth.shape[0]
    timings: dict[str, float] = {}
    report = progress or (lambda stage, done, total: None)

    root_offsets = None
    if body is not None and params.root_motion != "keep":
        offsets = estimate_root_offsets(body)
        if params.root_motion == "remove" or has_root_motion(offsets, cycle_frames, loop_closing.body_size(body)):
            root_offsets = offsets
            logger.info("%s: the character travels: searching in the root's frame", _clip_name(clip))
    if root_offsets is not None:
        # The whole search, closing and output happen in the root's frame (a walk on the spot).
        cloth = (cloth - root_offsets[:, None, :]).astype(np.float32)
        body = body - root_offsets[:, None, :]

    settle = params.settle_frames
    if settle is None:
        half = params.window // 2
        latest = frame_count - cycle_frames - half - 2  # the last start frame whose window fits (see cycle_search)
        settle = min(cycle_frames, max(latest, 0))
        if settle < cycle_frames:
            logger.warning("%s, cache frames [%d, %d): settle-in shortened to %d frames", _clip_name(clip), frame_offset,
                           frame_offset + frame_count, settle)

    report("pass 1", 0, 1)
    started = time.perf_counter()
    vertex_candidates, curves = cycle_search.search_vertex_candidates(
        cloth,
        cycle_frames,
        window=params.window,
        velocity_weight=params.velocity_weight,
        settle_frames=settle,
        max_candidates=params.max_candidates,
        threshold=params.threshold,
        min_separation=params.min_separation,
        max_cycle_count=params.max_cycle_count,
    )
    timings["pass1"] = time.perf_counter() - started
    report("pass 1", 1, 1)
    if not vertex_candidates:
        best = curves[0]
        lowest = int(np.nanargmin(best.distances))
        raise ValueError(
            f"no candidate cycle under the threshold {params.threshold}: the lowest vertex distance is "
            f"{best.distances[lowest]:.6g} at cache frame {int(best.start_frames[lowest]) + frame_offset}"
        )
    candidates = [
        Candidate(c.start_frame, c.start_frame + c.gap, c.cycle_count, c.vertex_distance) for c in vertex_candidates
    ]
    edge_pass = _EdgePass(cloth, body, render_views, params, report) if render_views is not None else None
    if edge_pass is not None:
        started = time.perf_counter()
        candidates = edge_pass.score(candidates)
        timings["pass2"] = time.perf_counter() - started

    report("closing", 0, 1)
    started = time.perf_counter()

    def close(candidate: Candidate, width: int | None) -> loop_closing.ClosedLoop:
        return loop_closing.close_cycle(
            cloth, candidate.start_frame, candidate.end_frame - candidate.start_frame, params.close, body=body,
            body_normals=body_normals, body_faces=body_faces, blend_frames=width, push_out_mode=params.push_out,
            cloth_faces=cloth_faces, rest_positions=rest_positions,
        )

    def where(candidate: Candidate) -> str:
        return _loop_name(clip, frame_offset, candidate.start_frame, candidate.end_frame)

    attempts: list[ClosingAttempt] = []
    closings: list[tuple[int, loop_closing.ClosedLoop]] = []
    found = _first_within_bounds(candidates, _best_first(candidates, range(len(candidates))), params, frame_count, close, where,
                                 attempts, closings)
    if found is None and params.max_candidates * MORE_CANDIDATES_FACTOR > len(candidates):
        # None of the K best keeps the bounds: look further down pass 1's list, edge_pass as the first K were.
        more, _ = cycle_search.search_vertex_candidates(
            cloth, cycle_frames, window=params.window, velocity_weight=params.velocity_weight, settle_frames=settle,
            max_candidates=params.max_candidates * MORE_CANDIDATES_FACTOR, threshold=params.threshold,
            min_separation=params.min_separation, max_cycle_count=params.max_cycle_count,
        )
        known = {(c.start_frame, c.end_frame) for c in candidates}
        extra = [Candidate(c.start_frame, c.start_frame + c.gap, c.cycle_count, c.vertex_distance)
                 for c in more if (c.start_frame, c.start_frame + c.gap) not in known]
        if extra:
            logger.info("%s: no closing of the %d best candidate loops keeps the quality bounds; trying %d more",
                        _clip_name(clip), len(candidates), len(extra))
            if edge_pass is not None:
                extra = edge_pass.score(extra)
            first = len(candidates)
            candidates = candidates + extra
            found = _first_within_bounds(candidates, _best_first(candidates, range(first, len(candidates))), params, frame_count,
                                         close, where, attempts, closings)
    # Nothing within the bounds: the search's own first choice (the caller decides whether a bake may keep it).
    chosen, closing = found if found is not None else closings[0]
    timings["closing"] = time.perf_counter() - started
    report("closing", 1, 1)
    winner = candidates[chosen]
    gap = winner.end_frame - winner.start_frame
    logger.info(
        "%s: seam position jump %.3f -> %.3f", where(winner),
        closing.seam_before.position_jump_ratio, closing.seam_after.position_jump_ratio,
    )
    if params.close == "crossfade" and params.blend_frames is None and closing.blend_frames < loop_closing.default_crossfade_frames(gap):
        logger.info("%s: crossfade shortened to %d frames either side of the seam: the searched frames end at cache frame %d",
                       where(winner), closing.blend_frames, frame_offset + frame_count - 1)
    winner_images = winner_edges = None
    if edge_pass is not None:
        winner_images, winner_edges = edge_pass.pictures(winner)
    return CycleResult(
        start_frame=winner.start_frame,
        end_frame=winner.end_frame,
        cycle_frames=gap,
        walk_cycle_frames=cycle_frames,
        cycle_count=winner.cycle_count,
        candidates=candidates,
        chosen=chosen,
        curves=curves,
        closing=closing,
        params=params,
        settle_frames=settle,
        frame_count=frame_count,
        vertex_count=cloth.shape[1],
        body_vertex_count=None if body is None else body.shape[1],
        winner_images=winner_images,
        winner_edges=winner_edges,
        root_offsets=root_offsets,
        timings=timings,
        closing_attempts=attempts,
    )
