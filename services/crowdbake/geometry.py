"""Geometry the file readers (crowdbake.formats) and the bake (crowdbake.bake) both use: area-weighted
vertex normals of a triangle mesh and rotation matrices of quaternions. Pure numpy/scipy, no I/O.

Triangles are counter-clockwise seen from outside (glTF/OBJ convention); faces are (T, 3) integer
indices into the vertices; quaternions are (x, y, z, w) and matrices act on column vectors.
"""
from __future__ import annotations

import numpy as np


def vertex_normals(positions: np.ndarray, faces: np.ndarray, weld: np.ndarray | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals of (..., V, 3) positions with (T, 3) triangles: (..., V, 3) float64.

    Counter-clockwise triangles face outwards. weld: optional (V,) int, the vertex each vertex is welded
    to (e.g. an OBJ's source_index): welded vertices share one normal, so a UV seam does not show as a
    lighting crease. Vertices that belong to no triangle, or only to degenerate ones, get a zero normal
    (a caller that needs unit vectors substitutes its own fallback).
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
    weld = np.arange(vertex_count) if weld is None else np.asarray(weld, dtype=np.int64)
    if weld.shape != (vertex_count,) or (vertex_count and weld.min() < 0):
        raise ValueError(f"vertex_normals: weld must be ({vertex_count},) non-negative indices")
    slots = int(weld.max()) + 1 if vertex_count else 0
    lead = positions.shape[:-2]
    flat = positions.reshape(-1, vertex_count, 3)
    a, b, c = flat[:, faces[:, 0]], flat[:, faces[:, 1]], flat[:, faces[:, 2]]
    face_normals = np.cross(b - a, c - a)  # length = 2 * area: the area weighting comes for free
    # Vertex-by-face incidence: one sparse product sums every frame's face normals onto the (welded) vertices.
    # scipy is imported here, not above: the impostor maps import this module and run without scipy on a
    # bare GPU machine (scripts/gpu-check/maps.py), where only what they call is carried.
    from scipy import sparse

    rows = weld[faces].reshape(-1)
    cols = np.repeat(np.arange(len(faces)), 3)
    incidence = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(slots, len(faces)))
    stacked = face_normals.transpose(1, 0, 2).reshape(len(faces), -1)  # (T, frames * 3)
    summed = (incidence @ stacked).reshape(slots, -1, 3).transpose(1, 0, 2)[:, weld]
    length = np.linalg.norm(summed, axis=-1, keepdims=True)
    normals = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
    return normals.reshape(*lead, vertex_count, 3)


def quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w), normalised here -> (..., 3, 3) rotation matrices (float64)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


# Work on at most this many (frame, vertex) pairs at once: bounds the (F, V, 4, 3, 4) gather.
SKIN_CHUNK_ELEMENTS = 1 << 19


def skin(
    positions: np.ndarray, normals: np.ndarray, joints: np.ndarray, weights: np.ndarray, matrices: np.ndarray,
    inverse_transpose_normals: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear blend skinning.

    positions, normals (V, 3); joints (V, 4) int; weights (V, 4) summing to 1; matrices (F, J, 4, 4)
    or (F, J, 3, 4) skinning matrices (crowdbake.bake.skinning.joint_matrices; a skinned pose cache's
    rows) -> positions (F, V, 3), unit normals (F, V, 3), float32.
    Normals blend the joints' inverse-transpose 3x3 blocks so non-uniform scale keeps them perpendicular
    (glTF's rule); with inverse_transpose_normals False they blend the 3x3 blocks themselves, as a skinned
    pose cache does (SPEC.md: the same for rotations and uniform scale, and linear in the matrices, so a
    blend of two poses' matrices turns normals as blending the two poses' normals does).
    """
    positions = np.asarray(positions, dtype=np.float32)
    normals = np.asarray(normals, dtype=np.float32)
    joints = np.asarray(joints, dtype=np.int64)
    weights = np.asarray(weights, dtype=np.float32)
    matrices = np.asarray(matrices, dtype=np.float32)
    vertex_count = len(positions)
    if positions.shape != (vertex_count, 3) or normals.shape != (vertex_count, 3):
        raise ValueError(f"positions and normals must be (V, 3), got {positions.shape} and {normals.shape}")
    if joints.shape != (vertex_count, 4) or weights.shape != (vertex_count, 4):
        raise ValueError(f"joints and weights must be ({vertex_count}, 4), got {joints.shape} and {weights.shape}")
    if matrices.ndim != 4 or matrices.shape[2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"matrices must be (F, J, 4, 4) or (F, J, 3, 4), got {matrices.shape}")
    if joints.size and (joints.min() < 0 or joints.max() >= matrices.shape[1]):
        raise ValueError(f"joint indices must lie in 0..{matrices.shape[1] - 1}")
    frame_count = matrices.shape[0]
    linear = matrices[:, :, :3, :3]
    normal_matrices = (np.linalg.inv(linear.astype(np.float64)).transpose(0, 1, 3, 2).astype(np.float32)
                       if inverse_transpose_normals else np.ascontiguousarray(linear))
    out_positions = np.empty((frame_count, vertex_count, 3), dtype=np.float32)
    out_normals = np.empty((frame_count, vertex_count, 3), dtype=np.float32)
    chunk = max(1, SKIN_CHUNK_ELEMENTS // max(vertex_count, 1))
    for start in range(0, frame_count, chunk):
        stop = min(frame_count, start + chunk)
        # (f, V, 4, 3, 4): the four influencing joints' top rows, blended by weight.
        blended = np.einsum("vk,fvkij->fvij", weights, matrices[start:stop][:, joints, :3, :])
        out_positions[start:stop] = np.einsum("fvij,vj->fvi", blended[..., :3], positions) + blended[..., 3]
        blended_normal = np.einsum("vk,fvkij->fvij", weights, normal_matrices[start:stop][:, joints])
        skinned = np.einsum("fvij,vj->fvi", blended_normal, normals)
        length = np.linalg.norm(skinned, axis=-1, keepdims=True)
        out_normals[start:stop] = np.divide(skinned, length, out=np.zeros_like(skinned), where=length > 0)
    return out_positions, out_normals
