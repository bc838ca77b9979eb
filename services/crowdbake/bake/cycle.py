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
   quality against the simulation (stretch, deviation, seam acceleration ratios) is measured and a closing
   that breaks loop_closing.QUALITY_BOUNDS is logged as a warning and flagged in cycle.json.

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
            logger.info("the character travels: searching in the root's frame")
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
            logger.warning("cache of %d frames: settle-in shortened to %d frames", frame_count, settle)

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
            f"{best.distances[lowest]:.6g} at frame {int(best.start_frames[lowest])}"
        )
    candidates = [
        Candidate(c.start_frame, c.start_frame + c.gap, c.cycle_count, c.vertex_distance) for c in vertex_candidates
    ]

    winner_images = None
    winner_edges = None
    chosen = 0
    if render_views is not None:
        started = time.perf_counter()
        frames = sorted({c.start_frame for c in candidates} | {c.end_frame for c in candidates})
        row = {frame: i for i, frame in enumerate(frames)}
        report("pass 2", 0, len(candidates))
        images = render_views(cloth[frames], None if body is None else body[frames])
        images = np.asarray(images)
        if images.ndim != 4 or images.shape[0] != len(frames) or images.dtype != np.uint8:
            raise ValueError(f"render_views returned {images.shape} {images.dtype}, expected ({len(frames)}, views, H, W) uint8")
        comparisons = []
        for i, c in enumerate(candidates):
            comparison = edge_metric.compare_views(
                images[row[c.start_frame]], images[row[c.end_frame]], params.canny_low, params.canny_high, params.truncation_px
            )
            comparisons.append(comparison)
            candidates[i] = Candidate(
                c.start_frame, c.end_frame, c.cycle_count, c.vertex_distance,
                comparison.total, tuple(float(v) for v in comparison.per_view),
            )
            report("pass 2", i + 1, len(candidates))
        # Smallest edge distance wins; the pass-1 order (the list's order) breaks ties.
        chosen = min(range(len(candidates)), key=lambda i: (candidates[i].edge_distance, i))
        winner = candidates[chosen]
        winner_images = np.stack([images[row[winner.start_frame]], images[row[winner.end_frame]]])
        winner_edges = comparisons[chosen]
        timings["pass2"] = time.perf_counter() - started

    winner = candidates[chosen]
    gap = winner.end_frame - winner.start_frame
    report("closing", 0, 1)
    started = time.perf_counter()
    closing = loop_closing.close_cycle(
        cloth, winner.start_frame, gap, params.close, body=body, body_normals=body_normals, body_faces=body_faces,
        blend_frames=params.blend_frames, push_out_mode=params.push_out, cloth_faces=cloth_faces,
        rest_positions=rest_positions,
    )
    timings["closing"] = time.perf_counter() - started
    report("closing", 1, 1)
    logger.info(
        "cycle [%d, %d): seam position jump %.3f -> %.3f",
        winner.start_frame, winner.end_frame, closing.seam_before.position_jump_ratio, closing.seam_after.position_jump_ratio,
    )
    if closing.quality is not None and closing.quality.exceeded:
        logger.warning(
            "the '%s' closing of [%d, %d) breaks its quality bounds: %s",
            params.close, winner.start_frame, winner.end_frame, _bounds_text(closing.quality),
        )
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
    )
