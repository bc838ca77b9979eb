"""Which triangle covers each texel centre of a view, resolved exactly in float64 from a triangle-id render
(crowdbake.reference.triangle_ids), and the per-texel interpolation the exact maps and references
build on (crowdbake.reference.impostor_maps, mesh_reference): a test oracle, not what a bake ships.

Dobbyn et al. 2006, sections 4 and 5: per viewpoint of a ring, the impostor's maps. The id render says
only *which triangle* covers each texel centre; the coverage is then resolved here:

- The views are orthographic, so a triangle's projection is an affine map and the barycentric coordinates
  of a texel centre are exact 2D arithmetic (no perspective correction).
- The silhouette: a texel belongs to a triangle only if its centre lies inside it (GL's rasterisation rule).
  Texels whose id fails that test (a multisampled resolve mixing two ids, say) are rasterised here
  instead: the nearest triangle that contains the centre, or none (the texel is left empty). Barycentrics are
  clamped into the triangle, so no texel carries a texture coordinate from outside its triangle: the
  filtering artefact the paper describes in section 5 cannot arise.

Texel (row, column) has its centre at (column + 0.5, row + 0.5) in pixel units, rows top first
(crowdbake.bake.impostor_views.project). Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.impostor_views import CAMERA_DISTANCE_RADII, OrthoView
from crowdbake.bake.short_rows import row_min, row_norm, row_sum

# A texel centre counts as inside a triangle up to this distance (pixels) outside an edge. GL rasterisers
# snap vertices to a sub-pixel grid (8 bits under llvmpipe: errors up to ~0.002 px were measured; 4 bits
# on some GPUs: 1/16 px), so the triangle GL filled can differ from the exact one by that much. Accepting
# such a texel costs nothing: its barycentrics are clamped onto the triangle's edge.
INSIDE_TOLERANCE_PX = 1.0 / 16.0

# When the renderer's depth is available, a triangle is accepted for a texel only if its interpolated
# depth agrees with the depth buffer within this fraction of the bounding radius (24-bit depth over a range
# of 3 radii resolves ~2e-7 r; the margin covers float32 transforms).
DEPTH_TOLERANCE_RADII = 1e-3


@dataclass(frozen=True)
class Coverage:
    """Which triangle covers each texel centre, and where in it.

    triangle: (H, W) int64, -1 where nothing covers the centre; barycentric: (H, W, 3) float64, clamped to
    the triangle (non-negative, summing to 1), zero where empty; repaired: texels whose rendered id was
    replaced or dropped by the inside test.
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    repaired: int

    @property
    def mask(self) -> np.ndarray:
        return self.triangle >= 0


def resolve_coverage(
    view: OrthoView,
    ids: np.ndarray,
    positions: np.ndarray,
    faces: np.ndarray,
    depth: np.ndarray | None = None,
) -> Coverage:
    """Exact per-texel coverage from a rendered id image.

    ids: (H, W) int64 triangle ids (crowdbake.reference.triangle_ids, -1 = background; H = W =
    view.size); positions: (V, 3) model space; faces: (T, 3) int; depth: optional (H, W) float eye-space
    depth in metres (0 = nothing drawn) to reject an id whose triangle lies elsewhere along the ray. One
    view of resolve_coverage_views.
    """
    ids = np.asarray(ids)
    if ids.shape != (view.size, view.size):
        raise ValueError(f"resolve_coverage: id image is {ids.shape}, the view is {view.size}²")
    return resolve_coverage_views([view], ids[None], positions, faces, None if depth is None else np.asarray(depth)[None])[0]


def resolve_coverage_views(
    views: list[OrthoView],
    ids: np.ndarray,
    positions: np.ndarray,
    faces: np.ndarray,
    depth: np.ndarray | None = None,
) -> list[Coverage]:
    """resolve_coverage for V views of one mesh at once: one pass of numpy over every covered texel of
    every view, instead of a pass per view (at 128² a view holds a few thousand texels, too few for numpy
    to amortise its per-call cost).

    ids: (V, S, S) int64 from triangle-id renders, S = every view's size; depth: optional (V, S, S) eye
    depth. Returns one Coverage per view, in order.
    """
    views = list(views)
    ids = np.asarray(ids, dtype=np.int64)
    faces = np.asarray(faces, dtype=np.int64)
    if not views:
        return []
    size = views[0].size
    if ids.shape != (len(views), size, size) or any(view.size != size for view in views):
        raise ValueError(f"resolve_coverage_views: id images are {ids.shape}, the views {[view.size for view in views]}²")
    if depth is not None and np.shape(depth) != ids.shape:
        raise ValueError(f"resolve_coverage_views: depth is {np.shape(depth)}, the id images {ids.shape}")
    screen, vertex_depth = project_views(views, positions)  # (V, P, 2), (V, P)
    triangle_count = len(faces)

    # Texels as flat indices into the (V, S, S) stack and corners as flat indices into the views' (V * P)
    # projected points: one integer gather per array instead of fancy indexing by three index arrays.
    texel = np.flatnonzero(ids >= 0)
    which, rows, columns = np.unravel_index(texel, ids.shape)
    candidate = ids.reshape(-1)[texel]
    in_range = candidate < triangle_count
    corner_index = faces[np.where(in_range, candidate, 0)].T + which * screen.shape[1]  # (3, N)
    screen_x, screen_y = screen[..., 0].reshape(-1), screen[..., 1].reshape(-1)
    distances, barycentric = _edge_distances_xy(screen_x[corner_index], screen_y[corner_index], columns + 0.5, rows + 0.5)
    accepted = in_range & (row_min(distances) >= -INSIDE_TOLERANCE_PX)
    if depth is not None:
        interpolated = row_sum(barycentric * vertex_depth.reshape(-1)[corner_index.T])
        radii = np.array([view.radius for view in views])
        accepted &= np.abs(interpolated - np.asarray(depth).reshape(-1)[texel]) <= DEPTH_TOLERANCE_RADII * radii[which]

    triangle = np.full(ids.shape, -1, dtype=np.int64)
    bary = np.zeros(ids.shape + (3,), dtype=np.float64)
    kept = texel[accepted]
    triangle.reshape(-1)[kept] = candidate[accepted]
    # Clamp into the triangle and renormalise, on the covered texels only.
    clamped = np.clip(barycentric[accepted], 0.0, None)
    total = row_sum(clamped)[:, None]
    np.divide(clamped, total, out=clamped, where=total > 0)
    bary.reshape(-1, 3)[kept] = clamped

    failed = ~accepted
    repaired = np.bincount(which[failed], minlength=len(views))
    for index in np.flatnonzero(repaired):
        mine = failed & (which == index)
        _repair(triangle[index], bary[index], rows[mine], columns[mine], screen[index][faces], vertex_depth[index][faces])
    return [Coverage(triangle[k], bary[k], int(repaired[k])) for k in range(len(views))]


def _repair(
    triangle: np.ndarray,
    bary: np.ndarray,
    rows: np.ndarray,
    columns: np.ndarray,
    corners: np.ndarray,
    corner_depth: np.ndarray,
) -> None:
    """Rasterise the failed texels in numpy: of every triangle whose box holds the texel centre, keep the
    nearest that really holds it (GL's depth test); if none does, the texel stays empty.

    Only the few texels whose rendered id failed get here, so testing them against every triangle's box
    is cheap, and unlike a search among the neighbours' ids it also finds slivers no other texel shows.
    """
    low = corners.min(axis=1) - INSIDE_TOLERANCE_PX  # (T, 2)
    high = corners.max(axis=1) + INSIDE_TOLERANCE_PX
    for row, column in zip(rows.tolist(), columns.tolist()):
        x, y = column + 0.5, row + 0.5
        options = np.flatnonzero((low[:, 0] <= x) & (x <= high[:, 0]) & (low[:, 1] <= y) & (y <= high[:, 1]))
        if options.size == 0:
            continue
        centre = np.tile([[x, y]], (len(options), 1))
        distances, barycentric = _edge_distances(corners[options], centre)
        margin = distances.min(axis=1)
        # Triangles that hold the centre exactly come first; the tolerance band only when none does
        # (otherwise a nearer triangle a hair away could win over the one GL would have drawn).
        inside = margin >= 0.0
        if not inside.any():
            inside = margin >= -INSIDE_TOLERANCE_PX
        if not inside.any():
            continue
        depth = (barycentric * corner_depth[options]).sum(axis=1)
        best = np.flatnonzero(inside)[np.argmin(depth[inside])]
        triangle[row, column] = options[best]
        clamped = np.clip(barycentric[best], 0.0, None)
        bary[row, column] = clamped / clamped.sum() if clamped.sum() > 0 else clamped


def project_views(views: list[OrthoView], points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """project() for V views at once: texel-space xy (V, P, 2) and depth (V, P) of (P, 3) points, float64."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centres = np.stack([view.center for view in views])  # (V, 3)
    radii = np.array([view.radius for view in views])
    scales = np.array([view.size / (2.0 * view.radius) for view in views])
    offset = points[None, :, :] - centres[:, None, :]  # (V, P, 3)

    def along(axis: str) -> np.ndarray:
        return np.einsum("vpc,vc->vp", offset, np.stack([getattr(view, axis) for view in views]))

    x = (along("right") + radii[:, None]) * scales[:, None]
    y = (radii[:, None] - along("up")) * scales[:, None]
    depth = CAMERA_DISTANCE_RADII * radii[:, None] - along("back")
    return np.stack([x, y], axis=-1), depth


def _edge_distances(corners: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances (N, 3) of points (N, 2) to the edges of triangles (N, 3, 2), positive inside,
    and barycentrics (N, 3). Degenerate triangles get -inf distances (never inside)."""
    corners = np.asarray(corners, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    return _edge_distances_xy(corners[..., 0].T, corners[..., 1].T, points[:, 0], points[:, 1])


def _edge_distances_xy(x: np.ndarray, y: np.ndarray, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """_edge_distances with the corners' coordinates as (3, N) arrays x, y (corner a, b, c by row) and the
    points' as (N,) px, py: the same arithmetic, operation for operation, on whole columns."""
    (ax, bx, cx), (ay, by, cy) = x, y

    def cross(ux: np.ndarray, uy: np.ndarray, vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
        return ux * vy - uy * vx

    def length(ux: np.ndarray, uy: np.ndarray) -> np.ndarray:
        return np.sqrt(ux * ux + uy * uy)  # bitwise row_norm of the (N, 2) edge vectors

    area = cross(bx - ax, by - ay, cx - ax, cy - ay)  # twice the signed area; its sign is the winding on screen
    weights = np.stack([
        cross(cx - bx, cy - by, px - bx, py - by), cross(ax - cx, ay - cy, px - cx, py - cy), cross(bx - ax, by - ay, px - ax, py - ay),
    ], axis=-1)
    valid = np.abs(area) > 1e-12
    sign = np.where(area < 0, -1.0, 1.0)[:, None]
    lengths = np.stack([length(cx - bx, cy - by), length(ax - cx, ay - cy), length(bx - ax, by - ay)], axis=-1)
    distances = np.where(valid[:, None], sign * weights / np.maximum(lengths, 1e-300), -np.inf)
    barycentric = np.where(valid[:, None], weights / np.where(valid, area, 1.0)[:, None], 0.0)
    return distances, barycentric


def interpolate(values: np.ndarray, faces: np.ndarray, coverage: Coverage) -> np.ndarray:
    """Per-vertex values (V, C) interpolated at every covered texel: (H, W, C) float64, zero elsewhere."""
    values = np.asarray(values, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    out = np.zeros(coverage.triangle.shape + (values.shape[1],), dtype=np.float64)
    mask = coverage.mask
    corners = values[faces[coverage.triangle[mask]]]  # (N, 3, C)
    out[mask] = np.einsum("nk,nkc->nc", coverage.barycentric[mask], corners)
    return out


def wrap_uv(uv: np.ndarray) -> np.ndarray:
    """Texture coordinates into [0, 1] under glTF's default REPEAT wrap (values inside are kept, 1 stays 1)."""
    uv = np.asarray(uv, dtype=np.float64)
    outside = (uv < 0.0) | (uv > 1.0)
    return np.where(outside, uv - np.floor(uv), uv)


def shading_normals_at(back: np.ndarray, interpolated: np.ndarray, face_normal: np.ndarray) -> np.ndarray:
    """Unit shading normals (N, 3) from interpolated vertex normals (N, 3), the face normals of the
    triangles hit (N, 3) and each texel's view direction back (N, 3) (see shading_normals)."""
    facing_away = row_sum(face_normal * back) < 0
    sign = np.where(facing_away, -1.0, 1.0)[:, None]
    chosen = interpolated * sign
    length = row_norm(chosen)[:, None]
    # A zero interpolated normal (opposite vertex normals) falls back to the face normal.
    chosen = np.where(length > 1e-12, chosen, face_normal * sign)
    chosen /= np.maximum(row_norm(chosen), 1e-300)[:, None]
    return chosen
