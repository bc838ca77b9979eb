"""Orthographic impostor views: the cameras of a ring (OrthoView, ortho_view), projection into a view's
texels, and the texture lookup and face normals the map shader (crowdbake.render.map_shader) and the
fidelity scores share.

Conventions (SPEC.md): the camera for azimuth θ and elevation φ sits in direction
(sin θ cos φ, sin φ, cos θ cos φ) from the bounds' centre, looks at it with +Y up, and sees a square of
2·radius metres. Texel (row, column) has its centre at (column + 0.5, row + 0.5) in pixel units, rows top
first. Pure numpy; no GL.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The camera sits this many radii from the centre: the sphere of the bounds then lies at depths 2r .. 4r,
# well inside a clip range of 1.5r .. 4.5r. Same as crowdbake.render.offscreen.
CAMERA_DISTANCE_RADII = 3.0
# Below this length an up vector is parallel to the viewing direction (looking straight down or up).
_PARALLEL = 1e-9


@dataclass(frozen=True)
class OrthoView:
    """An orthographic impostor view. Basis vectors are unit (3,) float64 in model space.

    right, up: the image's +x (columns) and +y (upwards; rows grow downwards); back: from the centre
    towards the camera, which sits CAMERA_DISTANCE_RADII · radius from the centre.
    """

    center: np.ndarray
    radius: float
    azimuth_deg: float
    elevation_deg: float
    size: int
    right: np.ndarray
    up: np.ndarray
    back: np.ndarray


def view_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit (3,) vector from the centre towards the camera (SPEC.md)."""
    azimuth, elevation = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.sin(azimuth) * np.cos(elevation), np.sin(elevation), np.cos(azimuth) * np.cos(elevation)])


def ortho_view(center, radius: float, azimuth_deg: float, elevation_deg: float, size: int) -> OrthoView:
    """The SPEC.md camera for (azimuth, elevation) framing the sphere (center, radius) in size² texels.

    At ±90° elevation +Y is parallel to the view, and world +Z serves as up instead (as
    crowdbake.render.offscreen.look_at does).
    """
    center = np.asarray(center, dtype=np.float64).reshape(3)
    if not radius > 0 or size < 1:
        raise ValueError(f"ortho_view: radius must be positive and size at least 1, got {radius}, {size}")
    back = view_direction(azimuth_deg, elevation_deg)
    right = _cross3(np.array([0.0, 1.0, 0.0]), back)
    if np.linalg.norm(right) < _PARALLEL:
        right = _cross3(np.array([0.0, 0.0, 1.0]), back)
    right /= np.linalg.norm(right)
    up = _cross3(back, right)
    return OrthoView(center, float(radius), float(azimuth_deg), float(elevation_deg), int(size), right, up, back)


def _cross3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(3,) u x v with np.cross's arithmetic (a product minus a product per component), without its set-up
    (a ring of views builds two cameras a view)."""
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def project(view: OrthoView, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Texel-space xy (..., 2) and depth (...) of (..., 3) model-space points, float64.

    x grows to the right, y downwards, both in texels (the image spans 0 .. size); depth is the distance
    from the eye along the view axis in metres (smaller is nearer).
    """
    offset = np.asarray(points, dtype=np.float64) - view.center
    scale = view.size / (2.0 * view.radius)
    x = (offset @ view.right + view.radius) * scale
    y = (view.radius - offset @ view.up) * scale
    depth = CAMERA_DISTANCE_RADII * view.radius - offset @ view.back
    return np.stack([x, y], axis=-1), depth


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample an (h, w, 4) uint8 texture at (N, 2) glTF uv (REPEAT): (N, 4) float64 in 0..255.

    RGB is bilinear between texel centres; alpha is the nearest texel's, because alpha holds region codes
    (SPEC.md), which are labels: a blend of codes 3 and 5 is not code 4.
    """
    texture = np.asarray(texture)
    height, width = texture.shape[:2]
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    x = uv[:, 0] * width - 0.5
    y = uv[:, 1] * height - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    x1, y1 = (x0 + 1) % width, (y0 + 1) % height
    x0, y0 = x0 % width, y0 % height
    # Gather whole RGBA texels as one 32-bit word each from the flat texture (one memory access per texel,
    # not three through 2D fancy indexing), then read their bytes.
    words = np.ascontiguousarray(texture, dtype=np.uint8).view(np.uint32).reshape(-1)

    def texel(rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
        gathered = words.take(rows * width + columns).view(np.uint8).reshape(-1, 4)
        return gathered[:, :3].astype(np.float64)  # gather first: converting the whole texture costs more

    colour = (
        texel(y0, x0) * (1 - fx) * (1 - fy) + texel(y0, x1) * fx * (1 - fy) + texel(y1, x0) * (1 - fx) * fy + texel(y1, x1) * fx * fy
    )
    nearest_x = np.floor(uv[:, 0] * width).astype(np.int64) % width
    nearest_y = np.floor(uv[:, 1] * height).astype(np.int64) % height
    alpha = words.take(nearest_y * width + nearest_x).view(np.uint8).reshape(-1, 4)[:, 3].astype(np.float64)
    return np.concatenate([colour, alpha[:, None]], axis=1)


def face_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T, 3) float64 unnormalised face normals (p1 - p0) x (p2 - p0): winding order, area-weighted."""
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    a = positions[faces[:, 0]]
    u, v = positions[faces[:, 1]] - a, positions[faces[:, 2]] - a
    # np.cross's own arithmetic (each component a product minus a product), without its per-call set-up.
    return np.stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1], u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2], u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]], axis=-1)
