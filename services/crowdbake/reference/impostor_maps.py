"""The impostor maps computed exactly per texel in float64: the reference the bake's shader
(crowdbake.render.map_shader) is tested against, not what a bake ships.

Dobbyn et al. 2006, sections 4 and 5: per view a normal map (normals as RGB), a detail map (diffuse RGBA
with the colour regions in alpha) and the paper's UV map (texture coordinates as colour). From a view's
exact coverage (crowdbake.reference.coverage): texture coordinates interpolated with the barycentrics and
stored in 16 bits; normals interpolated and normalised; the detail map samples the diffuse texture at the
interpolated UV. Nothing passes through 8-bit colour before the maps' own encodings. The surface map's
depth and motion come from the same coverage (surface_fields).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.impostor_views import OrthoView, face_normals, sample_texture
from crowdbake.reference.coverage import Coverage, interpolate, shading_normals_at, wrap_uv
from crowdbake.stages.impostors import fill_background, nearest_inside


def shading_normals(view: OrthoView, normals: np.ndarray, positions: np.ndarray, faces: np.ndarray, coverage: Coverage) -> np.ndarray:
    """Unit model-space normals at covered texels, (H, W, 3) float64 (zero elsewhere).

    Interpolated vertex normals, normalised. Where the camera sees a triangle's back (the inside of a skirt,
    drawn double-sided), the normal is flipped to face the camera, as double-sided shading does.
    """
    faces = np.asarray(faces, dtype=np.int64)
    mask = coverage.mask
    hit = coverage.triangle[mask]
    bary = coverage.barycentric[mask]
    interpolated = np.einsum("nk,nkc->nc", bary, np.asarray(normals, dtype=np.float64)[faces[hit]])
    out = np.zeros(coverage.triangle.shape + (3,), dtype=np.float64)
    out[mask] = shading_normals_at(np.broadcast_to(view.back, interpolated.shape), interpolated, face_normals(positions, faces[hit]))
    return out


def footprints(view: OrthoView, coverage: Coverage, supersample: int, normals: np.ndarray, positions: np.ndarray,
               faces: np.ndarray) -> np.ndarray:
    """Each texel's footprint from a view supersample x the tile (its exact coverage `coverage`, of size
    S · supersample): (S, S, 4) float64, RGB the mean over the texel's supersample² samples of the shading
    normal (0 for a sample the mesh misses), alpha the share it covers. What crowdbake.render.map_shader's
    footprint pass draws, and whose direction the bake's normal map keeps."""
    normal = shading_normals(view, normals, positions, faces, coverage)
    fields = np.concatenate([normal, coverage.mask[..., None].astype(np.float64)], axis=-1)
    size = coverage.mask.shape[0] // supersample
    return fields.reshape(size, supersample, size, supersample, 4).mean(axis=(1, 3))


@dataclass(frozen=True)
class ViewMaps:
    """The three maps of one view (size² texels each), SPEC.md's encodings.

    normal: (S, S, 4) uint8, RGB = (n + 1) / 2, A = 255 inside, background filled from the silhouette;
    uv: (S, S, 4) uint16, R = u · 65535, G = v · 65535, B = material index, A = 65535 inside, 0 outside;
    detail: (S, S, 4) uint8, RGB = diffuse variation 0, A = region code · 17 inside, 0 outside.
    """

    normal: np.ndarray
    uv: np.ndarray
    detail: np.ndarray
    coverage: Coverage


def view_maps(
    view: OrthoView,
    coverage: Coverage,
    positions: np.ndarray,
    normals: np.ndarray,
    uvs: np.ndarray,
    faces: np.ndarray,
    triangle_material: np.ndarray,
    diffuse: list[np.ndarray],
) -> ViewMaps:
    """Normal, UV and detail maps of one view.

    positions, normals: (V, 3); uvs: (V, 2) glTF convention; faces: (T, 3); triangle_material: (T,) int
    material index of each triangle; diffuse: per material, its variation-0 texture (h, w, 4) uint8.
    One view of view_maps_views.
    """
    return view_maps_views([view], [coverage], positions, normals, uvs, faces, triangle_material, diffuse)[0]


def view_maps_views(
    views: list[OrthoView],
    coverages: list[Coverage],
    positions: np.ndarray,
    normals: np.ndarray,
    uvs: np.ndarray,
    faces: np.ndarray,
    triangle_material: np.ndarray,
    diffuse: list[np.ndarray],
) -> list[ViewMaps]:
    """view_maps for many views of one mesh: interpolation, shading normals and texture sampling run once
    over the covered texels of every view; only the background fill (a distance transform) is per view.

    Arguments as view_maps, with one Coverage per view (all of one size). Returns one ViewMaps per view.
    """
    faces = np.asarray(faces, dtype=np.int64)
    triangle_material = np.asarray(triangle_material, dtype=np.int64)
    if triangle_material.shape != (len(faces),):
        raise ValueError(f"view_maps: triangle_material must be ({len(faces)},), got {triangle_material.shape}")
    if triangle_material.size and (triangle_material.min() < 0 or triangle_material.max() >= len(diffuse)):
        raise ValueError(f"view_maps: a material index is outside 0 .. {len(diffuse) - 1}")
    views, coverages = list(views), list(coverages)
    if len(views) != len(coverages):
        raise ValueError(f"view_maps: {len(views)} views but {len(coverages)} coverages")
    if not views:
        return []
    triangles = np.stack([coverage.triangle for coverage in coverages])  # (V, S, S)
    if triangles.shape[1:] != (views[0].size, views[0].size):
        raise ValueError(f"view_maps: coverage is {triangles.shape[1:]}, the view {views[0].size}²")
    masks = triangles >= 0
    texel = np.flatnonzero(masks)  # the covered texels of every view, view by view, as flat indices
    which = texel // (triangles.shape[1] * triangles.shape[2])
    hit = triangles.reshape(-1)[texel]  # (N,)
    # Gathered view by view (the same order): stacking the views' barycentrics first would copy them all.
    bary = np.concatenate([
        coverage.barycentric.reshape(-1, 3)[np.flatnonzero(mask)] for coverage, mask in zip(coverages, masks)
    ])  # (N, 3)
    corners = faces[hit]  # (N, 3)

    def at_texels(values: np.ndarray) -> np.ndarray:
        return np.einsum("nk,nkc->nc", bary, np.asarray(values, dtype=np.float64)[corners])

    backs = np.stack([view.back for view in views])[which]
    normal = shading_normals_at(backs, at_texels(normals), face_normals(positions, faces)[hit])
    uv = wrap_uv(at_texels(uvs))
    material = triangle_material[hit]
    detail = np.zeros((len(hit), 4), dtype=np.float64)
    for index, texture in enumerate(diffuse):
        selected = material == index
        if selected.any():
            detail[selected] = sample_texture(texture, uv[selected])

    shape = masks.shape
    normal_map = np.zeros(shape + (4,), dtype=np.uint8)
    normal_map.reshape(-1, 4)[texel, :3] = np.clip(np.rint((normal + 1.0) * 0.5 * 255.0), 0, 255)
    normal_map[..., 3] = np.where(masks, 255, 0)
    uv_map = np.zeros(shape + (4,), dtype=np.uint16)
    uv_texels = np.empty((len(texel), 4), dtype=np.uint16)
    uv_texels[:, :2] = np.clip(np.rint(uv * 65535.0), 0, 65535)
    uv_texels[:, 2] = material
    uv_texels[:, 3] = 65535
    uv_map.reshape(-1, 4)[texel] = uv_texels
    detail_map = np.zeros(shape + (4,), dtype=np.uint8)
    detail_map.reshape(-1, 4)[texel] = np.clip(np.rint(detail), 0, 255)
    fill_background(masks, [normal_map, detail_map])
    return [ViewMaps(normal_map[k], uv_map[k], detail_map[k], coverage) for k, coverage in enumerate(coverages)]


def surface_fields(view: OrthoView, coverage: Coverage, positions: np.ndarray,
                   next_positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(depth (S, S) metres along view.back from view.center, motion (S, S, 2) metres along view.right and
    view.up) of one view's coverage, dilated into the background: the exact surface map before its
    encoding (crowdbake.bake.surface_maps.encode_surface), the reference of the map shader's surface target.

    positions: (V, 3) model-space vertices at this baked frame; next_positions: (V, 3) where they are after
    the motion (crowdbake.bake.surface_maps.motion_positions); faces: (T, 3). The motion is that of the
    surface point the texel shows (same triangle, same barycentrics)."""
    mask = coverage.mask
    points = interpolate(positions, faces, coverage)
    moved = interpolate(next_positions, faces, coverage) - points
    depth = np.where(mask, (points - view.center) @ view.back, 0.0)
    motion = np.where(mask[..., None], np.stack([moved @ view.right, moved @ view.up], axis=-1), 0.0)
    nearest = nearest_inside(mask)
    if nearest is not None:
        depth, motion = depth[nearest], motion[nearest]
    return depth, motion
