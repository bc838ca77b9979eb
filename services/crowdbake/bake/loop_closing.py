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

Whatever the closing, cloth it pushed into the body is pushed back out smoothly in time: the depth to
remove is spread over a few frames either side with a raised-cosine envelope (a max-convolution, so
every penetrating frame still gets its full push), instead of a per-frame jump that would show as a spike
in acceleration.

Trajectories here run over frames Fs-1 .. Fe+1 (l + 3 frames: Fe and a frame either side are kept so the
seam can be measured); the looped cache is Fs .. Fe-1. Velocities are per frame (central differences).

Penetration is measured against the body given as arrays: for each cloth vertex the nearest body vertex
(a k-d tree per frame) and the sign of the offset along that vertex's normal. Pure numpy/scipy; no I/O.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

logger = logging.getLogger(__name__)

CLOSE_METHODS = ("none", "linear", "hermite", "crossfade")
# The closing that keeps the loop nearest the simulation (see the module docstring and docs/cycle.md).
DEFAULT_CLOSE_METHOD = "crossfade"
PUSH_OUT_MODES = ("none", "new", "all")

# A cloth vertex counts as inside the body only when it lies more than this fraction of the body's size
# (its first frame's bounding-box diagonal) behind the nearest body vertex's tangent plane. Relative, so
# caches in metres and in centimetres behave alike; 1/1000 of a person is ~2 mm, the order of a
# simulator's collision thickness, so resting contact is not reported as penetration.
PENETRATION_TOLERANCE_FRACTION = 1e-3
# Cloth further than this fraction of the body's size from every body vertex is never "inside": with the
# nearest-vertex test a far-away vertex behind a concave part of the body could otherwise read as inside.
# A quarter of a person is deeper than any torso or limb is thick.
MAX_DEPTH_FRACTION = 0.25
# Push-out repeats this many times: after a move the nearest body vertex can change.
PUSH_OUT_ITERATIONS = 3
# Steps shorter than this (cache units) mean the cloth does not move: seam ratios are then undefined.
_STILL_STEP = 1e-12
# Jacobi iterations of the crossfade's edge-length restoration, and their over-relaxation. The blend
# starts within a few percent of the target lengths, so 40 averaged Jacobi sweeps (relaxed by 1.5, the
# value Macklin et al. 2014 recommend for averaged constraint projection) bring the mean strain back to
# the simulation's on a 4,000-vertex skirt (measured by services/benchmarks/bench_closing.py).
EDGE_PROJECTION_ITERATIONS = 40
EDGE_PROJECTION_RELAXATION = 1.5
# A vertex whose two blended frames lie closer than this fraction of the seam's RMS gap is treated as
# pinned by the edge restoration: a waistband that follows the body is the same in A and B.
PINNED_GAP_FRACTION = 1e-3
# The stretch ratio's denominator is at least this mean strain (0.1 %): a cloth solver never holds its
# edges tighter than that, and a rigid synthetic cache (strain 0) would make any change read as infinite.
MIN_REFERENCE_STRAIN = 1e-3
# The smooth push-out spreads each push over this fraction of the cycle either side of the frame that
# needs it (at least 2 frames): 1/12 of a 48-frame walk is 4 frames, long enough to keep a 10 mm push
# below the cloth's own frame-to-frame acceleration, short enough to stay local.
PUSH_OUT_REACH_FRACTION = 1.0 / 12.0


def _as_cache(points: np.ndarray, name: str, dtype=np.float64) -> np.ndarray:
    """Check a (frames, vertices, 3) array; convert to `dtype` (None: keep it, so slicing a big cache copies nothing)."""
    points = np.asarray(points, dtype=dtype)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"{name}: expected a (frames, vertices, 3) array, got shape {points.shape}")
    return points


def _rms(delta: np.ndarray) -> np.ndarray:
    """RMS length over vertices of (..., V, 3) offsets: (...,) float64."""
    return np.sqrt(np.mean(np.sum(np.square(delta), axis=-1), axis=-1))


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


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges of (T, 3) triangles -> (E, 2) int64, each once, sorted."""
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"unique_edges: expected (T, 3) faces, got shape {faces.shape}")
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def edge_lengths(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Lengths of (E, 2) edges in (..., V, 3) points: (..., E) float64."""
    points = np.asarray(points, dtype=np.float64)
    return np.linalg.norm(points[..., edges[:, 1], :] - points[..., edges[:, 0], :], axis=-1)


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
        error = delta * (1.0 - target / np.maximum(length, _STILL_STEP))[..., None]  # what closes the gap
        x += step_scale * (gather(share_i * error, scatter_i) - gather(share_j * error, scatter_j))
    return x


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
    points = _as_cache(points, "close_loop", dtype=None)
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
            logger.warning("crossfade shortened to %d frames either side of the seam: the cache ends there", half)
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
    w = weight[:, None, None]
    blended = (1.0 - w) * end_side + w * start_side
    if edges is not None and len(edges):
        edges = np.asarray(edges, dtype=np.int64)
        target = (1.0 - weight[:, None]) * edge_lengths(end_side, edges) + weight[:, None] * edge_lengths(start_side, edges)
        gap = np.sqrt(np.sum(np.square(start_side - end_side), axis=-1))  # (2h, V)
        movable = gap > PINNED_GAP_FRACTION * max(float(np.sqrt(np.mean(np.square(gap)))), _STILL_STEP)
        blended = restore_edge_lengths(blended, edges, target, movable)
    loop = points[start:end].astype(np.float64)
    before_seam = offsets < 0
    loop[cycle_frames + offsets[before_seam]] = blended[before_seam]  # frames Fe - h .. Fe - 1
    loop[offsets[~before_seam]] = blended[~before_seam]  # frames Fs .. Fs + h - 1
    # The loop is now periodic: the frame before Fs is the last looped frame, Fe is Fs, Fe + 1 is Fs + 1.
    return np.concatenate([loop[-1:], loop, loop[:2]])


def looped_frames(trajectory: np.ndarray) -> np.ndarray:
    """The loop (l, V, 3) inside a (l + 3, V, 3) trajectory from close_loop: frames Fs .. Fe-1."""
    return trajectory[1:-2]


@dataclass(frozen=True)
class SeamFigures:
    """How visible the seam is, relative to the cycle's own motion.

    position_jump_ratio: RMS over vertices of x(Fe) - x(Fs), over the median RMS frame-to-frame step of the
        cycle. 0 for a closed loop; about 1 means the seam jumps as far as a typical frame moves.
    velocity_jump_ratio: RMS of x'(Fe) - x'(Fs) (central differences, per frame), over the same median step:
        0 when the cloth leaves Fe as it left Fs, whatever its acceleration.
    max_step_ratio: the largest step of the looped playback (the wrap-around step from Fe-1 to Fs
        included) over the median step: catches a kink a closing may leave inside the cycle.
    median_step: the median RMS frame-to-frame step from Fs to Fe (cache units per frame).
    Ratios are inf when the cloth does not move at all and the seam does.
    """

    position_jump_ratio: float
    velocity_jump_ratio: float
    max_step_ratio: float
    median_step: float


def _ratio(value: float, scale: float) -> float:
    if scale > _STILL_STEP:
        return float(value / scale)
    return 0.0 if value <= _STILL_STEP else float("inf")


def seam_figures(trajectory: np.ndarray) -> SeamFigures:
    """Seam figures of a (l + 3, V, 3) trajectory over Fs-1 .. Fe+1 (see close_loop), l >= 2."""
    trajectory = _as_cache(trajectory, "seam_figures")
    if trajectory.shape[0] < 5:
        raise ValueError(f"seam_figures: need at least 5 frames (Fs-1 .. Fe+1), got {trajectory.shape[0]}")
    start, end = 1, trajectory.shape[0] - 2
    steps = _rms(np.diff(trajectory[start : end + 1], axis=0))  # the l steps Fs -> Fe
    median_step = float(np.median(steps))
    position_jump = float(_rms(trajectory[end] - trajectory[start]))
    velocity_end = 0.5 * (trajectory[end + 1] - trajectory[end - 1])
    velocity_start = 0.5 * (trajectory[start + 1] - trajectory[start - 1])
    velocity_jump = float(_rms(velocity_end - velocity_start))
    wrap_step = float(_rms(trajectory[start] - trajectory[end - 1]))
    loop_steps = np.append(steps[:-1], wrap_step)
    return SeamFigures(
        position_jump_ratio=_ratio(position_jump, median_step),
        velocity_jump_ratio=_ratio(velocity_jump, median_step),
        max_step_ratio=_ratio(float(loop_steps.max()), median_step),
        median_step=median_step,
    )


# Bounds a closing must keep to on every loop, each a ratio to what the simulator itself did (see LoopQuality):
# 10 % more mean edge strain than the raw frames is below what shows as rubbery cloth; no frame further from
# its simulated self than 1.5 seam jumps (a closing must move frames, but by the order of the jump it hides,
# not more); and no acceleration at the seam above 1.5 times the larger of the loop's median and the
# simulator's own acceleration there, the size of kink the eye picks out in a looping walk.
QUALITY_BOUNDS = {"stretch_ratio": 1.10, "deviation_ratio": 1.5, "seam_acceleration_ratio": 1.5}


@dataclass(frozen=True)
class LoopQuality:
    """How far a closed loop strays from the simulation it came from; every ratio is 1 or less for a good closing.

    stretch_ratio: mean edge strain |L / L_rest - 1| over the loop's frames and edges, over that of the raw
        frames Fs .. Fe-1 (at least MIN_REFERENCE_STRAIN; L_rest: the rest lengths given, by default the
        cache's first frame). None without edges.
    deviation_ratio: the largest per-frame RMS distance between a looped frame and the simulator's same frame,
        over the raw seam jump RMS |x(Fe) - x(Fs)|.
    seam_acceleration_ratio: RMS acceleration (second difference) at the two frames either side of the
        loop's wrap, over the larger of the loop's median acceleration and the simulator's own acceleration
        at those frames (a seam cut where the legs kick the cloth hardest is not a kink).
    max_acceleration_ratio: the loop's largest per-frame RMS acceleration over its median (kinks anywhere).
    seam_jump, seam_acceleration, median_acceleration, simulated_seam_acceleration: the figures behind the
        ratios (cache units, per frame and per frame squared).
    exceeded: names of the ratios above QUALITY_BOUNDS.
    """

    stretch_ratio: float | None
    deviation_ratio: float
    seam_acceleration_ratio: float
    max_acceleration_ratio: float
    seam_jump: float
    seam_acceleration: float
    median_acceleration: float
    simulated_seam_acceleration: float
    exceeded: tuple[str, ...]

    @property
    def within_bounds(self) -> bool:
        return not self.exceeded


def mean_edge_strain(points: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray) -> float:
    """Mean over frames and edges of |L / L_rest - 1|: (N, V, 3) points, (E, 2) edges, (E,) rest lengths."""
    rest_lengths = np.asarray(rest_lengths, dtype=np.float64)
    valid = rest_lengths > _STILL_STEP  # a degenerate rest edge has no strain to speak of
    strain = edge_lengths(points, edges[valid]) / rest_lengths[valid] - 1.0
    return float(np.mean(np.abs(strain))) if strain.size else 0.0


def _cyclic_accelerations(loop: np.ndarray) -> np.ndarray:
    """RMS over vertices of x(i + 1) - 2 x(i) + x(i - 1) for a (l, V, 3) loop played cyclically: (l,)."""
    return _rms(np.roll(loop, -1, axis=0) - 2.0 * loop + np.roll(loop, 1, axis=0))


def loop_quality(
    raw_trajectory: np.ndarray,
    looped: np.ndarray,
    edges: np.ndarray | None = None,
    rest_lengths: np.ndarray | None = None,
) -> LoopQuality:
    """LoopQuality of `looped` (l, V, 3) against the simulator's frames.

    raw_trajectory: (l + 3, V, 3) close_loop(..., "none"): frames Fs-1 .. Fe+1 as simulated.
    edges: (E, 2) cloth edges and rest_lengths (E,) for the stretch ratio (both or neither).
    """
    raw_trajectory = _as_cache(raw_trajectory, "loop_quality raw")
    looped = _as_cache(looped, "loop_quality looped")
    length = looped.shape[0]
    if raw_trajectory.shape != (length + 3, *looped.shape[1:]):
        raise ValueError(f"loop_quality: raw trajectory {raw_trajectory.shape} does not frame a loop of {looped.shape}")
    raw_loop = raw_trajectory[1:-2]
    seam_jump = float(_rms(raw_trajectory[-2] - raw_trajectory[1]))
    deviation = float(_rms(looped - raw_loop).max())
    acceleration = _cyclic_accelerations(looped)
    median_acceleration = float(np.median(acceleration))
    seam_acceleration = float(max(acceleration[0], acceleration[-1]))
    # The simulator's accelerations at the same frames: at Fs (from Fs-1, Fs, Fs+1) and at Fe-1.
    simulated = _rms(raw_trajectory[2:] - 2.0 * raw_trajectory[1:-1] + raw_trajectory[:-2])  # frames Fs .. Fe
    simulated_seam = float(max(simulated[0], simulated[length - 1]))
    stretch = None
    if edges is not None and rest_lengths is not None and len(edges):
        raw_strain = mean_edge_strain(raw_loop, edges, rest_lengths)
        stretch = _ratio(mean_edge_strain(looped, edges, rest_lengths), max(raw_strain, MIN_REFERENCE_STRAIN))
    ratios = {
        "stretch_ratio": stretch,
        "deviation_ratio": _ratio(deviation, seam_jump),
        "seam_acceleration_ratio": _ratio(seam_acceleration, max(median_acceleration, simulated_seam)),
    }
    exceeded = tuple(name for name, bound in QUALITY_BOUNDS.items() if ratios[name] is not None and not ratios[name] <= bound)
    return LoopQuality(
        stretch_ratio=ratios["stretch_ratio"],
        deviation_ratio=ratios["deviation_ratio"],
        seam_acceleration_ratio=ratios["seam_acceleration_ratio"],
        max_acceleration_ratio=_ratio(float(acceleration.max()), median_acceleration),
        seam_jump=seam_jump,
        seam_acceleration=seam_acceleration,
        median_acceleration=median_acceleration,
        simulated_seam_acceleration=simulated_seam,
        exceeded=exceeded,
    )


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of (..., V, 3) positions with (T, 3) triangles: (..., V, 3) float64.

    Counter-clockwise triangles face outwards (glTF/OBJ convention). Vertices that belong to no triangle, or
    only to degenerate ones, get a zero normal.
    """
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if positions.ndim < 2 or positions.shape[-1] != 3:
        raise ValueError(f"vertex_normals: expected (..., V, 3) positions, got shape {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"vertex_normals: expected (T, 3) faces, got shape {faces.shape}")
    vertex_count = positions.shape[-2]
    if faces.size and (faces.min() < 0 or faces.max() >= vertex_count):
        raise ValueError(f"vertex_normals: a face index is outside [0, {vertex_count})")
    lead = positions.shape[:-2]
    flat = positions.reshape(-1, vertex_count, 3)
    a, b, c = flat[:, faces[:, 0]], flat[:, faces[:, 1]], flat[:, faces[:, 2]]
    face_normals = np.cross(b - a, c - a)  # length = 2 * area: the area weighting comes for free
    # Vertex-by-face incidence: one sparse product sums every frame's face normals onto the vertices.
    rows = faces.reshape(-1)
    cols = np.repeat(np.arange(len(faces)), 3)
    incidence = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(vertex_count, len(faces)))
    stacked = face_normals.transpose(1, 0, 2).reshape(len(faces), -1)  # (T, frames * 3)
    summed = (incidence @ stacked).reshape(vertex_count, -1, 3).transpose(1, 0, 2)
    length = np.linalg.norm(summed, axis=-1, keepdims=True)
    normals = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
    return normals.reshape(*lead, vertex_count, 3)


def body_size(body: np.ndarray) -> float:
    """The body's size: the bounding-box diagonal of its first frame, (F, Vb, 3) -> float (cache units)."""
    body = _as_cache(body, "body_size", dtype=None)
    first = body[0].astype(np.float64)
    return float(np.linalg.norm(first.max(axis=0) - first.min(axis=0)))


@dataclass(frozen=True)
class PenetrationSettings:
    """Tolerances of the penetration test in cache units (see PENETRATION_TOLERANCE_FRACTION, MAX_DEPTH_FRACTION)."""

    tolerance: float
    max_depth: float

    @classmethod
    def for_body(cls, body: np.ndarray) -> "PenetrationSettings":
        size = body_size(body)
        return cls(tolerance=PENETRATION_TOLERANCE_FRACTION * size, max_depth=MAX_DEPTH_FRACTION * size)


class BodyFrames:
    """The body over the frames of a cycle, with one k-d tree per frame built on first use.

    positions: (F, Vb, 3) body vertices; normals: (F, Vb, 3) unit outward normals (see vertex_normals).
    """

    def __init__(self, positions: np.ndarray, normals: np.ndarray):
        self.positions = _as_cache(positions, "BodyFrames positions")
        self.normals = _as_cache(normals, "BodyFrames normals")
        if self.positions.shape != self.normals.shape:
            raise ValueError(
                f"BodyFrames: positions {self.positions.shape} and normals {self.normals.shape} differ in shape"
            )
        self._trees: dict[int, cKDTree] = {}

    def __len__(self) -> int:
        return self.positions.shape[0]

    def signed_offsets(self, frame: int, cloth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For (V, 3) cloth at `frame`: offset along the nearest body vertex's normal (V,), distance (V,), nearest (V,)."""
        tree = self._trees.get(frame)
        if tree is None:
            tree = self._trees[frame] = cKDTree(self.positions[frame])
        distance, nearest = tree.query(cloth)
        offset = np.einsum("ij,ij->i", cloth - self.positions[frame][nearest], self.normals[frame][nearest])
        return offset, distance, nearest


def penetration_mask(cloth: np.ndarray, body: BodyFrames, settings: PenetrationSettings) -> np.ndarray:
    """(F, V) bool: cloth vertex v is inside the body at frame f.

    cloth: (F, V, 3) with F == len(body), frame f of the cloth meeting frame f of the body.
    """
    cloth = _as_cache(cloth, "penetration_mask")
    if cloth.shape[0] != len(body):
        raise ValueError(f"penetration_mask: {cloth.shape[0]} cloth frames against {len(body)} body frames")
    mask = np.zeros(cloth.shape[:2], dtype=bool)
    for frame in range(cloth.shape[0]):
        offset, distance, _ = body.signed_offsets(frame, cloth[frame])
        mask[frame] = (offset < -settings.tolerance) & (distance < settings.max_depth)
    return mask


def push_out(
    cloth: np.ndarray, body: BodyFrames, settings: PenetrationSettings, only: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Move penetrating cloth vertices out along the nearest body normal to `tolerance` above the surface.

    cloth: (F, V, 3); only: optional (F, V) bool, the vertices allowed to move (default: all).
    Returns (pushed cloth (F, V, 3) float64, moved (F, V) bool).
    """
    pushed = _as_cache(cloth, "push_out").copy()
    moved = np.zeros(pushed.shape[:2], dtype=bool)
    for frame in range(pushed.shape[0]):
        for _ in range(PUSH_OUT_ITERATIONS):
            offset, distance, nearest = body.signed_offsets(frame, pushed[frame])
            inside = (offset < -settings.tolerance) & (distance < settings.max_depth)
            if only is not None:
                inside &= only[frame]
            if not inside.any():
                break
            lift = (settings.tolerance - offset[inside])[:, None] * body.normals[frame][nearest[inside]]
            pushed[frame][inside] += lift
            moved[frame] |= inside
    return pushed, moved


def raised_cosine(reach: int) -> np.ndarray:
    """(2 reach + 1,) weights 0.5 (1 + cos(pi t / (reach + 1))), t = -reach .. reach: 1 at t = 0, easing to 0."""
    t = np.arange(-reach, reach + 1)
    return 0.5 * (1.0 + np.cos(np.pi * t / (reach + 1)))


def smooth_push_out(
    loop: np.ndarray, body: BodyFrames, settings: PenetrationSettings, only: np.ndarray | None = None, reach: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Push penetrating cloth out of the body with a push that eases in and out over `reach` frames either side.

    loop: (l, V, 3) frames played cyclically, frame i meeting body frame i; only: optional (l, V) bool, the
    (frame, vertex) pairs whose penetration is to be removed (default: all). Each pass finds the depth d(i, v)
    a penetrating vertex must rise to sit `tolerance` above the nearest body vertex's tangent plane, spreads
    it over time by a max-convolution with a raised cosine (so every penetrating frame still gets its whole
    push, and its neighbours a part of it: no jump from one frame to the next), and moves every vertex along
    its nearest body normal at that frame by the spread depth. PUSH_OUT_ITERATIONS passes, as the nearest
    body vertex may change after a move. Returns (pushed (l, V, 3) float64, moved (l, V) bool).
    """
    pushed = _as_cache(loop, "smooth_push_out").copy()
    frame_count, vertex_count, _ = pushed.shape
    if frame_count != len(body):
        raise ValueError(f"smooth_push_out: {frame_count} cloth frames against {len(body)} body frames")
    kernel = raised_cosine(max(0, min(int(reach), (frame_count - 1) // 2)))
    half = len(kernel) // 2
    moved = np.zeros((frame_count, vertex_count), dtype=bool)
    for _ in range(PUSH_OUT_ITERATIONS):
        depth = np.zeros((frame_count, vertex_count))
        normal = np.empty((frame_count, vertex_count, 3))
        for frame in range(frame_count):
            offset, distance, nearest = body.signed_offsets(frame, pushed[frame])
            inside = (offset < -settings.tolerance) & (distance < settings.max_depth)
            if only is not None:
                inside &= only[frame]
            depth[frame, inside] = settings.tolerance - offset[inside]
            normal[frame] = body.normals[frame][nearest]
        if not depth.any():
            break
        spread = depth.copy()
        for shift in range(1, half + 1):  # cyclic max-convolution with the raised cosine
            weight = kernel[half + shift]
            spread = np.maximum(spread, weight * np.maximum(np.roll(depth, shift, axis=0), np.roll(depth, -shift, axis=0)))
        pushed += spread[..., None] * normal
        moved |= spread > 0
    return pushed, moved


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
    push_out_mode: "new" moves back out only the vertices that penetrate after closing but did not in the
    raw frame (so an unclosed loop is exactly the simulator's output), "all" every penetrating vertex,
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
        body = _as_cache(body, "close_cycle body", dtype=None)
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
            allowed = mask_closed & ~mask_before if push_out_mode == "new" else None
            reach = max(2, round(PUSH_OUT_REACH_FRACTION * cycle_frames))
            pushed_loop, moved = smooth_push_out(closed[loop], frames_of_body, settings, only=allowed, reach=reach)
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
