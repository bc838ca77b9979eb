"""Cloth inside the body: finding it, and pushing it back out smoothly in time.

Penetration is measured against the body given as arrays: for each cloth vertex the nearest body vertex
(a k-d tree per frame) and the sign of the offset along that vertex's normal. Whatever closing made the
loop, cloth it pushed into the body is pushed back out smoothly in time: the depth to remove is spread
over a few frames either side with a raised-cosine envelope (a max-convolution, so every penetrating
frame still gets its full push), instead of a per-frame jump that would show as a spike in acceleration.
Pure numpy/scipy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from crowdbake.bake.mesh import as_point_frames

# What close_cycle pushes out: nothing, only penetration the closing made ("new"), or all of it.
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
# The smooth push-out spreads each push over this fraction of the cycle either side of the frame that
# needs it (at least 2 frames): 1/12 of a 48-frame walk is 4 frames, long enough to keep a 10 mm push
# below the cloth's own frame-to-frame acceleration, short enough to stay local.
PUSH_OUT_REACH_FRACTION = 1.0 / 12.0


def body_size(body: np.ndarray) -> float:
    """The body's size: the bounding-box diagonal of its first frame, (F, Vb, 3) -> float (cache units)."""
    body = as_point_frames(body, "body_size", dtype=None)
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

    positions: (F, Vb, 3) body vertices; normals: (F, Vb, 3) unit outward normals (see crowdbake.geometry.vertex_normals).
    """

    def __init__(self, positions: np.ndarray, normals: np.ndarray):
        self.positions = as_point_frames(positions, "BodyFrames positions")
        self.normals = as_point_frames(normals, "BodyFrames normals")
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
        # Every core: the cycle stage runs this on the bake's critical path (nothing else can start before
        # the cycle is known); the answers do not depend on the threads.
        distance, nearest = tree.query(cloth, workers=-1)
        offset = np.einsum("ij,ij->i", cloth - self.positions[frame][nearest], self.normals[frame][nearest])
        return offset, distance, nearest


def penetration_mask(cloth: np.ndarray, body: BodyFrames, settings: PenetrationSettings) -> np.ndarray:
    """(F, V) bool: cloth vertex v is inside the body at frame f.

    cloth: (F, V, 3) with F == len(body), frame f of the cloth meeting frame f of the body.
    """
    cloth = as_point_frames(cloth, "penetration_mask")
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
    pushed = as_point_frames(cloth, "push_out").copy()
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
    pushed = as_point_frames(loop, "smooth_push_out").copy()
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
