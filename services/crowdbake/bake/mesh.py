"""Triangle-mesh helpers every stage shares: edges and their lengths, point-cache checks (vertex normals
are crowdbake.geometry's, which the file readers use too).

Pure numpy, no I/O. Triangles are counter-clockwise seen from outside (glTF/OBJ convention);
faces are (T, 3) integer indices into the vertices; a point cache is (frames, vertices, 3).
"""
from __future__ import annotations

import numpy as np


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
