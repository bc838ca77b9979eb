"""Test shapes with answers known by construction, shared by the impostor and fidelity tests."""
from __future__ import annotations

import numpy as np


def uv_sphere(rings: int = 24, segments: int = 48, radius: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """positions (V, 3), normals (V, 3), uvs (V, 2), faces (T, 3): a sphere without its polar caps, with a
    UV seam of duplicated vertices at u = 0 / 1 (as an OBJ with seams is split on import)."""
    latitude = np.linspace(0.08 * np.pi, 0.92 * np.pi, rings)
    longitude = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    lat, lon = np.meshgrid(latitude, longitude, indexing="ij")
    normals = np.stack([np.sin(lat) * np.sin(lon), np.cos(lat), np.sin(lat) * np.cos(lon)], axis=-1).reshape(-1, 3)
    uvs = np.stack([lon / (2 * np.pi), (lat - latitude[0]) / (latitude[-1] - latitude[0])], axis=-1).reshape(-1, 2)
    index = np.arange(rings * (segments + 1)).reshape(rings, segments + 1)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return normals * radius, normals, uvs, faces
