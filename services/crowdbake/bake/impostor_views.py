"""Orthographic impostor views and what covers their texels: cameras, projection, triangle ids, exact
coverage, texture sampling and the background fill, shared by the maps a bake ships (drawn by
crowdbake.render.map_shader) and their exact reference (crowdbake.bake.reference.impostor_maps).

Dobbyn et al. 2006, sections 4 and 5: per viewpoint of a ring, the impostor's maps. The GL side
(crowdbake.render.impostor) renders only *which triangle* covers each texel centre: every triangle drawn
in one flat colour, its index + 1 in 24 bits, with no lighting, blending, or filtering; the coverage is
then resolved here in float64:

- The views are orthographic, so a triangle's projection is an affine map and the barycentric coordinates
  of a texel centre are exact 2D arithmetic (no perspective correction).
- The silhouette: a texel belongs to a triangle only if its centre lies inside it (GL's rasterisation rule).
  Texels whose id fails that test (a multisampled resolve mixing two ids, say) are rasterised here
  instead: the nearest triangle that contains the centre, or none (the texel is left empty). Barycentrics are
  clamped into the triangle, so no texel carries a texture coordinate from outside its triangle: the
  filtering artefact the paper describes in section 5 cannot arise.

Conventions (SPEC.md): the camera for azimuth θ and elevation φ sits in direction
(sin θ cos φ, sin φ, cos θ cos φ) from the bounds' centre, looks at it with +Y up, and sees a square of
2·radius metres. Texel (row, column) has its centre at (column + 0.5, row + 0.5) in pixel units, rows top
first. Pure numpy/scipy; no GL.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.short_rows import row_min, row_norm, row_sum

# The camera sits this many radii from the centre: the sphere of the bounds then lies at depths 2r .. 4r,
# well inside the clip range used by the renderer (1.5r .. 4.5r). Same as crowdbake.render.offscreen.
CAMERA_DISTANCE_RADII = 3.0
# A texel centre counts as inside a triangle up to this distance (pixels) outside an edge. GL rasterisers
# snap vertices to a sub-pixel grid (8 bits under llvmpipe: errors up to ~0.002 px were measured; 4 bits
# on some GPUs: 1/16 px), so the triangle GL filled can differ from the exact one by that much. Accepting
# such a texel costs nothing: its barycentrics are clamped onto the triangle's edge.
INSIDE_TOLERANCE_PX = 1.0 / 16.0
# When the renderer's depth is available, a triangle is accepted for a texel only if its interpolated
# depth agrees with the depth buffer within this fraction of the bounding radius (24-bit depth over a range
# of 3 radii resolves ~2e-7 r; the margin covers float32 transforms).
DEPTH_TOLERANCE_RADII = 1e-3
# Below this length an up vector is parallel to the viewing direction (looking straight down or up).
_PARALLEL = 1e-9
# 24 bits of triangle id: RGB8, id + 1 so that 0 is the background.
MAX_TRIANGLES = (1 << 24) - 1


@dataclass(frozen=True)
class OrthoView:
    """An orthographic impostor view. Basis vectors are unit (3,) float64 in model space.

    right, up: the image's +x (columns) and +y (upwards; rows grow downwards); back: from the centre
    towards the camera. eye = centre + CAMERA_DISTANCE_RADII · radius · back.
    """

    center: np.ndarray
    radius: float
    azimuth_deg: float
    elevation_deg: float
    size: int
    right: np.ndarray
    up: np.ndarray
    back: np.ndarray

    @property
    def eye(self) -> np.ndarray:
        return self.center + CAMERA_DISTANCE_RADII * self.radius * self.back

    def camera_pose(self) -> np.ndarray:
        """(4, 4) float64 camera-to-world matrix (camera looks down its -Z), as pyrender wants it."""
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = self.right, self.up, self.back, self.eye
        return pose

    @property
    def clip_range(self) -> tuple[float, float]:
        """(znear, zfar) in metres from the eye that hold the whole bounding sphere with margin."""
        return (CAMERA_DISTANCE_RADII - 1.5) * self.radius, (CAMERA_DISTANCE_RADII + 1.5) * self.radius


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


def triangle_id_colours(triangle_count: int) -> np.ndarray:
    """(T, 3) uint8 colours encoding triangle index + 1 in 24 bits, little end in red."""
    if not 0 < triangle_count <= MAX_TRIANGLES:
        raise ValueError(f"triangle_id_colours: 1 .. {MAX_TRIANGLES} triangles, got {triangle_count}")
    code = np.arange(1, triangle_count + 1, dtype=np.uint32)
    return np.stack([code & 255, (code >> 8) & 255, (code >> 16) & 255], axis=-1).astype(np.uint8)


def decode_triangle_ids(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3+) uint8 id image -> (H, W) int64 triangle index, -1 for the background."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] < 3 or rgb.dtype != np.uint8:
        raise ValueError(f"decode_triangle_ids: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    code = rgb[..., 0].astype(np.int64) | (rgb[..., 1].astype(np.int64) << 8) | (rgb[..., 2].astype(np.int64) << 16)
    return code - 1


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

    ids: (H, W) int64 from decode_triangle_ids (H = W = view.size); positions: (V, 3) model space;
    faces: (T, 3) int; depth: optional (H, W) float eye-space depth in metres (0 = nothing drawn) to reject
    an id whose triangle lies elsewhere along the ray. One view of resolve_coverage_views.
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

    ids: (V, S, S) int64 from decode_triangle_ids, S = every view's size; depth: optional (V, S, S) eye
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


def nearest_inside(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(rows, columns) (H, W) of the nearest texel inside `mask` for every texel; None if mask is empty or full."""
    from scipy import ndimage  # a third of a second to import; only the background fill needs it

    if not mask.any() or mask.all():
        return None
    _, (rows, columns) = ndimage.distance_transform_edt(~mask, return_indices=True)
    return rows, columns


def flatten_empty_blocks(image: np.ndarray, mask: np.ndarray, block: int = 4) -> np.ndarray:
    """Copy of (..., H, W, C) `image` whose block x block tiles holding no texel of the (..., H, W) `mask`
    are one flat colour (their top-left texel's). A flat block compresses exactly and needs no encoder
    effort; only blocks on the silhouette need the dilated values. Leading axes are independent images
    (views). Sizes that are not multiples of `block` are left unchanged."""
    height, width = mask.shape[-2:]
    out = image.copy()
    if height % block or width % block:
        return out
    lead = mask.shape[:-2]
    rows, columns = height // block, width // block
    empty = ~mask.reshape(lead + (rows, block, columns, block)).any(axis=(-3, -1))  # (..., rows, columns)
    tiles = out.reshape(lead + (rows, block, columns, block, -1))
    corner = tiles[..., :1, :, :1, :]  # (..., rows, 1, columns, 1, C)
    tiles[:] = np.where(empty[..., :, None, :, None, None], corner, tiles)
    return out


def dilate_into_background(image: np.ndarray, mask: np.ndarray, nearest: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Copy of (H, W, C) `image` whose texels outside `mask` take the value of the nearest texel inside.

    Block compression fits each 4x4 block's endpoints to all 16 texels; filling the background with the
    silhouette's own values keeps it from spending precision on texels nobody sees. Unchanged if mask is
    empty. nearest: nearest_inside(mask), when the caller already has it.
    """
    if nearest is None:
        nearest = nearest_inside(mask)
    if nearest is None:
        return image.copy()
    return image[nearest[0], nearest[1]]


def nearest_inside_views(masks: np.ndarray) -> np.ndarray:
    """(V, H, W) int64 flat index into a (V * H * W) stack of the nearest texel inside each view's mask
    (nearest_inside per view, whose distance transform stays 2D); a view whose mask is empty or full
    points at itself."""
    count, height, width = masks.shape
    index = np.arange(count * height * width, dtype=np.int64).reshape(count, height, width)
    for k in range(count):
        nearest = nearest_inside(masks[k])
        if nearest is not None:
            index[k] = k * height * width + nearest[0] * width + nearest[1]
    return index


# Coverage below this share of a texel stores as alpha 0 (SPEC.md: 4-bit alpha rounds it away).
MIN_COVERAGE = 1.0 / 30.0


def extend_to_partial_texels(mask: np.ndarray, coverage: np.ndarray, maps: list[np.ndarray]) -> np.ndarray:
    """Give the texels the mesh covers only in part (their centre outside `mask`) the values of their
    view's nearest covered texel, in place, and return the extended mask.

    mask: (V, S, S) bool, texel centres the mesh covers; coverage: (V, S, S) float 0..1, the share of each
    texel the mesh covers (supersampled); maps: (V, S, S, C) images of those views. A soft silhouette is
    drawn from these texels too (SPEC.md "Impostor maps", the surface map's alpha): they need a surface
    point to colour, light and reproject, and the nearest covered one is the surface beside them."""
    partial = (np.asarray(coverage) >= MIN_COVERAGE) & ~mask
    if not partial.any():
        return mask
    nearest = nearest_inside_views(mask).reshape(-1)
    chosen = partial.reshape(-1)
    for image in maps:
        flat = image.reshape(-1, image.shape[-1])
        flat[chosen] = flat[nearest[chosen]]
    return mask | partial


def fill_background(mask: np.ndarray, maps: list[np.ndarray], unflattened: list[np.ndarray] = ()) -> np.ndarray:
    """Give the texels outside `mask` the RGB of their view's nearest covered texel, in place.

    mask: (V, S, S) bool; maps, unflattened: (V, S, S, C >= 3) images of those views (alpha left alone).
    The 4 x 4 blocks of `maps` holding no covered texel are then made flat (flatten_empty_blocks); those
    of `unflattened` keep the filled values. Returns the flat index (V·S·S,) of every texel's nearest
    covered texel (nearest_inside_views).

    Block compression fits each block's endpoints to all 16 texels: filling the background with the
    silhouette's own values keeps it from spending precision on texels nobody sees, and a flat block
    costs the encoder nothing. Both map makers end here: view_maps_views (numpy, float64) and
    crowdbake.render.map_shader (a shader)."""
    shape = mask.shape
    nearest = nearest_inside_views(mask).reshape(-1)
    for image in maps:
        image[..., :3] = flatten_empty_blocks(image[..., :3].reshape(-1, 3)[nearest].reshape(shape + (3,)), mask)
    for image in unflattened:
        image[..., :3] = image[..., :3].reshape(-1, 3)[nearest].reshape(shape + (3,))
    return nearest
