"""Cloth as bones: a garment's loop decomposed into a few rigid bones with linear blend skinning, so it plays
as an ordinary skinned mesh with an ordinary glTF animation in any engine, no custom shader.

Smooth skinning decomposition (Le & Deng 2012, "Smooth Skinning Decomposition with Rigid Bones"; Kavan et
al. 2007 applied skinning approximation to cloth), solved by Dem Bones (BSD-3) through `py-dem-bones`. The
rest pose is the loop's frame 0; bone b's transform at frame f maps frame 0's vertices to frame f:

    v_f = sum_b w_vb (R_fb v_0 + t_fb)          (at most MAX_INFLUENCES bones per vertex, weights sum to 1)

Real cloth needs many bones: on the sample's skirt 16 bones leave a few millimetres RMS, on the shared long
skirt 128 bones still a centimetre (docs/export.md "Cloth as bones").
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

MAX_INFLUENCES = 4  # glTF's JOINTS_0 / WEIGHTS_0 hold four; every engine skins with four
DEFAULT_ITERATIONS = 30  # Dem Bones' own default; the error changes little past it (measured on the sample)
# Bone counts `choose_bone_count` tries, in order, for an error budget.
AUTO_BONE_COUNTS = (4, 8, 16, 32, 64, 128)


@dataclass(frozen=True)
class ClothBones:
    """A decomposed loop. joints, weights: (V, 4) uint16 bone indices and float32 weights (summing to 1,
    unused slots weight 0); rotations (F, B, 4) float64 unit quaternions (x, y, z, w), translations
    (F, B, 3) metres: bone b at frame f maps frame 0's positions to frame f's. rms_m, max_m: the skinned
    loop against the loop, over every vertex and frame."""

    joints: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    rms_m: float
    max_m: float
    iterations: int

    @property
    def bone_count(self) -> int:
        return int(self.rotations.shape[1])


def skin(rest: np.ndarray, joints: np.ndarray, weights: np.ndarray, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Linear blend skinning: rest (V, 3), joints/weights (V, K), rotations (F, B, 4) xyzw, translations (F, B, 3)
    -> (F, V, 3) positions."""
    matrices = quaternion_matrices(rotations)  # (F, B, 3, 3)
    posed = np.einsum("fbij,vj->fbvi", matrices, rest) + translations[:, :, None, :]  # (F, B, V, 3)
    vertex = np.arange(rest.shape[0])
    out = np.zeros((rotations.shape[0], rest.shape[0], 3))
    for k in range(joints.shape[1]):
        out += weights[None, :, k, None] * posed[:, joints[:, k], vertex]
    return out


def quaternion_matrices(quaternions: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w, glTF's order) -> (..., 3, 3) rotation matrices."""
    quaternions = np.asarray(quaternions, dtype=np.float64)
    return Rotation.from_quat(quaternions.reshape(-1, 4)).as_matrix().reshape(quaternions.shape[:-1] + (3, 3))


def matrix_quaternions(matrices: np.ndarray) -> np.ndarray:
    """(..., 3, 3) near-rotations -> (..., 4) unit quaternions (x, y, z, w), w >= 0: glTF animates rotations,
    so each matrix becomes its nearest rotation (scipy's from_matrix)."""
    matrices = np.asarray(matrices, dtype=np.float64)
    q = Rotation.from_matrix(matrices.reshape(-1, 3, 3)).as_quat(canonical=True)
    return q.reshape(matrices.shape[:-2] + (4,))


def top_influences(weights: np.ndarray, count: int = MAX_INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """(B, V) weights -> joints (V, count) uint16 and weights (V, count) float32 of each vertex's largest
    `count` weights, renormalised to sum 1 (unused slots: joint 0, weight 0)."""
    weights = np.clip(np.asarray(weights, dtype=np.float64), 0.0, None)
    if weights.shape[0] < count:  # fewer bones than slots: the rest weigh 0 (and name joint 0)
        weights = np.concatenate([weights, np.zeros((count - weights.shape[0], weights.shape[1]))])
    order = np.argsort(-weights, axis=0, kind="stable")[:count].T  # (V, count)
    chosen = np.take_along_axis(weights.T, order, axis=1)
    total = chosen.sum(axis=1, keepdims=True)
    # A vertex no bone claims follows the first bone alone.
    chosen = np.where(total > 0, chosen / np.where(total > 0, total, 1.0), np.eye(count)[0])
    joints = np.where(chosen > 0, order, 0).astype(np.uint16)
    out = chosen.astype(np.float32)
    out[:, 0] += np.float32(1.0) - out.sum(axis=1)  # exactly 1 in float32, as glTF-Validator checks
    return joints, out


def decompose_cloth(positions: np.ndarray, triangles: np.ndarray, bones: int, iterations: int = DEFAULT_ITERATIONS) -> ClothBones:
    """positions (F, V, 3) metres, the loop; triangles (T, 3) vertex indices -> ClothBones with at most `bones`
    bones (Dem Bones may use fewer). Raises ValueError for shapes that do not fit or a bone count outside
    1..V, ImportError when py-dem-bones is not installed."""
    from py_dem_bones import solve_skinning

    positions = np.asarray(positions, dtype=np.float64)
    triangles = np.asarray(triangles).reshape(-1, 3)
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[0] < 2:
        raise ValueError(f"positions must be (F, V, 3) with F >= 2, got {positions.shape}")
    if not 1 <= bones <= positions.shape[1]:
        raise ValueError(f"bones must be between 1 and the vertex count {positions.shape[1]}, got {bones}")
    result = solve_skinning(positions[0], positions, int(bones), faces=triangles.astype(np.int64), max_influences=MAX_INFLUENCES,
                            iterations=int(iterations))
    joints, weights = top_influences(result.weights)
    rotations = matrix_quaternions(result.transforms[:, :, :3, :3])
    translations = result.transforms[:, :, :3, 3].copy()
    error = np.linalg.norm(skin(positions[0], joints, weights.astype(np.float64), rotations, translations) - positions, axis=-1)
    return ClothBones(joints, weights, rotations, translations, float(np.sqrt((error ** 2).mean())), float(error.max()), int(iterations))


def choose_bone_count(positions: np.ndarray, triangles: np.ndarray, budget_mm: float, counts: tuple[int, ...] = AUTO_BONE_COUNTS,
                      iterations: int = DEFAULT_ITERATIONS, on_try: Callable[[ClothBones], None] | None = None) -> ClothBones:
    """The decomposition with the fewest bones of `counts` whose RMS error is within `budget_mm`; the last
    (most bones) tried when none is. Counts above the vertex count are skipped. on_try, where given, sees
    each decomposition as it is made: one can take a minute on a real garment."""
    if budget_mm <= 0:
        raise ValueError(f"the error budget must be positive millimetres, got {budget_mm}")
    usable = [c for c in counts if c <= np.asarray(positions).shape[1]] or [1]
    result = None
    for count in usable:
        result = decompose_cloth(positions, triangles, count, iterations)
        if on_try is not None:
            on_try(result)
        if result.rms_m * 1000 <= budget_mm:
            break
    return result
