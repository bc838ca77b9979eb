"""The impostor surface map (SPEC.md "Impostor maps", role impostor-surface): per texel of a (view, frame)
tile, how far the surface it shows lies along the view axis, and how fast that surface point moves in the
tile's plane at that baked frame. crowdview reprojects every blended sample with it
(crowdbake.reference.impostor_warp, shaders/impostor_warp.glsl), so a camera between baked views, or a cycle
frame between baked frames, sees the character where the mesh would be instead of a cross-fade of two
misplaced pictures.

Channels (8 bits each, before block compression), as fractions of the bounds radius R:

    R: depth along the view's `back` axis from the bounds centre, in [-R, R]  (code 0..255 -> -R..R)
    G: motion along the view's `right` axis, in [-R/2, R/2]
    B: the same along the view's `up` axis
    A: 255

The motion is the point's velocity at the baked frame over one baked step: half its move from the previous
baked frame to the next (central difference; one-sided where a range has no frame on one side,
motion_positions). The runtime moves the earlier of two blended frames forward by the frame weight w times
it and the later one back by 1 - w times it, so one layer a frame serves both. The heavier sample is always
the nearer frame, and near its own frame a velocity is second-order right where the one-sided move to the
next frame is not: on CesiumMan's skirt this raised SSIM a third of the way between frames from 0.822 to
0.858 (services/benchmarks/bench_between_views.py, warp_central against warp_velocity). Texels outside the
silhouette hold the nearest inside texel's values, so the runtime's bilinear reads and fixed-point steps
that land beside the character still find the surface next to it. Pure numpy; metres in, codes out.
"""
from __future__ import annotations

import numpy as np

from crowdbake.bake import impostor_views
from crowdbake.formats.ranges import Clip, Ranges

DEPTH_RANGE = 1.0   # depth codes span +-DEPTH_RANGE * radius
MOTION_RANGE = 0.5  # motion codes span +-MOTION_RANGE * radius


def motion_positions(positions: np.ndarray, previous: np.ndarray | None, following: np.ndarray | None) -> np.ndarray:
    """(V, 3) where each vertex would be after one step of its velocity at this baked frame (module
    docstring): positions + (following - previous) / 2; with only one neighbouring baked frame (None for the
    other: a transition's ends, or one baked frame) the move to or from it; with none, positions.

    positions, previous, following: (V, 3) model-space vertices at this baked frame and its neighbours."""
    positions = np.asarray(positions, dtype=np.float64)
    if previous is not None and following is not None:
        return positions + (np.asarray(following, dtype=np.float64) - np.asarray(previous, dtype=np.float64)) / 2.0
    if following is not None:
        return np.asarray(following, dtype=np.float64)
    if previous is not None:
        return 2.0 * positions - np.asarray(previous, dtype=np.float64)
    return positions


def motion_sides(frame: int, previous: int, following: int) -> tuple[int | None, int | None]:
    """The baked frames (previous, following) the motion at baked frame `frame` is taken between, for
    motion_positions: None for a side whose neighbour is `frame` itself (a range's end, or one baked frame).
    With two baked frames in a loop both neighbours are the other frame, where a central difference would
    be zero: the move to it alone."""
    if previous == following != frame:
        return None, following
    return (None if previous == frame else previous), (None if following == frame else following)


def _codes(values: np.ndarray, limit: float) -> np.ndarray:
    return np.rint((np.clip(values, -limit, limit) + limit) / (2.0 * limit) * 255.0).astype(np.uint8)


def _values(codes: np.ndarray, limit: float) -> np.ndarray:
    return codes.astype(np.float64) / 255.0 * (2.0 * limit) - limit


def encode_surface(depth: np.ndarray, motion: np.ndarray, radius: float) -> np.ndarray:
    """(S, S, 4) uint8 RGBA texels of (depth (S, S), motion (S, S, 2)) in metres (module docstring)."""
    rgba = np.empty(depth.shape + (4,), dtype=np.uint8)
    rgba[..., 0] = _codes(depth, DEPTH_RANGE * radius)
    rgba[..., 1:3] = _codes(motion, MOTION_RANGE * radius)
    rgba[..., 3] = 255
    return rgba


def decode_surface(texels: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(depth (..., ), motion (..., 2)) in metres from (..., 4) uint8 (or 0..255 float) surface texels."""
    texels = np.asarray(texels)
    return _values(texels[..., 0], DEPTH_RANGE * radius), _values(texels[..., 1:3], MOTION_RANGE * radius)


def motion_in_model(view: impostor_views.OrthoView, motion: np.ndarray) -> np.ndarray:
    """(..., 3) model-space motion of (..., 2) tile-plane motion (right, up components) in `view`."""
    return motion[..., 0:1] * view.right + motion[..., 1:2] * view.up


def next_baked_frame(frame: int, frame_indices) -> int:
    """The baked frame after `frame` in the cycle, wrapping to the first (itself when only one is baked)."""
    indices = list(frame_indices)
    return indices[(indices.index(frame) + 1) % len(indices)]


def previous_baked_frame(frame: int, frame_indices) -> int:
    """The baked frame before `frame` in the cycle, wrapping to the last (itself when only one is baked)."""
    indices = list(frame_indices)
    return indices[indices.index(frame) - 1]


def previous_baked_frame_in_range(ranges: Ranges, frame: int, frame_indices) -> int:
    """With several clips (crowdbake.bake.pose_ranges.next_baked_frame the other way): the baked frame
    before `frame` in its own range; a clip's first wraps to the clip's last, a transition's first leads to
    itself (playback never goes back past a transition's start)."""
    item = next((r for r in ranges.all() if r.first_frame <= frame < r.first_frame + r.frames), None)
    inside = [] if item is None else [f for f in frame_indices if item.first_frame <= f < item.first_frame + item.frames]
    if frame not in inside:
        raise ValueError(f"previous_baked_frame_in_range: {frame} is not a baked frame")
    earlier = [f for f in inside if f < frame]
    if earlier:
        return earlier[-1]
    return inside[-1] if isinstance(item, Clip) else frame
