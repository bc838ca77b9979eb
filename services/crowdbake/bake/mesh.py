"""Triangle-mesh helpers every stage shares: vertex normals, edges and their lengths, point-cache checks.

Pure numpy/scipy, no I/O. Triangles are counter-clockwise seen from outside (glTF/OBJ convention);
faces are (T, 3) integer indices into the vertices; a point cache is (frames, vertices, 3).
"""
from __future__ import annotations

import numpy as np
from scipy import sparse


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
    rows = weld[faces].reshape(-1)
    cols = np.repeat(np.arange(len(faces)), 3)
    incidence = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(slots, len(faces)))
    stacked = face_normals.transpose(1, 0, 2).reshape(len(faces), -1)  # (T, frames * 3)
    summed = (incidence @ stacked).reshape(slots, -1, 3).transpose(1, 0, 2)[:, weld]
    length = np.linalg.norm(summed, axis=-1, keepdims=True)
    normals = np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)
    return normals.reshape(*lead, vertex_count, 3)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges of (T, 3) triangles -> (E, 2) int64, each once, sorted."""
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"unique_edges: expected (T, 3) faces, got shape {faces.shape}")
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def edge_lengths(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Lengths of (E, 2) edges in (..., V, 3) points: (..., E) float64."""
    points = np.asarray(points, dtype=np.float64)
    return np.linalg.norm(points[..., edges[:, 1], :] - points[..., edges[:, 0], :], axis=-1)


def as_point_frames(points: np.ndarray, name: str, dtype=np.float64) -> np.ndarray:
    """Check a (frames, vertices, 3) array; convert to `dtype` (None: keep it, so slicing a big cache copies nothing)."""
    points = np.asarray(points, dtype=dtype)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"{name}: expected a (frames, vertices, 3) array, got shape {points.shape}")
    return points
