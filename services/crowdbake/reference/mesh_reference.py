"""The mesh as the fidelity scores see it at 1:1 pixel-to-texel, in float64: the reference of the mesh
pictures the bake draws with a shader (crowdbake.render.map_shader.draw_references).

Shaded per sample at `supersample`² samples per pixel (exact visibility, interpolated normals, the diffuse
texture sampled at the interpolated UV, crowdbake.bake.shading's light) and box-filtered down to the tile:
an anti-aliased rendering of the mesh.
"""
from __future__ import annotations

import numpy as np

from crowdbake.bake.impostor_views import OrthoView, face_normals
from crowdbake.reference.coverage import Coverage, shading_normals_at, wrap_uv
from crowdbake.bake.shading import apply_outfit, lambert, texels_at

# Samples per pixel side for the mesh reference (4 = 16 samples, the anti-aliasing of a good runtime).
DEFAULT_SUPERSAMPLE = 4


def mesh_reference(
    view: OrthoView,
    coverage: Coverage,
    supersample: int,
    positions: np.ndarray,
    normals: np.ndarray,
    uvs: np.ndarray,
    faces: np.ndarray,
    triangle_material: np.ndarray,
    diffuse: list[np.ndarray],
    outfit_row: np.ndarray,
    light: np.ndarray,
) -> np.ndarray:
    """The mesh, shaded and anti-aliased: (S, S, 3) float64 0..1, black background. The bake draws the
    same picture with a shader (crowdbake.render.map_shader.draw_references); this is its float64 reference.

    view, coverage: at S·supersample texels (view.size = S · supersample); the other arrays as in
    crowdbake.reference.impostor_maps.view_maps; diffuse: per material, the texture to use (h, w, 4) uint8.
    """
    if view.size % supersample:
        raise ValueError(f"mesh_reference: view size {view.size} is not a multiple of {supersample}")
    faces = np.asarray(faces, dtype=np.int64)
    size = view.size // supersample
    reference = np.zeros((size, size, 3), dtype=np.float64)
    # Shade the covered samples only (a character covers a seventh of its frame), as lists, and box-filter
    # only the block-aligned box around them: the rest of the picture is black either way. Per sample the
    # arithmetic is the whole-image one, operation for operation, so the picture is the same to the bit.
    rows, columns = np.nonzero(coverage.mask)
    if rows.size == 0:
        return reference
    hit = coverage.triangle[rows, columns]
    bary = coverage.barycentric[rows, columns]  # (N, 3)
    corners = faces[hit]  # (N, 3)

    def at_samples(values: np.ndarray) -> np.ndarray:
        return np.einsum("nk,nkc->nc", bary, np.asarray(values, dtype=np.float64)[corners])

    uv = wrap_uv(at_samples(uvs))
    material = np.asarray(triangle_material, dtype=np.int64)[hit]
    interpolated = at_samples(normals)
    shading = shading_normals_at(
        np.broadcast_to(view.back, interpolated.shape), interpolated, face_normals(positions, faces)[hit]
    )
    colour = lambert(apply_outfit(texels_at(uv, material, diffuse), outfit_row), shading, light)
    top, left = rows.min() // supersample, columns.min() // supersample
    bottom, right = rows.max() // supersample + 1, columns.max() // supersample + 1
    box = np.zeros(((bottom - top) * supersample, (right - left) * supersample, 3), dtype=np.float64)
    box[rows - top * supersample, columns - left * supersample] = colour
    reference[top:bottom, left:right] = box.reshape(bottom - top, supersample, right - left, supersample, 3).mean(axis=(1, 3))
    return reference
