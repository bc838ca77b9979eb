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
  few frames.

Trajectories here run over frames Fs-1 .. Fe+1 (l + 3 frames: Fe and a frame either side are kept so the
seam can be measured); the looped cache is Fs .. Fe-1. Velocities are per frame (central differences).

Penetration is measured against the body given as arrays: for each cloth vertex the nearest body vertex
(a k-d tree per frame) and the sign of the offset along that vertex's normal. Pure numpy/scipy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

CLOSE_METHODS = ("none", "linear", "hermite")
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


def close_loop(
    points: np.ndarray, start: int, cycle_frames: int, method: str, blend_frames: int | None = None
) -> np.ndarray:
    """The closed trajectory over frames Fs-1 .. Fe+1: (cycle_frames + 3, V, 3) float64.

    Row 1 + i is frame Fs + i; rows 1 .. l are the loop (see `looped_frames`), row l + 1 is the closed Fe
    (equal to row 1 once the seam is closed), and rows 0 and l + 2 carry each method's own continuation
    either side, so central velocities at Fs and Fe are defined for the seam figures.

    points: (F, V, 3) cache; start: Fs; cycle_frames: l (Fe = Fs + l); method: one of CLOSE_METHODS;
    blend_frames: b for "linear" (default `default_blend_frames(l)`), which needs Fs >= b.
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


@dataclass(frozen=True)
class ClosedLoop:
    """The result of closing one cycle.

    looped: (l, V, 3) float32, the frames to play in a loop.
    method, blend_frames: the closing used (blend_frames None unless "linear").
    seam_before, seam_after: seam figures of the raw cycle and of the closed (and pushed-out) one.
    penetrating_before, penetrating_closed, penetrating_after: (l,) int64 penetrating cloth vertices per
        looped frame for the raw cycle, after closing, and after the push-out.
    pushed_vertices: how many (frame, vertex) pairs the push-out moved.
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
) -> ClosedLoop:
    """Close the cycle [start, start + cycle_frames) of a cloth cache and measure what that did.

    cloth: (F, V, 3); body: (F, Vb, 3) over the same frames, or None to skip penetration; body_normals:
    (F, Vb, 3) unit outward normals, or None to compute them from body_faces (T, 3) for the cycle's frames.
    push_out_mode: "new" moves back out only the vertices that penetrate after closing but did not in the
    raw frame (so an unclosed loop is exactly the simulator's output), "all" every penetrating vertex,
    "none" nothing. settings: penetration tolerances, default PenetrationSettings.for_body(body).
    """
    if push_out_mode not in PUSH_OUT_MODES:
        raise ValueError(f"close_cycle: push_out_mode must be one of {PUSH_OUT_MODES}, got {push_out_mode!r}")
    raw = close_loop(cloth, start, cycle_frames, "none")
    closed = close_loop(cloth, start, cycle_frames, method, blend_frames)
    loop = slice(1, cycle_frames + 1)  # rows of the looped frames Fs .. Fe-1
    if body is None:
        zero = np.zeros(cycle_frames, dtype=np.int64)
        final, pushed_count = closed, 0
        before = closed_count = after = zero
    else:
        body = _as_cache(body, "close_cycle body", dtype=None)
        if body.shape[0] != np.asarray(cloth).shape[0]:
            raise ValueError(f"close_cycle: body has {body.shape[0]} frames, cloth {np.asarray(cloth).shape[0]}")
        rows = slice(start - 1, start + cycle_frames + 2)  # the trajectory's frames, Fs-1 .. Fe+1
        if body_normals is not None:
            normals = np.asarray(body_normals)[rows]
        elif body_faces is not None:
            normals = vertex_normals(body[rows], body_faces)
        else:
            raise ValueError("close_cycle: a body needs body_normals or body_faces")
        settings = settings or PenetrationSettings.for_body(body)
        frames_of_body = BodyFrames(body[rows], normals)
        mask_before = penetration_mask(raw, frames_of_body, settings)
        mask_closed = penetration_mask(closed, frames_of_body, settings)
        if push_out_mode == "none":
            final, moved = closed, np.zeros_like(mask_closed)
        else:
            allowed = mask_closed & ~mask_before if push_out_mode == "new" else None
            final, moved = push_out(closed, frames_of_body, settings, only=allowed)
        mask_after = penetration_mask(final, frames_of_body, settings) if moved.any() else mask_closed
        before = mask_before[loop].sum(axis=1)
        closed_count = mask_closed[loop].sum(axis=1)
        after = mask_after[loop].sum(axis=1)
        pushed_count = int(moved[loop].sum())
    return ClosedLoop(
        looped=looped_frames(final).astype(np.float32),
        method=method,
        blend_frames=(default_blend_frames(cycle_frames) if blend_frames is None else int(blend_frames))
        if method == "linear"
        else None,
        push_out=push_out_mode,
        seam_before=seam_figures(raw),
        seam_after=seam_figures(final),
        penetrating_before=np.asarray(before, dtype=np.int64),
        penetrating_closed=np.asarray(closed_count, dtype=np.int64),
        penetrating_after=np.asarray(after, dtype=np.int64),
        pushed_vertices=pushed_count,
    )
