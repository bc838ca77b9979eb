"""The low LOD (crowdbake.bake.lod, crowdbake.bake.poses.low_lod): meshoptimizer keeps a vertex subset,
hits its triangle target, keeps garment borders and UV seams, and every frame's motion carries over."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import lod, poses


def skirt(rings: int = 24, columns: int = 48, frames: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An open, flaring tube (a skirt): positions (F, V, 3), faces (T, 3), uvs (V, 2).

    Like a garment exported to OBJ and split by crowdbake.formats.obj, the UV seam is a column of
    duplicated vertices: same positions, u = 0 on one side and u = 1 on the other. The hem and the waist
    are open borders. Each frame sways the hem.
    """
    heights = np.linspace(1.0, 0.3, rings)
    angles = np.linspace(0.0, 2 * np.pi, columns + 1)  # column `columns` duplicates column 0
    frame_positions = []
    for frame in range(frames):
        radius = 0.15 + 0.25 * (1.0 - heights)[:, None] * (1.0 + 0.1 * np.sin(3 * angles + frame))[None, :]
        x = radius * np.sin(angles)[None, :]
        z = radius * np.cos(angles)[None, :]
        y = np.broadcast_to(heights[:, None], x.shape)
        points = np.stack([x, y, z], axis=-1)
        points[:, -1] = points[:, 0]  # the seam: exactly equal positions
        frame_positions.append(points.reshape(-1, 3))
    u, v = np.meshgrid(angles / (2 * np.pi), np.linspace(0.0, 1.0, rings))
    uvs = np.stack([u, v], axis=-1).reshape(-1, 2)
    index = np.arange(rings * (columns + 1)).reshape(rings, columns + 1)
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return np.asarray(frame_positions, dtype=np.float32), faces.astype(np.uint32), uvs.astype(np.float32)


def welded_boundary(positions: np.ndarray, faces: np.ndarray) -> set[tuple[tuple[float, ...], tuple[float, ...]]]:
    """Open-border edges as pairs of positions (seam-independent)."""
    edges = lod.boundary_edges(positions, faces)
    weld = lod.weld_by_position(positions)
    coordinates = {int(w): tuple(np.round(positions[int(w)], 6)) for w in np.unique(weld)}
    return {tuple(sorted((coordinates[int(a)], coordinates[int(b)]))) for a, b in edges}


@pytest.mark.parametrize("target", [400, 900])
def test_garment_lod_hits_target_keeps_subset_border_and_seam(target):
    positions, faces, uvs = skirt()
    simplified = lod.simplify(positions[0], faces, target, uvs=uvs, lock_border=True)
    assert abs(simplified.triangle_count - target) <= lod.TARGET_TOLERANCE * target
    assert simplified.locked_border
    # A subset: kept indices are distinct input vertices and the faces only use them.
    assert np.all(np.diff(simplified.kept) > 0) and simplified.kept.max() < len(positions[0])
    assert simplified.faces.max() == len(simplified.kept) - 1
    # Every hem and waist vertex stays, so the outline of the garment does not change.
    border = np.flatnonzero(lod.border_vertex_mask(positions[0], faces))
    assert len(border) > 0 and np.isin(border, simplified.kept).all()
    # No cracks: welded by position, the low LOD's open borders are exactly the input's (the UV seam
    # collapsed on both sides alike, or it would show up here as new border edges).
    low_positions = positions[0][simplified.kept]
    assert welded_boundary(low_positions, simplified.faces) == welded_boundary(positions[0], faces)
    # Both sides of the seam are still there, with their own u.
    seam_u = uvs[simplified.kept][np.isclose(low_positions[:, 0], 0.0, atol=1e-6) & (low_positions[:, 2] > 0), 0]
    assert {0.0, 1.0} <= set(np.round(seam_u, 6))


def test_low_lod_carries_every_frame_over():
    positions, faces, uvs = skirt(frames=4)
    normals = poses.pose_normals(positions, faces, weld=lod.weld_by_position(positions[0]))
    high = poses.PartPoses(faces, uvs, positions, normals)
    simplified = lod.simplify(positions[0], faces, 500, uvs=uvs, lock_border=True)
    low = poses.low_lod(high, simplified)
    assert low.frame_count == 4 and low.triangle_count == simplified.triangle_count
    for frame in range(4):
        np.testing.assert_array_equal(low.positions[frame], positions[frame][simplified.kept])
        np.testing.assert_array_equal(low.normals[frame], normals[frame][simplified.kept])
    np.testing.assert_array_equal(low.uvs, uvs[simplified.kept])


def test_seam_vertices_share_one_normal():
    positions, faces, uvs = skirt(frames=1)
    welded = poses.pose_normals(positions, faces, weld=lod.weld_by_position(positions[0]))[0]
    split = poses.pose_normals(positions, faces)[0]
    columns = 49
    first, last = np.arange(0, len(uvs), columns), np.arange(columns - 1, len(uvs), columns)
    np.testing.assert_allclose(welded[first], welded[last], atol=1e-6)
    assert np.abs(split[first] - split[last]).max() > 0.05, "without welding the seam would show"
    np.testing.assert_allclose(np.linalg.norm(welded, axis=-1), 1.0, atol=1e-5)


def test_border_gives_way_only_when_the_target_is_unreachable():
    positions, faces, uvs = skirt(rings=6, columns=64)
    border = lod.border_vertex_mask(positions[0], faces).sum()
    # 130 border vertices need more than 60 triangles to stay put: the lock is dropped, with a warning.
    simplified = lod.simplify(positions[0], faces, 60, uvs=uvs, lock_border=True)
    assert border > 100 and not simplified.locked_border
    assert abs(simplified.triangle_count - 60) <= lod.TARGET_TOLERANCE * 60


def test_body_of_a_real_character(shared_asset):
    from crowdbake.formats.gltf import load_character

    character = load_character(shared_asset("CesiumMan.glb"))
    target = int(round(len(character.faces) * lod.PAPER_LOD_RATIO))
    simplified = lod.simplify(character.positions, character.faces, target, uvs=character.uvs)
    assert abs(simplified.triangle_count - target) <= lod.TARGET_TOLERANCE * target
    assert np.isin(simplified.kept, np.arange(len(character.positions))).all()
    assert simplified.relative_error < 0.05  # a few percent of the body's extent


def test_target_split_over_parts_is_exact():
    assert lod.target_for_parts([13056 - 4000, 4000], 1899) == [1317, 582]
    assert sum(lod.target_for_parts([5712, 4176], 1000)) == 1000
    with pytest.raises(ValueError):
        lod.target_for_parts([10, 0], 5)
    with pytest.raises(ValueError):
        lod.target_for_parts([10, 10], 1)


def test_target_above_input_keeps_the_mesh():
    positions, faces, uvs = skirt(rings=4, columns=8, frames=1)
    simplified = lod.simplify(positions[0], faces, 10_000)
    assert simplified.triangle_count == len(faces)
    np.testing.assert_array_equal(simplified.kept, np.arange(len(positions[0])))


def flat_shaded_balls(count: int, segments: int = 12, rings: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """`count` faceted balls in a row, flat-shaded as exporters write them: every triangle's corners are
    vertices of their own, so every edge is a normal seam and no two triangles share a vertex index."""
    theta = np.linspace(0.0, np.pi, rings + 1)
    phi = np.linspace(0.0, 2 * np.pi, segments + 1)
    grid = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.cos(theta)[:, None] * np.ones_like(phi),
                     np.sin(theta)[:, None] * np.sin(phi)], axis=-1)
    triangles = []
    for i in range(rings):
        for j in range(segments):
            a, b, c, d = grid[i, j], grid[i, j + 1], grid[i + 1, j], grid[i + 1, j + 1]
            triangles += [(a, c, b), (b, c, d)]
    ball = np.array([t for t in triangles if np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) > 1e-9])
    positions = np.concatenate([ball.reshape(-1, 3) + [3.0 * k, 0.0, 0.0] for k in range(count)]).astype(np.float32)
    return positions, np.arange(len(positions)).reshape(-1, 3)


def test_a_flat_shaded_mesh_of_many_parts_still_gets_near_its_target():
    """Regression: a flat-shaded robot of 14 parts kept 3,224 of 3,237 triangles for a target of 431, since
    edge collapses cannot cross its normal seams; vertex clustering (the fallback) reduces it, to a subset
    of its vertices as every low LOD."""
    positions, faces = flat_shaded_balls(10)
    low = lod.simplify(positions, faces, len(faces) // 6)
    assert 0 < len(low.faces) <= len(faces) // 6 * 1.25, (len(low.faces), len(faces))
    assert np.all(np.diff(low.kept) > 0) and low.kept.max() < len(positions)
    assert low.faces.max() < len(low.kept)
