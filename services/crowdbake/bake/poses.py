"""Poses (paper section 4): the skinned body and the simulated cloth stored per frame of the cycle.

"Once the character's meshes are pre-simulated, they are then exported and stored in separate keyframed
meshes or 'poses'" (Dobbyn et al. 2006, section 4): nothing is skinned or simulated at run time. This module
holds the pure parts of that bake: which source times a cycle covers, cloth frames on split (seam) vertices,
normals that agree across UV seams, the low LOD carried over every frame, the impostors' frames and their
common framing. The skinning itself is crowdbake.bake.skinning; the I/O is crowdbake.stages.poses.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from crowdbake.bake.body_skin import BodySkin
from crowdbake.bake.lod import Simplified
from crowdbake.geometry import vertex_normals

# A vertex that belongs to no (non-degenerate) triangle has no normal of its own; the pose cache needs a
# unit vector anyway (SPEC.md), so it gets +Y. It is never drawn, so the choice cannot show.
FALLBACK_NORMAL = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class PartPoses:
    """One mesh part at one LOD over the cycle: what a CBPC file holds.

    faces: (T, 3) uint32, counter-clockwise; uvs: (V, 2) float32 (glTF convention, v down);
    positions, normals: (F, V, 3) float32, metres and unit vectors; skin: see below.
    """

    faces: np.ndarray
    uvs: np.ndarray
    positions: np.ndarray
    normals: np.ndarray
    # A body whose frames are these matrices skinning its rest mesh (positions, normals are those frames):
    # stored as a skinned pose cache (crowdbake.bake.body_skin). None: stored as vertex frames.
    skin: BodySkin | None = None
    # (V, 3) the pose the low LOD is simplified on, where it is not positions[0]: a skinned body keeps its
    # vertex frames' first pose, so the simplifier (sensitive to the last float bit) makes the same low mesh
    # whether the body is stored skinned or as vertex frames.
    simplify_pose: np.ndarray | None = None

    def __post_init__(self) -> None:
        frames, vertices, _ = self.positions.shape
        if self.normals.shape != self.positions.shape or self.uvs.shape != (vertices, 2):
            raise ValueError(
                f"PartPoses: positions {self.positions.shape}, normals {self.normals.shape}, uvs {self.uvs.shape} disagree"
            )

    @property
    def frame_count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def vertex_count(self) -> int:
        return int(self.positions.shape[1])

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])


def pose_normals(positions: np.ndarray, faces: np.ndarray, weld: np.ndarray | None = None) -> np.ndarray:
    """Unit vertex normals for a pose cache, (F, V, 3) float32, of (F, V, 3) positions and (T, 3) faces.

    crowdbake.geometry.vertex_normals (area-weighted; weld: (V,) int, the vertex each vertex is welded to,
    e.g. an OBJ's source_index, so a UV seam does not show as a lighting crease), with FALLBACK_NORMAL for
    the vertices of no triangle: the pose cache needs unit vectors.
    """
    positions = np.asarray(positions)
    if positions.ndim != 3 or positions.shape[2] != 3:
        raise ValueError(f"pose_normals: expected (F, V, 3) positions, got {positions.shape}")
    normals = vertex_normals(positions, faces, weld)
    return np.where(np.any(normals != 0, axis=-1, keepdims=True), normals, FALLBACK_NORMAL).astype(np.float32)


def unit_normals(normals: np.ndarray) -> np.ndarray:
    """(..., 3) float32 normals with near-zero ones (length <= 0.5) replaced by FALLBACK_NORMAL: a pose
    cache needs unit vectors (SPEC.md)."""
    normals = np.asarray(normals, dtype=np.float32)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    fixed = np.where(length > 0.5, normals / np.where(length > 0, length, 1.0), FALLBACK_NORMAL)
    return fixed.astype(np.float32)


def cloth_on_vertices(points: np.ndarray, source_index: np.ndarray) -> np.ndarray:
    """A point cache (F, P, 3) in OBJ position order onto the mesh's (seam-split) vertices: (F, V, 3) float32."""
    points = np.asarray(points, dtype=np.float32)
    source_index = np.asarray(source_index, dtype=np.int64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"cloth_on_vertices: expected (F, P, 3) points, got {points.shape}")
    if source_index.size and (source_index.min() < 0 or source_index.max() >= points.shape[1]):
        raise ValueError(
            f"cloth_on_vertices: the mesh refers to position {int(source_index.max())}, the cache has {points.shape[1]}"
        )
    return points[:, source_index]


def low_lod(high: PartPoses, simplified: Simplified) -> PartPoses:
    """The low LOD of a part: the simplified triangles over the kept vertices, every frame carried over."""
    kept = simplified.kept
    return PartPoses(
        faces=np.ascontiguousarray(simplified.faces, dtype=np.uint32),
        uvs=np.ascontiguousarray(high.uvs[kept]),
        positions=np.ascontiguousarray(high.positions[:, kept]),
        normals=np.ascontiguousarray(high.normals[:, kept]),
        skin=None if high.skin is None else high.skin.subset(kept),
    )


def impostor_frame_indices(cycle_frames: int, count: int) -> list[int]:
    """`count` cycle frames spread evenly over the cycle, ascending, starting at 0 (all of them if fewer).

    The paper bakes 10 frames of the walk (section 6); frame k is round(k · l / count).
    """
    if cycle_frames < 1 or count < 1:
        raise ValueError(f"impostor_frame_indices: need positive counts, got {cycle_frames} frames, {count} samples")
    if count >= cycle_frames:
        return list(range(cycle_frames))
    return sorted({int(np.floor(k * cycle_frames / count + 0.5)) % cycle_frames for k in range(count)})


def common_bounds(*positions: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (3,) float64 and radius of the sphere framing every given (F, V, 3) array in every frame.

    The centre is the middle of the axis-aligned box over all frames and parts, the radius half its
    diagonal: one framing for every frame, so impostors do not swim (SPEC.md, "Impostor maps").
    """
    if not positions:
        raise ValueError("common_bounds: no positions")
    low = np.min([np.asarray(p, dtype=np.float64).reshape(-1, 3).min(axis=0) for p in positions], axis=0)
    high = np.max([np.asarray(p, dtype=np.float64).reshape(-1, 3).max(axis=0) for p in positions], axis=0)
    if not (np.isfinite(low).all() and np.isfinite(high).all()):
        raise ValueError("common_bounds: positions contain NaN or infinity")
    centre = 0.5 * (low + high)
    radius = 0.5 * float(np.linalg.norm(high - low))
    if radius <= 0:
        raise ValueError("common_bounds: every position is the same point")
    return centre, radius
