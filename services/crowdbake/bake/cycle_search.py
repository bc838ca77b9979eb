"""Pass 1 of the cycle search: a windowed vertex distance between frames a cycle apart, and its candidates.

Dobbyn et al. 2006, section 3: "a distance metric similar to Kovar et al. [KGP02] ... between all frames that
were of length l apart", over all the cloth's vertices, counting position and velocity. For a start frame s
and a gap g (the walk's cycle length l, or a multiple of it) the distance is

    D(s)^2 = sum_j w_j [ P(s + j) + lambda^2 V(s + j) ],   j = -h .. h,  k = 2h + 1 frames,

    P(f) = mean over vertices of |x_v(f) - x_v(f + g)|^2                  (squared length)
    V(f) = mean over vertices of |x'_v(f) - x'_v(f + g)|^2               (squared length per frame)

with binomial weights w (they sum to 1; Kovar et al. taper their window the same way so that the seam
frame itself counts most) and central-difference velocities x'(f) = (x(f+1) - x(f-1)) / 2. lambda is a
time in frames that turns a velocity into a length: a velocity mismatch of u per frame costs as much as
a position mismatch of lambda * u. D is thus an RMS length in the cache's units.

Unlike Kovar et al. there is no rigid 2D alignment of the two windows: the character walks on the spot, so
the frames are already in the same place, and an alignment would hide a real twist of the garment. When
the character does travel, pass `root_offsets` (the root's position per frame) and the cloth is compared
in the root's frame.

Pure numpy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np

# Frames processed together when forming the seam error x(f) - x(f + g); bounds the temporary memory
# to chunk * V * 3 floats without costing speed (each chunk is still a large vectorised operation).
_CHUNK_FRAMES = 48

DEFAULT_WINDOW = 5
DEFAULT_VELOCITY_WEIGHT = 1.0
DEFAULT_MAX_CANDIDATES = 5


def binomial_weights(window: int) -> np.ndarray:
    """(window,) float64 binomial weights C(window-1, i) / 2^(window-1); `window` must be odd and >= 1."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"binomial_weights: window must be a positive odd number of frames, got {window}")
    n = window - 1
    return np.array([comb(n, i) for i in range(window)], dtype=np.float64) / 2.0**n


def _validate_cache(points: np.ndarray, name: str = "points") -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"{name}: expected a (frames, vertices, 3) cache, got shape {points.shape}")
    if points.shape[1] == 0:
        raise ValueError(f"{name}: the cache has no vertices")
    if not np.issubdtype(points.dtype, np.floating):
        raise ValueError(f"{name}: expected floating-point positions, got {points.dtype}")
    return points


def seam_error_energies(
    points: np.ndarray, gap: int, root_offsets: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame position and velocity mismatch between frame f and frame f + gap, over all vertices.

    points: (F, V, 3) float cache. gap: frames between the compared frames (>= 1, < F - 2).
    root_offsets: optional (F, 3) root position per frame, subtracted from every vertex first.
    Returns (position, velocity), both (F - gap,) float64:
      position[f] = mean_v |x(f) - x(f + gap)|^2,
      velocity[f] = mean_v |x'(f) - x'(f + gap)|^2 with central differences, NaN at f = 0 and f = F - gap - 1
      where the difference is not defined.
    """
    points = _validate_cache(points)
    frame_count, vertex_count, _ = points.shape
    if not 1 <= gap <= frame_count - 3:
        raise ValueError(f"seam_error_energies: gap {gap} needs at least {gap + 3} frames, the cache has {frame_count}")
    if root_offsets is not None:
        root_offsets = np.asarray(root_offsets, dtype=np.float64)
        if root_offsets.shape != (frame_count, 3):
            raise ValueError(f"seam_error_energies: root_offsets must be ({frame_count}, 3), got {root_offsets.shape}")
    pair_count = frame_count - gap
    position = np.empty(pair_count, dtype=np.float64)
    velocity = np.full(pair_count, np.nan, dtype=np.float64)
    work_dtype = np.float32 if points.dtype == np.float32 else np.float64
    scale = 1.0 / vertex_count
    for begin in range(0, pair_count, _CHUNK_FRAMES):
        end = min(begin + _CHUNK_FRAMES, pair_count)
        # One extra frame each side so the central velocity difference is defined across chunk borders.
        lo, hi = max(begin - 1, 0), min(end + 1, pair_count)
        error = np.subtract(points[lo:hi], points[lo + gap : hi + gap], dtype=work_dtype)
        if root_offsets is not None:
            # The root moves x(f) and x(f + g) by different amounts: compare each in its own root frame.
            error -= (root_offsets[lo:hi] - root_offsets[lo + gap : hi + gap]).astype(work_dtype)[:, None, :]
        flat = error.reshape(hi - lo, -1)
        energy = np.einsum("ij,ij->i", flat, flat, dtype=np.float64) * scale
        position[begin:end] = energy[begin - lo : end - lo]
        # x'(f) - x'(f+g) = (e(f+1) - e(f-1)) / 2, with e(f) = x(f) - x(f+g): no second pass over the cache.
        first, last = max(begin, 1), min(end, pair_count - 1)
        if last > first:
            diff = flat[first + 1 - lo : last + 1 - lo] - flat[first - 1 - lo : last - 1 - lo]
            velocity[first:last] = np.einsum("ij,ij->i", diff, diff, dtype=np.float64) * (0.25 * scale)
    return position, velocity


@dataclass(frozen=True)
class DistanceCurve:
    """Pass-1 distance for every admissible start frame at one gap.

    start_frames: (N,) int64 start frames s (Fs), consecutive.
    distances: (N,) float64 D(s), an RMS length in the cache's units (see the module docstring).
    gap: frames from Fs to Fe (the cycle length times `cycle_count`).
    cycle_count: how many walk cycles the gap spans.
    """

    start_frames: np.ndarray
    distances: np.ndarray
    gap: int
    cycle_count: int


def vertex_distance_curve(
    points: np.ndarray,
    gap: int,
    window: int = DEFAULT_WINDOW,
    velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
    settle_frames: int = 0,
    root_offsets: np.ndarray | None = None,
    cycle_count: int = 1,
) -> DistanceCurve:
    """D(s) for every start frame s >= settle_frames whose whole window (and velocities) lies in the cache.

    points: (F, V, 3) float cache; gap: frames between Fs and Fe; window: k, odd number of frames;
    velocity_weight: lambda in frames (>= 0); settle_frames: the first start frame considered (the cloth
    needs time to settle from its rest pose before any cycle can repeat); root_offsets: optional (F, 3).
    Raises ValueError when no start frame is admissible, naming how many frames would be needed.
    """
    points = _validate_cache(points)
    weights = binomial_weights(window)
    if velocity_weight < 0:
        raise ValueError(f"vertex_distance_curve: velocity_weight must be >= 0, got {velocity_weight}")
    if settle_frames < 0:
        raise ValueError(f"vertex_distance_curve: settle_frames must be >= 0, got {settle_frames}")
    half = window // 2
    frame_count = points.shape[0]
    # s - half - 1 >= 0 and s + half + 1 <= F - gap - 1 keep every windowed velocity defined.
    first = max(settle_frames, half + 1)
    last = frame_count - gap - half - 2
    if last < first:
        needed = first + gap + half + 2 + 1
        raise ValueError(
            f"too few frames: a gap of {gap} frames with a {window}-frame window after {settle_frames} settle-in "
            f"frames needs at least {needed} frames, the cache has {frame_count}"
        )
    position, velocity = seam_error_energies(points, gap, root_offsets)
    per_frame = position + velocity_weight**2 * velocity
    starts = np.arange(first, last + 1)
    # Windowed sum as a sliding dot product: per_frame is short (F), so this costs nothing.
    offsets = np.arange(-half, half + 1)
    windowed = (per_frame[starts[:, None] + offsets[None, :]] * weights[None, :]).sum(axis=1)
    return DistanceCurve(starts.astype(np.int64), np.sqrt(np.maximum(windowed, 0.0)), int(gap), int(cycle_count))


def local_minima(values: np.ndarray) -> np.ndarray:
    """Indices of the local minima of a 1-D curve, boundaries included, one index per flat bottom.

    An index i is a minimum when values[i] <= both neighbours and values[i] < the next different value on
    each side; a plateau yields its first index. NaN values are never minima.
    """
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    # Collapse runs of equal values so plateaus behave like single points.
    change = np.ones(n, dtype=bool)
    change[1:] = values[1:] != values[:-1]
    run_starts = np.flatnonzero(change)
    run_values = values[run_starts]
    left = np.concatenate([[np.inf], run_values[:-1]])
    right = np.concatenate([run_values[1:], [np.inf]])
    is_min = (run_values < left) & (run_values < right) & np.isfinite(run_values)
    return run_starts[is_min].astype(np.int64)


def pick_candidates(
    start_frames: np.ndarray,
    distances: np.ndarray,
    min_separation: int,
    max_candidates: int = DEFAULT_MAX_CANDIDATES,
    threshold: float | None = None,
) -> np.ndarray:
    """Indices into the curve of the candidate cycles, best (smallest distance) first.

    Candidates are local minima of `distances` (each valley of the curve gives at most one), under
    `threshold` when one is set, at least `min_separation` frames apart (the paper's candidates are distinct
    cycles, not neighbouring frames of one valley), at most `max_candidates` of them.
    """
    start_frames = np.asarray(start_frames)
    distances = np.asarray(distances, dtype=np.float64)
    if start_frames.shape != distances.shape or start_frames.ndim != 1:
        raise ValueError("pick_candidates: start_frames and distances must be 1-D arrays of one length")
    if max_candidates < 1:
        raise ValueError(f"pick_candidates: max_candidates must be at least 1, got {max_candidates}")
    minima = local_minima(distances)
    if threshold is not None:
        minima = minima[distances[minima] <= threshold]
    order = minima[np.argsort(distances[minima], kind="stable")]
    chosen: list[int] = []
    for index in order:
        if all(abs(int(start_frames[index]) - int(start_frames[c])) >= min_separation for c in chosen):
            chosen.append(int(index))
            if len(chosen) == max_candidates:
                break
    return np.array(chosen, dtype=np.int64)


@dataclass(frozen=True)
class VertexCandidate:
    """One pass-1 candidate: the cycle [start_frame, start_frame + gap) and its distance D(start_frame)."""

    start_frame: int
    gap: int
    cycle_count: int
    vertex_distance: float


def search_vertex_candidates(
    points: np.ndarray,
    cycle_frames: int,
    window: int = DEFAULT_WINDOW,
    velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
    settle_frames: int = 0,
    max_candidates: int = DEFAULT_MAX_CANDIDATES,
    threshold: float | None = None,
    min_separation: int | None = None,
    max_cycle_count: int = 1,
    root_offsets: np.ndarray | None = None,
) -> tuple[list[VertexCandidate], list[DistanceCurve]]:
    """Pass 1 over gaps of 1 .. max_cycle_count walk cycles: candidates (best first) and the distance curves.

    points: (F, V, 3) cloth cache; cycle_frames: l, the walk's cycle length in frames (>= 2).
    min_separation: frames between candidates of one gap, default l / 2 (rounded up).
    Gaps whose window does not fit the cache are skipped; if even one cycle does not fit, ValueError.
    The candidates of all gaps compete on their distance; at most `max_candidates` are returned.
    """
    if cycle_frames < 2:
        raise ValueError(f"search_vertex_candidates: cycle_frames must be at least 2, got {cycle_frames}")
    if max_cycle_count < 1:
        raise ValueError(f"search_vertex_candidates: max_cycle_count must be at least 1, got {max_cycle_count}")
    separation = (cycle_frames + 1) // 2 if min_separation is None else int(min_separation)
    curves: list[DistanceCurve] = []
    candidates: list[VertexCandidate] = []
    for cycle_count in range(1, max_cycle_count + 1):
        gap = cycle_count * cycle_frames
        try:
            curve = vertex_distance_curve(
                points, gap, window, velocity_weight, settle_frames, root_offsets, cycle_count
            )
        except ValueError:
            if cycle_count == 1:
                raise
            break  # longer gaps do not fit either
        curves.append(curve)
        picked = pick_candidates(curve.start_frames, curve.distances, separation, max_candidates, threshold)
        candidates.extend(
            VertexCandidate(int(curve.start_frames[i]), gap, cycle_count, float(curve.distances[i])) for i in picked
        )
    candidates.sort(key=lambda c: c.vertex_distance)
    return candidates[:max_candidates], curves
