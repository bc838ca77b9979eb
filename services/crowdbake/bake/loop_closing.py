"""Closing the chosen cycle's seam, the seam's figures, and cloth-into-body penetration.

Dobbyn et al. 2006, section 3: "in certain cases, an extra linear blend step between Fe and Fs was needed
... it often resulted in the cloth intersecting with the human model". Three closings are offered:

- "none": the simulator's frames Fs .. Fe-1 as they are.
- "linear" (the paper's): over the last b frames of the cycle the cloth is cross-faded, with a weight
  rising linearly to 1, from its own frames towards the frames that lead into Fs one cycle earlier
  (x(Fs - l + i)); the last looped frame is then exactly the frame before Fs, so the seam is a real step
  of the simulation. Positions only are blended, so the ramp's start carries a small kink.
- "hermite": every frame of the cycle is corrected by a cubic Hermite curve that is zero at Fs and,
  at Fe, equals the position mismatch D = x(Fe) - x(Fs) with slope equal to the velocity mismatch
  d = x'(Fe) - x'(Fs):  x'(t) = x(t) - [D (3u^2 - 2u^3) + d l (u^3 - u^2)], u = t / l (with d scaled by
  1 / (1 - 1/(2l)) so that the velocities close exactly on frames, not only in the continuous limit).
  It closes position and velocity and spreads the correction thinly over the whole cycle instead of a
  few frames. On real cloth that is its weakness: the correction peaks mid-loop, far from any frame the
  simulator made, and stretches the cloth (on a Blender skirt, edges stretched 9x the simulation's).
- "crossfade" (the default): a two-sided crossfade confined to `h` frames either side of the seam. Around
  the seam two simulated trajectories exist, the end of the cycle A(t) = x(Fe + t) and the start shifted
  by one cycle B(t) = x(Fs + t), t = -h .. h; the loop plays (1 - s(t)) A(t) + s(t) B(t) with s a quintic
  smoothstep from 0 at t = -h to 1 at t = h (zero slope and curvature at both ends, so the window joins
  the untouched frames without a kink). The seam falls mid-blend, every frame stays between two frames
  the simulator made (at most half the local gap from its own), and nothing outside the window moves.
  Averaging two differently folded shapes shortens edges, so a few Jacobi iterations of position-based
  distance constraints (Mueller et al. 2007) then bring every edge back to the blend of its two simulated
  lengths; vertices that A and B agree on (pins) stay put.

Whatever the closing, cloth it pushed into the body is pushed back out smoothly in time
(crowdbake.bake.penetration), and the result is measured against the simulation
(crowdbake.bake.loop_quality); `close_cycle` does all three.

Trajectories here run over frames Fs-1 .. Fe+1 (l + 3 frames: Fe and a frame either side are kept so the
seam can be measured); the looped cache is Fs .. Fe-1. Velocities are per frame (central differences).
Pure numpy/scipy; no I/O.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import sparse

# The seam figures, quality ratios and push-out live in their own modules; their names are re-exported
# here (__all__) because callers of close_cycle read them off crowdbake.bake.loop_closing.
from crowdbake.bake.loop_quality import (
    MIN_REFERENCE_STRAIN,
    QUALITY_BOUNDS,
    STILL_STEP,
    LoopQuality,
    SeamFigures,
    loop_quality,
    mean_edge_strain,
    seam_figures,
)
from crowdbake.bake.mesh import as_point_frames, edge_lengths, unique_edges
from crowdbake.bake.penetration import (
    MAX_DEPTH_FRACTION,
    PENETRATION_TOLERANCE_FRACTION,
    PUSH_OUT_ITERATIONS,
    PUSH_OUT_MODES,
    PUSH_OUT_REACH_FRACTION,
    BodyFrames,
    PenetrationSettings,
    body_size,
    penetration_mask,
    push_out,
    raised_cosine,
    smooth_push_out,
)
from crowdbake.geometry import vertex_normals

logger = logging.getLogger(__name__)

__all__ = [
    "CLOSE_METHODS",
    "DEFAULT_CLOSE_METHOD",
    "EDGE_PROJECTION_ITERATIONS",
    "EDGE_PROJECTION_RELAXATION",
    "PINNED_GAP_FRACTION",
    "ClosedLoop",
    "close_cycle",
    "close_loop",
    "crossfade_blend",
    "crossfade_weights",
    "default_blend_frames",
    "default_crossfade_frames",
    "looped_frames",
    "restore_edge_lengths",
    "smootherstep",
    "MIN_REFERENCE_STRAIN",
    "QUALITY_BOUNDS",
    "STILL_STEP",
    "LoopQuality",
    "SeamFigures",
    "loop_quality",
    "mean_edge_strain",
    "seam_figures",
    "edge_lengths",
    "unique_edges",
    "vertex_normals",
    "MAX_DEPTH_FRACTION",
    "PENETRATION_TOLERANCE_FRACTION",
    "PUSH_OUT_ITERATIONS",
    "PUSH_OUT_MODES",
    "PUSH_OUT_REACH_FRACTION",
    "BodyFrames",
    "PenetrationSettings",
    "body_size",
    "penetration_mask",
    "push_out",
    "raised_cosine",
    "smooth_push_out",
]

CLOSE_METHODS = ("none", "linear", "hermite", "crossfade")
# The closing that keeps the loop nearest the simulation (see the module docstring and docs/cycle.md).
DEFAULT_CLOSE_METHOD = "crossfade"
# Jacobi iterations of the crossfade's edge-length restoration, and their over-relaxation. The blend
# starts within a few percent of the target lengths, so averaged Jacobi sweeps (relaxed by 1.5, the
# value Macklin et al. 2014 recommend for averaged constraint projection) bring the mean strain back to
# the simulation's on a 4,000-vertex skirt (measured by services/benchmarks/bench_closing.py); 80 rather
# than 40 because each frame starts from the frame before's correction (_restore_in_time), which 40 sweeps
# leave partly undone (robot_clips' first Walking loop: stretch ratio 1.096 with 40, 1.062 with 80).
EDGE_PROJECTION_ITERATIONS = 80
EDGE_PROJECTION_RELAXATION = 1.5
# A vertex whose two blended frames lie closer than this fraction of the seam's RMS gap is treated as
# pinned by the edge restoration: a waistband that follows the body is the same in A and B.
PINNED_GAP_FRACTION = 1e-3


def default_blend_frames(cycle_frames: int) -> int:
    """The linear blend's default length: a quarter of the cycle, at least 2 frames."""
    return max(2, cycle_frames // 4)


def default_crossfade_frames(cycle_frames: int) -> int:
    """The crossfade's default half-width h (frames either side of the seam): l / 6, at least 2, at most l / 2.

    Long enough that the blend weight's curvature times the seam gap stays under the cloth's own
    acceleration, short enough that the window stays near the seam the search picked (pass 1 judged
    only the k frames around it).
    """
    return max(1, min(cycle_frames // 2, max(2, cycle_frames // 6)))


def smootherstep(u: np.ndarray) -> np.ndarray:
    """Quintic ease 6u^5 - 15u^4 + 10u^3 of u clipped to [0, 1]: 0 -> 0, 1 -> 1, zero slope and curvature at both."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    return u**3 * (u * (6.0 * u - 15.0) + 10.0)


def crossfade_weights(half_width: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame offsets t = -h .. h-1 from the seam and the weight s(t) of the cycle's start B: ((2h,), (2h,)).

    s(-h) = 0 and s(h) = 1 (frames Fe - h and Fs + h keep their simulated positions); s(t) + s(-t) = 1.
    """
    if half_width < 1:
        raise ValueError(f"crossfade_weights: half_width must be at least 1, got {half_width}")
    offsets = np.arange(-half_width, half_width)
    return offsets, smootherstep((offsets + half_width) / (2.0 * half_width))



def restore_edge_lengths(
    points: np.ndarray,
    edges: np.ndarray,
    target: np.ndarray,
    movable: np.ndarray,
    iterations: int = EDGE_PROJECTION_ITERATIONS,
    relaxation: float = EDGE_PROJECTION_RELAXATION,
) -> np.ndarray:
    """Move vertices so edges approach their target lengths: averaged Jacobi distance-constraint projection.

    points: (N, V, 3) frames, each solved on its own (all at once, vectorised); edges: (E, 2) int;
    target: (N, E) lengths (cache units); movable: (N, V) bool, False for vertices that must stay put.
    Every sweep projects each edge's constraint |x_j - x_i| = target, splitting the correction between
    its movable ends, and moves each vertex by the mean of its edges' corrections times `relaxation`
    (Macklin et al. 2014, averaged Jacobi). Returns (N, V, 3) float64.
    """
    x = np.array(points, dtype=np.float64)
    frame_count, vertex_count, _ = x.shape
    edges = np.asarray(edges, dtype=np.int64)
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (frame_count, len(edges)) or np.shape(movable) != (frame_count, vertex_count):
        raise ValueError(
            f"restore_edge_lengths: target {target.shape} and movable {np.shape(movable)} must be "
            f"({frame_count}, {len(edges)}) and ({frame_count}, {vertex_count})"
        )
    if len(edges) == 0 or iterations < 1:
        return x
    mass = np.asarray(movable, dtype=np.float64)  # inverse masses: 1 movable, 0 fixed
    w_i, w_j = mass[:, edges[:, 0]], mass[:, edges[:, 1]]
    total = w_i + w_j
    share_i = np.divide(w_i, total, out=np.zeros_like(total), where=total > 0)[..., None]
    share_j = np.divide(w_j, total, out=np.zeros_like(total), where=total > 0)[..., None]
    # Scatter matrices: one sparse product sums every frame's edge corrections onto their vertices.
    columns = np.arange(len(edges))
    ones = np.ones(len(edges))
    scatter_i = sparse.csr_matrix((ones, (edges[:, 0], columns)), shape=(vertex_count, len(edges)))
    scatter_j = sparse.csr_matrix((ones, (edges[:, 1], columns)), shape=(vertex_count, len(edges)))
    degree = np.maximum(np.bincount(edges.ravel(), minlength=vertex_count), 1).astype(np.float64)
    step_scale = (relaxation / degree)[None, :, None]

    def gather(per_edge: np.ndarray, scatter: sparse.csr_matrix) -> np.ndarray:
        stacked = per_edge.transpose(1, 0, 2).reshape(len(edges), -1)  # (E, N * 3)
        return (scatter @ stacked).reshape(vertex_count, frame_count, 3).transpose(1, 0, 2)

    for _ in range(iterations):
        delta = x[:, edges[:, 1]] - x[:, edges[:, 0]]
        length = np.sqrt(np.einsum("nej,nej->ne", delta, delta))
        error = delta * (1.0 - target / np.maximum(length, STILL_STEP))[..., None]  # what closes the gap
        x += step_scale * (gather(share_i * error, scatter_i) - gather(share_j * error, scatter_j))
    return x


# The cloth round a pushed vertex follows the push this many edges out, so a push lifts a patch of cloth
# instead of stretching the edges of one vertex; pins and the rest of the garment stay where they are.
PUSH_NEIGHBOUR_RINGS = 3


def edge_rings(seed: np.ndarray, edges: np.ndarray, rings: int) -> np.ndarray:
    """(N, V) bool: vertices within `rings` edges of a True vertex of seed (N, V), frame by frame; edges (E, 2)."""
    vertex_count = seed.shape[1]
    adjacency = sparse.csr_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                                  shape=(vertex_count, vertex_count))
    reached = np.asarray(seed, dtype=bool)
    for _ in range(rings):
        reached = reached | (adjacency @ reached.T.astype(np.float64)).T.astype(bool)
    return reached


def carry_push_to_neighbours(before: np.ndarray, pushed: np.ndarray, moved: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Restore the edge lengths a push-out changed by moving the pushed vertices' neighbours with them.

    before, pushed: (N, V, 3) frames before and after the push; moved: (N, V) bool, the vertices pushed;
    edges: (E, 2). The pushed vertices stay where the push put them (outside the body); vertices within
    PUSH_NEIGHBOUR_RINGS edges of them move to give their edges back the lengths they had before the
    push (restore_edge_lengths); every other vertex stays put. Returns (N, V, 3) float64.
    """
    movable = edge_rings(moved, edges, PUSH_NEIGHBOUR_RINGS) & ~moved
    return restore_edge_lengths(pushed, edges, edge_lengths(before, edges), movable)


def close_loop(
    points: np.ndarray,
    start: int,
    cycle_frames: int,
    method: str,
    blend_frames: int | None = None,
    edges: np.ndarray | None = None,
) -> np.ndarray:
    """The closed trajectory over frames Fs-1 .. Fe+1: (cycle_frames + 3, V, 3) float64.

    Row 1 + i is frame Fs + i; rows 1 .. l are the loop (see `looped_frames`), row l + 1 is the closed Fe
    (equal to row 1 once the seam is closed), and rows 0 and l + 2 carry each method's own continuation
    either side, so central velocities at Fs and Fe are defined for the seam figures.

    points: (F, V, 3) cache; start: Fs; cycle_frames: l (Fe = Fs + l); method: one of CLOSE_METHODS;
    blend_frames: b for "linear" (default `default_blend_frames(l)`), which needs Fs >= b; for "crossfade"
    the half-width h (default `default_crossfade_frames(l)`, at most l / 2), which needs Fs >= h and
    Fe + h < F. edges: (E, 2) cloth edges for the crossfade's edge-length restoration (None skips it).
    Every method needs Fs >= 1 and Fe + 1 < F.
    """
    points = as_point_frames(points, "close_loop", dtype=None)
    frame_count = points.shape[0]
    end = start + cycle_frames
    if method not in CLOSE_METHODS:
        raise ValueError(f"close_loop: method must be one of {CLOSE_METHODS}, got {method!r}")
    if cycle_frames < 2 or start < 1 or end + 1 >= frame_count:
        raise ValueError(
            f"close_loop: the cycle [{start}, {end}] with a frame either side does not fit a cache of {frame_count} frames"
        )
    raw = points[start - 1 : end + 2].astype(np.float64)
    index = np.arange(-1, cycle_frames + 2)  # frame offset from Fs of each row
    if method == "none":
        return raw
    if method == "linear":
        blend = default_blend_frames(cycle_frames) if blend_frames is None else int(blend_frames)
        if not 1 <= blend <= cycle_frames:
            raise ValueError(f"close_loop: blend_frames must be in [1, {cycle_frames}], got {blend}")
        if start < blend:
            raise ValueError(f"close_loop: a {blend}-frame linear blend needs Fs >= {blend}, got Fs = {start}")
        # Weight 1/b on the first blended frame (i = l - b), 1 from the last looped frame (i = l - 1) on:
        # from there the trajectory is the previous cycle's lead-in, x(Fs - l + i), which flows into Fs.
        weight = np.clip((index - (cycle_frames - blend) + 1) / blend, 0.0, 1.0)
        active = np.flatnonzero(weight > 0)
        lead_in = points[start - cycle_frames + index[active]].astype(np.float64)  # earliest: Fs - b >= 0
        w = weight[active][:, None, None]
        blended = raw.copy()
        blended[active] = (1.0 - w) * raw[active] + w * lead_in
        return blended
    if method == "crossfade":
        return _crossfade(points, start, cycle_frames, blend_frames, edges)
    # hermite: C(i) = D h(u) + d' l g(u), u = i / l, h = 3u^2 - 2u^3, g = u^3 - u^2; C = 0 before Fs and
    # continues along its end slope, D + d' (i - l), after Fe. The continuous curve would take d' = d; on
    # frames, the central differences around Fs and Fe see C(1) and C(l - 1), and with h(e) + h(1 - e) = 1
    # and l (g(e) + g(1 - e)) = 1/l - 1 (e = 1/l) the closed velocity jump comes out as d' (1 - 1/(2l)) - d.
    # Scaling d' = d / (1 - 1/(2l)) makes it exactly 0 on frames.
    position_jump = raw[-2] - raw[1]
    velocity_jump = 0.5 * (raw[-1] - raw[-3]) - 0.5 * (raw[2] - raw[0])
    end_slope = velocity_jump / (1.0 - 0.5 / cycle_frames)
    u = np.clip(index / cycle_frames, 0.0, 1.0)[:, None, None]
    correction = position_jump[None] * (3 * u**2 - 2 * u**3) + end_slope[None] * cycle_frames * (u**3 - u**2)
    correction[-1] = position_jump + end_slope
    return raw - correction


def _crossfade(
    points: np.ndarray, start: int, cycle_frames: int, half_width: int | None, edges: np.ndarray | None
) -> np.ndarray:
    """The "crossfade" closing of close_loop (see the module docstring): (l + 3, V, 3) float64."""
    frame_count = points.shape[0]
    end = start + cycle_frames
    if half_width is None:
        # The default shrinks to what the cache holds either side of the cycle (a cycle found near the
        # cache's end still closes); a half-width the caller chose is kept or refused.
        half = min(default_crossfade_frames(cycle_frames), start, frame_count - 1 - end)
        if half < default_crossfade_frames(cycle_frames):
            logger.warning("the crossfade of the cycle [%d, %d) is shortened to %d frames either side of the seam: the cache "
                           "holds frames 0..%d", start, end, half, frame_count - 1)
    else:
        half = int(half_width)
    if not 1 <= half <= cycle_frames // 2:
        raise ValueError(f"close_loop: the crossfade half-width must be in [1, {cycle_frames // 2}], got {half}")
    if start < half or end + half >= frame_count:
        raise ValueError(
            f"close_loop: a crossfade of {half} frames either side of the seam needs Fs >= {half} and "
            f"Fe + {half} < {frame_count} frames, got Fs = {start}, Fe = {end}"
        )
    offsets, weight = crossfade_weights(half)
    end_side = points[end + offsets].astype(np.float64)  # A(t) = x(Fe + t)
    start_side = points[start + offsets].astype(np.float64)  # B(t) = x(Fs + t)
    blended = crossfade_blend(end_side, start_side, weight, edges)
    loop = points[start:end].astype(np.float64)
    before_seam = offsets < 0
    loop[cycle_frames + offsets[before_seam]] = blended[before_seam]  # frames Fe - h .. Fe - 1
    loop[offsets[~before_seam]] = blended[~before_seam]  # frames Fs .. Fs + h - 1
    # The loop is now periodic: the frame before Fs is the last looped frame, Fe is Fs, Fe + 1 is Fs + 1.
    return np.concatenate([loop[-1:], loop, loop[:2]])


def crossfade_blend(leaving: np.ndarray, arriving: np.ndarray, weight: np.ndarray, edges: np.ndarray | None) -> np.ndarray:
    """(1 - s) A + s B frame by frame, then edge lengths restored to the blend of A's and B's, each frame's
    restoration started from the frame before's (_restore_in_time): (N, V, 3) float64.

    leaving: A, (N, V, 3) float64, the trajectory faded out; arriving: B, the same shape, faded in;
    weight: s, (N,) in [0, 1]; edges: (E, 2) cloth edges, or None to skip the restoration. Vertices
    where A and B agree (pins) stay put. The loop's crossfade and a transition's joins
    (crowdbake.bake.transitions) blend alike.
    """
    w = weight[:, None, None]
    blended = (1.0 - w) * leaving + w * arriving
    if edges is not None and len(edges):
        edges = np.asarray(edges, dtype=np.int64)
        target = (1.0 - weight[:, None]) * edge_lengths(leaving, edges) + weight[:, None] * edge_lengths(arriving, edges)
        gap = np.sqrt(np.sum(np.square(arriving - leaving), axis=-1))  # (N, V)
        movable = gap > PINNED_GAP_FRACTION * max(float(np.sqrt(np.mean(np.square(gap)))), STILL_STEP)
        blended = _restore_in_time(blended, edges, target, movable)
    return blended


def _restore_in_time(blended: np.ndarray, edges: np.ndarray, target: np.ndarray, movable: np.ndarray) -> np.ndarray:
    """restore_edge_lengths frame after frame, each frame started from its blend plus the correction of the
    frame before: (N, V, 3) float64 from blended (N, V, 3), target (N, E), movable (N, V).

    Averaging two differently folded shapes leaves slack that the projection takes up by bulging the cloth
    out; solved apart, neighbouring frames may bulge different ways, a kink in time that the seam
    acceleration reads (7.4 x its bound's reference at a transition of the clips sample, 4 cm between the
    shapes blended). Started from the frame before's bulge, every frame keeps it.
    """
    restored = np.empty_like(blended)
    correction = np.zeros_like(blended[0])
    for frame in range(len(blended)):
        start = blended[frame] + np.where(movable[frame][:, None], correction, 0.0)
        restored[frame] = restore_edge_lengths(start[None], edges, target[frame : frame + 1], movable[frame : frame + 1])[0]
        correction = restored[frame] - blended[frame]
    return restored


def looped_frames(trajectory: np.ndarray) -> np.ndarray:
    """The loop (l, V, 3) inside a (l + 3, V, 3) trajectory from close_loop: frames Fs .. Fe-1."""
    return trajectory[1:-2]


@dataclass(frozen=True)
class ClosedLoop:
    """The result of closing one cycle.

    looped: (l, V, 3) float32, the frames to play in a loop.
    method, blend_frames: the closing used (blend_frames: the linear blend's b or the crossfade's half-width
        h; None for the others).
    seam_before, seam_after: seam figures of the raw cycle and of the closed (and pushed-out) one.
    penetrating_before, penetrating_closed, penetrating_after: (l,) int64 penetrating cloth vertices per
        looped frame for the raw cycle, after closing, and after the push-out.
    pushed_vertices: how many (frame, vertex) pairs the push-out moved (the frames it eases in and out included).
    quality: the loop against the simulation (LoopQuality); quality.exceeded names the bounds it breaks.
    """

    looped: np.ndarray
    method: str
    blend_frames: int | None
    push_out: str
    seam_before: SeamFigures
    seam_after: SeamFigures
    penetrating_before: np.ndarray
    penetrating_closed: np.ndarray
    penetrating_after: np.ndarray
    pushed_vertices: int
    quality: LoopQuality | None = None


def _blend_frames_used(method: str, cycle_frames: int, blend_frames: int | None, start: int, frame_count: int) -> int | None:
    if method == "linear":
        return default_blend_frames(cycle_frames) if blend_frames is None else int(blend_frames)
    if method == "crossfade":
        if blend_frames is None:
            return min(default_crossfade_frames(cycle_frames), start, frame_count - 1 - start - cycle_frames)
        return int(blend_frames)
    return None


def close_cycle(
    cloth: np.ndarray,
    start: int,
    cycle_frames: int,
    method: str,
    body: np.ndarray | None = None,
    body_normals: np.ndarray | None = None,
    body_faces: np.ndarray | None = None,
    blend_frames: int | None = None,
    push_out_mode: str = "new",
    settings: PenetrationSettings | None = None,
    cloth_faces: np.ndarray | None = None,
    rest_positions: np.ndarray | None = None,
) -> ClosedLoop:
    """Close the cycle [start, start + cycle_frames) of a cloth cache and measure what that did.

    cloth: (F, V, 3); body: (F, Vb, 3) over the same frames, or None to skip penetration; body_normals:
    (F, Vb, 3) unit outward normals, or None to compute them from body_faces (T, 3) for the cycle's frames.
    push_out_mode: "new" moves back out only the vertices that penetrate after closing and were outside the
    body in every raw frame of the cycle (so an unclosed loop is exactly the simulator's output), "all"
    every penetrating vertex,
    "none" nothing; pushes ease in and out over time (smooth_push_out). settings: penetration tolerances,
    default PenetrationSettings.for_body(body).
    cloth_faces: (T, 3) cloth triangles: the crossfade restores edge lengths along their edges, and the
    quality figures gain the stretch ratio; rest_positions: (V, 3) for the rest edge lengths, default the
    cache's first frame (a simulator starts from the rest shape).
    """
    if push_out_mode not in PUSH_OUT_MODES:
        raise ValueError(f"close_cycle: push_out_mode must be one of {PUSH_OUT_MODES}, got {push_out_mode!r}")
    edges = None if cloth_faces is None else unique_edges(cloth_faces)
    if edges is not None and len(edges) and edges.max() >= np.shape(cloth)[1]:
        raise ValueError(f"close_cycle: cloth_faces index vertices outside the cache's {np.shape(cloth)[1]} points")
    raw = close_loop(cloth, start, cycle_frames, "none")
    closed = close_loop(cloth, start, cycle_frames, method, blend_frames, edges)
    loop = slice(1, cycle_frames + 1)  # rows of the looped frames Fs .. Fe-1
    if body is None:
        zero = np.zeros(cycle_frames, dtype=np.int64)
        final, pushed_count = closed, 0
        before = closed_count = after = zero
    else:
        body = as_point_frames(body, "close_cycle body", dtype=None)
        if body.shape[0] != np.asarray(cloth).shape[0]:
            raise ValueError(f"close_cycle: body has {body.shape[0]} frames, cloth {np.asarray(cloth).shape[0]}")
        rows = slice(start, start + cycle_frames)  # the looped frames Fs .. Fe-1
        if body_normals is not None:
            normals = np.asarray(body_normals)[rows]
        elif body_faces is not None:
            normals = vertex_normals(body[rows], body_faces)
        else:
            raise ValueError("close_cycle: a body needs body_normals or body_faces")
        settings = settings or PenetrationSettings.for_body(body)
        frames_of_body = BodyFrames(body[rows], normals)
        mask_before = penetration_mask(raw[loop], frames_of_body, settings)
        mask_closed = penetration_mask(closed[loop], frames_of_body, settings)
        if push_out_mode == "none":
            pushed_loop, moved = closed[loop], np.zeros_like(mask_closed)
        else:
            # A vertex the simulation itself left behind a body face in some frame of the cycle is where the
            # solver accepts it: open, single-sided meshes (a robot's 14 shells) hold cloth behind a face
            # all along, and blending such a vertex between two raw frames is no new penetration. Pushing
            # it to the face's front would stretch the cloth (1.12-1.40 on robot_clips' loops).
            allowed = mask_closed & ~mask_before.any(axis=0)[None, :] if push_out_mode == "new" else None
            reach = max(2, round(PUSH_OUT_REACH_FRACTION * cycle_frames))
            pushed_loop, moved = smooth_push_out(closed[loop], frames_of_body, settings, only=allowed, reach=reach)
            if edges is not None and len(edges) and moved.any():
                pushed_loop = carry_push_to_neighbours(closed[loop], pushed_loop, moved, edges)
        mask_after = penetration_mask(pushed_loop, frames_of_body, settings) if moved.any() else mask_closed
        final = closed.copy()
        final[loop] = pushed_loop
        # The rows either side of the loop follow the push of the looped frames they continue into.
        displacement = pushed_loop - closed[loop]
        final[0] += displacement[-1]
        final[-2] += displacement[0]
        final[-1] += displacement[1]
        before, closed_count, after = mask_before.sum(axis=1), mask_closed.sum(axis=1), mask_after.sum(axis=1)
        pushed_count = int(moved.sum())
    rest_lengths = None
    if edges is not None:
        rest = np.asarray(cloth[0] if rest_positions is None else rest_positions, dtype=np.float64)
        if rest.shape != np.shape(cloth)[1:]:
            raise ValueError(f"close_cycle: rest_positions must be {np.shape(cloth)[1:]}, got {rest.shape}")
        rest_lengths = edge_lengths(rest, edges)
    looped = looped_frames(final)
    quality = loop_quality(raw, looped, edges, rest_lengths)
    return ClosedLoop(
        looped=looped.astype(np.float32),
        method=method,
        blend_frames=_blend_frames_used(method, cycle_frames, blend_frames, start, np.shape(cloth)[0]),
        push_out=push_out_mode,
        seam_before=seam_figures(raw),
        seam_after=seam_figures(final),
        penetrating_before=np.asarray(before, dtype=np.int64),
        penetrating_closed=np.asarray(closed_count, dtype=np.int64),
        penetrating_after=np.asarray(after, dtype=np.int64),
        pushed_vertices=pushed_count,
        quality=quality,
    )
