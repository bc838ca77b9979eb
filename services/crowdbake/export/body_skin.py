"""A skinned pose cache (CBSK, SPEC.md "Skinned pose cache") as a glTF skin.

A CBSK stores per pose frame each joint's skinning matrix M_j(f) (world · inverse bind). The glTF keeps
the rest mesh, its four influences a vertex, an identity inverse bind per joint and one joint node per
joint, all children of the character: node j's translation, rotation and scale are M_j(f)'s, so glTF's
skinning (joint world · inverse bind) gives M_j(f) back.

A frame whose matrices are a blend of two poses (a clip's crossfade, a transition) holds matrices with
shear, which no translation, rotation and scale give. Such a frame gets the nearest TRS and a corrective
morph target on the rest mesh: glTF morphs before it skins, so the target moves each vertex by what the
TRS leaves over (skinned back through the vertex's blended TRS matrix), and the frame plays exactly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from crowdbake.export.morph_normals import normal_deltas
from crowdbake.formats.skinned_cache import WEIGHT_CODE_SUM, SkinnedPoseCache

# A matrix whose TRS gives it back within this (relative to its largest scale) is played by its joint alone.
TRS_TOLERANCE = 1e-5
# Below this determinant (of a weighted joint's 3 x 3 block over its largest scale cubed) a matrix has no
# rotation to take apart, and a mirrored one (negative determinant) none a glTF viewer animates smoothly.
MIN_RELATIVE_DETERMINANT = 1e-6
# A corrective target's position deltas lie on a power-of-two grid of the rest mesh's units (corrective_step):
# the coarsest whose half step, turned by the frame's blended 3 x 3 blocks, moves no vertex more than this. Float
# values on such a grid keep their low mantissa bits zero, which deflate takes away (the robot's body: 0.45 MB
# of float deltas in the zip before, 0.19 MB after).
CORRECTIVE_BOUND_M = 1e-4


@dataclass(frozen=True)
class GltfSkin:
    """A skinned body as the glTF writes it. rest_positions, rest_normals (V, 3) float32 (metres, unit);
    joints, weight_codes (V, 4) uint16 (codes / 65535 sum to 1); per pose frame and joint translations
    (F, J, 3), rotations (F, J, 4) unit xyzw with w >= 0, scales (F, J, 3); animated (A,) the joints some
    vertex weighs; corrected (C,) the pose frames that need a corrective target, position_deltas (C, V, 3)
    float32 in the rest mesh's units, on corrective_step's grid, and normal_deltas (C, V, 3) in [-1, 1] (morph_normals.normal_deltas)."""

    rest_positions: np.ndarray
    rest_normals: np.ndarray
    joints: np.ndarray
    weight_codes: np.ndarray
    translations: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    animated: np.ndarray
    corrected: np.ndarray
    position_deltas: np.ndarray
    normal_deltas: np.ndarray

    @property
    def joint_count(self) -> int:
        return int(self.translations.shape[1])

    def trs_matrices(self) -> np.ndarray:
        """(F, J, 3, 4) float64: the matrices the joints' TRS give (what a glTF viewer skins with)."""
        return trs_matrices(self.translations, self.rotations, self.scales)


def decompose(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(..., 3, 4) affine matrices -> translations (..., 3), rotations (..., 4) unit xyzw with w >= 0,
    scales (..., 3) and the error (...) of rebuilding each from them, over its largest scale.

    Rotation: the polar decomposition's (the nearest rotation to the 3 x 3 block); scale: the block's
    columns projected on that rotation's axes. Exact for a rotation times a diagonal scale; a sheared block
    (a blend of two poses) leaves an error."""
    matrices = np.asarray(matrices, dtype=np.float64)
    block = matrices[..., :3]
    u, _, vt = np.linalg.svd(block)
    rotation = u @ vt
    flip = np.linalg.det(rotation) < 0  # mirrored blocks: the caller refuses them (relative_determinants)
    rotation[flip] = -rotation[flip]
    scales = np.einsum("...ki,...ki->...i", rotation, block)
    rebuilt = rotation * scales[..., None, :]
    largest = np.maximum(np.abs(scales).max(axis=-1), 1e-30)
    error = np.abs(rebuilt - block).max(axis=(-2, -1)) / largest
    shape = matrices.shape[:-2]
    quaternions = Rotation.from_matrix(rotation.reshape(-1, 3, 3)).as_quat(canonical=True).reshape(shape + (4,))
    return matrices[..., 3].copy(), quaternions, scales, error


def trs_matrices(translations: np.ndarray, rotations: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """translations (..., 3), rotations (..., 4) xyzw, scales (..., 3) -> (..., 3, 4) float64 T · R · S."""
    rotations = np.asarray(rotations, dtype=np.float64)
    shape = rotations.shape[:-1]
    matrix = Rotation.from_quat(rotations.reshape(-1, 4)).as_matrix().reshape(shape + (3, 3)) * np.asarray(scales, np.float64)[..., None, :]
    return np.concatenate([matrix, np.asarray(translations, np.float64)[..., None]], axis=-1)


def relative_determinants(matrices: np.ndarray) -> np.ndarray:
    """(..., 3, 4) -> (...) det of the 3 x 3 block over its largest column length cubed: 1 for a rotation
    with uniform scale, near 0 for a block that flattens space, negative for a mirror."""
    block = np.asarray(matrices, dtype=np.float64)[..., :3]
    largest = np.maximum(np.linalg.norm(block, axis=-2).max(axis=-1), 1e-30)
    return np.linalg.det(block) / largest ** 3


def hemisphere_continuous(quaternions: np.ndarray) -> np.ndarray:
    """(K, ..., 4) quaternions keyed in order -> the same rotations with each key's sign chosen to lie within
    90 degrees of the previous key's, so a glTF player's slerp between keys takes the short way round."""
    out = np.array(quaternions, dtype=np.float64, copy=True)
    for k in range(1, out.shape[0]):
        out[k] *= np.where((out[k] * out[k - 1]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    return out


def why_not_a_skin(cache: SkinnedPoseCache) -> str | None:
    """Why a CBSK's body cannot be a glTF skin (a weighted joint's matrix flattens or mirrors space in some
    frame: no rotation to animate), or None."""
    animated = np.unique(cache.joints[cache.weight_codes > 0])
    determinants = relative_determinants(cache.matrices[:, animated])
    if determinants.size and determinants.min() <= MIN_RELATIVE_DETERMINANT:
        frame, joint = np.unravel_index(int(np.argmin(determinants)), determinants.shape)
        return f"joint {int(animated[joint])}'s matrix at pose frame {int(frame)} flattens or mirrors space (no rotation to animate)"
    return None


def gltf_skin(cache: SkinnedPoseCache) -> GltfSkin:
    """The glTF skin of a CBSK (why_not_a_skin must be None): each joint's TRS per pose frame, joints no vertex
    weighs held at identity, and a corrective target for each frame some weighted joint's TRS misses by more
    than TRS_TOLERANCE (its position deltas on corrective_step's grid: within CORRECTIVE_BOUND_M once skinned)."""
    frame_count, joint_count = cache.matrices.shape[:2]
    animated = np.unique(cache.joints[cache.weight_codes > 0]).astype(np.int64)
    translations = np.zeros((frame_count, joint_count, 3))
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (frame_count, joint_count, 1))
    scales = np.ones((frame_count, joint_count, 3))
    t, r, s, error = decompose(cache.matrices[:, animated])
    translations[:, animated], rotations[:, animated], scales[:, animated] = t, r, s
    corrected = np.flatnonzero((error > TRS_TOLERANCE).any(axis=1))
    weights = cache.weight_codes.astype(np.float64) / WEIGHT_CODE_SUM
    position_deltas = np.zeros((corrected.size, cache.vertex_count, 3), np.float32)
    normal_delta = np.zeros((corrected.size, cache.vertex_count, 3))
    rest_positions = cache.rest_positions.astype(np.float64)
    largest_block = 0.0  # the largest Frobenius norm of a corrected frame's blended 3 x 3 block: bounds how far a rest delta moves
    for row, frame in enumerate(corrected):
        matrices = trs_matrices(translations[frame], rotations[frame], scales[frame])  # (J, 3, 4)
        blended = np.einsum("vk,vkij->vij", weights, matrices[cache.joints])  # (V, 3, 4)
        largest_block = max(largest_block, float(np.sqrt((blended[..., :3] ** 2).sum(axis=(1, 2))).max()))
        skinned = np.einsum("vij,vj->vi", blended[..., :3], rest_positions) + blended[..., 3]
        inverse = np.linalg.inv(blended[..., :3])
        target = cache.positions[frame].astype(np.float64)
        position_deltas[row] = np.einsum("vij,vj->vi", inverse, target - skinned)
        # The normal that, turned by the blended block, points along the frame's normal (a player normalises).
        wanted = np.einsum("vij,vj->vi", inverse, cache.normals[frame].astype(np.float64))
        wanted /= np.maximum(np.linalg.norm(wanted, axis=1, keepdims=True), 1e-12)
        normal_delta[row] = normal_deltas(cache.rest_normals, wanted[None])[0]
    if corrected.size:
        step = corrective_step(largest_block)
        position_deltas = (np.rint(position_deltas.astype(np.float64) / step) * step).astype(np.float32)  # exact in float32
    return GltfSkin(cache.rest_positions.astype(np.float32), cache.rest_normals.astype(np.float32), cache.joints.astype(np.uint16),
                    cache.weight_codes.astype(np.uint16), translations, rotations, scales, animated, corrected, position_deltas, normal_delta)


def corrective_step(largest_block: float, bound_m: float = CORRECTIVE_BOUND_M) -> float:
    """The grid step (a power of two, rest mesh units) of corrective position deltas whose blended 3 x 3 blocks
    have Frobenius norms up to largest_block: the largest with largest_block · sqrt(3) · step / 2 <= bound_m (a
    half step on each axis, turned by a block no longer than its Frobenius norm)."""
    return float(2.0 ** np.floor(np.log2(2 * bound_m / (np.sqrt(3.0) * max(largest_block, 1e-30)))))


def skin_bytes(skin: GltfSkin, key_count: int) -> int:
    """Bytes of a skin in the .glb: the rest mesh (float positions and normals, 4 joints and 4 unorm16 weights a
    vertex), the inverse binds, each corrective target (float position, int8 normal a vertex), and per key of
    all animations (key_count) each weighted joint's translation (float), rotation (snorm16) and scale (float)
    and the corrective weights (unorm8)."""
    vertex_count, corrective = skin.rest_positions.shape[0], int(skin.corrected.size)
    mesh = vertex_count * (12 + 12 + 8 + 8) + skin.joint_count * 64 + corrective * vertex_count * (12 + 4)
    return int(mesh + key_count * (skin.animated.size * (12 + 8 + 12) + corrective))


def morph_bytes(vertex_count: int, frame_count: int) -> int:
    """Bytes of a part's quantized base and morph targets in the .glb (int16 position and int8 normal, 12 bytes a
    vertex, for the base and each pose frame): what a skin must beat."""
    return 12 * vertex_count * (frame_count + 1)


def play(skin: GltfSkin, frames: np.ndarray) -> np.ndarray:
    """(K,) pose frames -> (K, V, 3) float64 positions a glTF player gives at keys showing them: the rest
    mesh plus the frame's corrective target (if any), skinned by the joints' TRS (for tests and reports)."""
    weights = skin.weight_codes.astype(np.float64) / WEIGHT_CODE_SUM
    row_of = {int(frame): row for row, frame in enumerate(skin.corrected)}
    out = []
    for frame in np.asarray(frames).reshape(-1):
        rest = skin.rest_positions.astype(np.float64)
        if int(frame) in row_of:
            rest = rest + skin.position_deltas[row_of[int(frame)]]
        matrices = trs_matrices(skin.translations[frame], skin.rotations[frame], skin.scales[frame])
        blended = np.einsum("vk,vkij->vij", weights, matrices[skin.joints])
        out.append(np.einsum("vij,vj->vi", blended[..., :3], rest) + blended[..., 3])
    return np.asarray(out)
