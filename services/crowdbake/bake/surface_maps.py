"""The impostor surface map (SPEC.md "Impostor maps", role impostor-surface): per texel of a (view, frame)
tile, how far the surface it shows lies along the view axis, and how that surface point moves in the tile's
plane on the way to the next baked frame. crowdview reprojects every blended sample with it
(crowdbake.bake.reference.impostor_warp, shaders/impostor_warp.glsl), so a camera between baked views, or a cycle
frame between baked frames, sees the character where the mesh would be instead of a cross-fade of two
misplaced pictures.

Channels (8 bits each, before block compression), as fractions of the bounds radius R:

    R: depth along the view's `back` axis from the bounds centre, in [-R, R]  (code 0..255 -> -R..R)
    G: motion to the next baked frame along the view's `right` axis, in [-R/2, R/2]
    B: the same along the view's `up` axis
    A: 255

The next baked frame wraps round the cycle; the way back to the previous baked frame is the same motion
reversed (constant velocity between baked frames), so one layer a frame suffices. Texels outside the
silhouette hold the nearest inside texel's values, so the runtime's bilinear reads and fixed-point steps
that land beside the character still find the surface next to it. Pure numpy; metres in, codes out.
"""
from __future__ import annotations

import numpy as np

from crowdbake.bake import impostor_views

DEPTH_RANGE = 1.0   # depth codes span +-DEPTH_RANGE * radius
MOTION_RANGE = 0.5  # motion codes span +-MOTION_RANGE * radius


def surface_fields(view: impostor_views.OrthoView, coverage: impostor_views.Coverage, positions: np.ndarray,
                   next_positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(depth (S, S) metres along view.back from view.center, motion (S, S, 2) metres along view.right and
    view.up to the next baked frame) of one view's coverage, dilated into the background.

    positions, next_positions: (V, 3) model-space vertices at this baked frame and the next; faces: (T, 3).
    The motion is that of the surface point the texel shows (same triangle, same barycentrics)."""
    mask = coverage.mask
    points = impostor_views.interpolate(positions, faces, coverage)
    moved = impostor_views.interpolate(next_positions, faces, coverage) - points
    depth = np.where(mask, (points - view.center) @ view.back, 0.0)
    motion = np.where(mask[..., None], np.stack([moved @ view.right, moved @ view.up], axis=-1), 0.0)
    nearest = impostor_views.nearest_inside(mask)
    if nearest is not None:
        depth, motion = depth[nearest], motion[nearest]
    return depth, motion


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
