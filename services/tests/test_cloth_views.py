"""Pass-2 pictures lit two-sided: the face winding of a cloth mesh cannot change what pass 2 sees."""
from __future__ import annotations

import numpy as np

from crowdbake.geometry import vertex_normals
from crowdbake.render.cloth_views import ClothViewRenderer, facing_normals


def wavy_skirt(rings: int = 12, segments: int = 48, phase: float = 0.0):
    """(V, 3) points of a cone with vertical folds, and (T, 3) triangles wound outwards."""
    t = np.linspace(0.0, 1.0, rings)[:, None]
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    radius = 0.15 + 0.15 * t + 0.02 * t * np.sin(7 * angle + phase)
    points = np.stack([radius * np.sin(angle), np.broadcast_to(1.0 - 0.6 * t, radius.shape), radius * np.cos(angle)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return points, faces


def test_facing_normals_ignore_the_sign_of_the_normal():
    points, faces = wavy_skirt()
    normals = vertex_normals(points, faces)
    towards = np.array([0.0, 0.2, 1.0]) / np.hypot(0.2, 1.0)
    facing = facing_normals(normals, towards)
    assert np.all(facing @ towards >= 0.0)
    np.testing.assert_array_equal(facing_normals(-normals, towards), facing)


def test_reversed_winding_renders_the_same_pictures():
    """An inward-wound mesh used to shade flat grey under one-sided lighting (its normals point away from
    the light), so Canny saw only silhouettes; lit two-sided it gives the outward mesh's pictures."""
    points, faces = wavy_skirt()
    frames = np.stack([wavy_skirt(phase=p)[0] for p in (0.0, 0.8)])
    outward = ClothViewRenderer(faces, views=3, size=96)(frames)
    inward = ClothViewRenderer(faces[:, ::-1], views=3, size=96)(frames)
    differing = np.mean(np.abs(outward.astype(int) - inward.astype(int)) > 2)
    assert differing < 0.002, differing
    # The folds shade: the cloth is not one flat grey (the pictures carry more than a silhouette).
    cloth = outward[0, 0][outward[0, 0] > 0]
    assert np.ptp(cloth) > 40
