"""Keyframe sampling and linear blend skinning, as glTF 2.0 defines them. Pure numpy, no I/O.

A character here is anything shaped like `SkinnedCharacter` (crowdbake.formats.gltf.Character is
one): joint_parents, joint_parent_transforms, inverse_bind_matrices, rest TRS, channels, and the
bind-pose mesh arrays. The shape is a Protocol so bake/ imports nothing from formats/ (both take their
quaternion maths from crowdbake.geometry).

Conventions: matrices act on column vectors (p' = M @ p); quaternions are (x, y, z, w); times in
seconds. Times outside an animation's keyframes clamp to the first or last key (glTF's rule), so a
looping animation's time must be wrapped by the caller (``t % duration``).
"""
from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np

from crowdbake.geometry import quaternion_matrices, skin  # noqa: F401 (skin: linear blend skinning, shared with the skinned pose cache reader)


class KeyframeChannel(Protocol):
    """Keyframes of one joint property (crowdbake.formats.gltf.AnimationChannel is one).

    path: "translation" | "rotation" | "scale"; times (K,) seconds; values (K, C), or (K, 3, C) for
    CUBICSPLINE (in-tangent, value, out-tangent); interpolation: "LINEAR" | "STEP" | "CUBICSPLINE".
    """

    joint: int
    path: str
    times: np.ndarray
    values: np.ndarray
    interpolation: str


class SkinnedCharacter(Protocol):
    """What skinning reads from a character (crowdbake.formats.gltf.Character is one)."""

    positions: np.ndarray
    normals: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    joint_parents: np.ndarray
    joint_parent_transforms: np.ndarray
    inverse_bind_matrices: np.ndarray
    rest_translations: np.ndarray
    rest_rotations: np.ndarray
    rest_scales: np.ndarray
    channels: Sequence[KeyframeChannel]
    # Optional (read with getattr, empty when absent): morph_targets, each with start (int), positions
    # (n, 3) and normals (n, 3) or None, bind-space displacements of vertices start..start+n-1;
    # morph_weights (N,) default weights; weight_channels, keyframes of targets first..first+count-1
    # (see crowdbake.formats.gltf.MorphTarget and WeightsChannel).

# Below this angle between keys (radians), slerp's sin(theta) in the denominator loses precision
# and normalised lerp is indistinguishable from it.
SLERP_LINEAR_THRESHOLD = 1e-4


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Shortest-arc spherical interpolation. q0, q1 (N, 4) unit quaternions, alpha (N,) in [0, 1] -> (N, 4)."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)[:, None]
    dot = np.sum(q0 * q1, axis=1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)  # q and -q are the same rotation; take the short way round
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    near = theta < SLERP_LINEAR_THRESHOLD
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / safe)
    w1 = np.where(near, alpha, np.sin(alpha * theta) / safe)
    out = w0 * q0 + w1 * q1
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def sample_channel(channel: KeyframeChannel, times: np.ndarray) -> np.ndarray:
    """Evaluate one keyframed channel at times (F,) seconds -> (F, C) float64 (C = 3, or 4 for rotations).

    LINEAR rotations use slerp; CUBICSPLINE uses glTF's Hermite form; times clamp to the key range.
    """
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    key_times = np.asarray(channel.times, dtype=np.float64)
    values = np.asarray(channel.values, dtype=np.float64)
    is_rotation = channel.path == "rotation"
    if channel.interpolation == "CUBICSPLINE":
        in_tangents, key_values, out_tangents = values[:, 0], values[:, 1], values[:, 2]
    else:
        key_values = values
    if len(key_times) == 1:
        result = np.repeat(key_values[:1], len(times), axis=0)
        return result / np.linalg.norm(result, axis=1, keepdims=True) if is_rotation else result
    clamped = np.clip(times, key_times[0], key_times[-1])
    if channel.interpolation == "STEP":
        index = np.clip(np.searchsorted(key_times, clamped, side="right") - 1, 0, len(key_times) - 1)
        result = key_values[index]
        return result / np.linalg.norm(result, axis=1, keepdims=True) if is_rotation else result
    index = np.clip(np.searchsorted(key_times, clamped, side="right") - 1, 0, len(key_times) - 2)
    span = key_times[index + 1] - key_times[index]
    alpha = np.clip((clamped - key_times[index]) / span, 0.0, 1.0)
    if channel.interpolation == "CUBICSPLINE":
        s = alpha[:, None]
        s2, s3 = s * s, s * s * s
        result = (
            (2 * s3 - 3 * s2 + 1) * key_values[index]
            + (s3 - 2 * s2 + s) * span[:, None] * out_tangents[index]
            + (-2 * s3 + 3 * s2) * key_values[index + 1]
            + (s3 - s2) * span[:, None] * in_tangents[index + 1]
        )
        return result / np.linalg.norm(result, axis=1, keepdims=True) if is_rotation else result
    if is_rotation:
        return slerp(key_values[index], key_values[index + 1], alpha)
    return key_values[index] + alpha[:, None] * (key_values[index + 1] - key_values[index])


def local_transforms(character: SkinnedCharacter, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each joint's local TRS at times (F,) -> translations (F, J, 3), rotations (F, J, 4), scales (F, J, 3)."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    frames = len(times)
    translations = np.repeat(np.asarray(character.rest_translations, np.float64)[None], frames, axis=0)
    rotations = np.repeat(np.asarray(character.rest_rotations, np.float64)[None], frames, axis=0)
    scales = np.repeat(np.asarray(character.rest_scales, np.float64)[None], frames, axis=0)
    targets = {"translation": translations, "rotation": rotations, "scale": scales}
    for channel in character.channels:
        targets[channel.path][:, channel.joint] = sample_channel(channel, times)
    return translations, rotations, scales


def joint_order(joint_parents: np.ndarray) -> np.ndarray:
    """Joint indices sorted so every parent comes before its children. joint_parents (J,) int, -1 = root.

    Linear in J: each joint's depth is computed once (a 16,000-joint chain costs 16,000 steps, not
    16,000 squared). Raises ValueError for a parent index out of range or a cycle.
    """
    parents = np.asarray(joint_parents, dtype=np.int64)
    count = len(parents)
    if count and (parents.min() < -1 or parents.max() >= count):
        raise ValueError(f"joint_parents must lie in -1..{count - 1}")
    depth = np.full(count, -1, dtype=np.int64)
    on_path = np.zeros(count, dtype=bool)
    for joint in range(count):
        path = []
        node = joint
        while node >= 0 and depth[node] < 0:
            if on_path[node]:
                raise ValueError(f"joint_parents has a cycle through joint {node}")
            on_path[node] = True
            path.append(node)
            node = parents[node]
        base = -1 if node < 0 else depth[node]
        for step, visited in enumerate(reversed(path)):
            depth[visited] = base + 1 + step
            on_path[visited] = False
    return np.argsort(depth, kind="stable")


def joint_world_matrices(character: SkinnedCharacter, times: np.ndarray) -> np.ndarray:
    """World transforms of every joint at times (F,) -> (F, J, 4, 4) float64."""
    return world_from_local(character, *local_transforms(character, times))


def world_from_local(character: SkinnedCharacter, translations: np.ndarray, rotations: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """World transforms of every joint from local TRS (F, J, 3), (F, J, 4) (x, y, z, w), (F, J, 3) -> (F, J, 4, 4)
    float64, down the character's hierarchy (what joint_world_matrices does with sampled channels)."""
    local = np.zeros(translations.shape[:2] + (4, 4))
    local[..., :3, :3] = quaternion_matrices(rotations) * scales[..., None, :]
    local[..., :3, 3] = translations
    local[..., 3, 3] = 1.0
    above = np.asarray(character.joint_parent_transforms, dtype=np.float64)
    parents = np.asarray(character.joint_parents, dtype=np.int64)
    world = np.empty_like(local)
    for joint in joint_order(parents):
        base = above[joint] @ local[:, joint]
        world[:, joint] = base if parents[joint] < 0 else world[:, parents[joint]] @ base
    return world


def joint_matrices(character: SkinnedCharacter, times: np.ndarray) -> np.ndarray:
    """Skinning matrices world(j) @ inverseBind(j) at times (F,) seconds -> (F, J, 4, 4) float32."""
    world = joint_world_matrices(character, times)
    return (world @ np.asarray(character.inverse_bind_matrices, dtype=np.float64)).astype(np.float32)


def morph_weights(character: SkinnedCharacter, times: np.ndarray) -> np.ndarray:
    """Each morph target's weight at times (F,) seconds -> (F, N) float64: the default weights, and the
    animated ones where a weights channel drives them (sampled like any channel, clamped to its keys)."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    targets = getattr(character, "morph_targets", None) or []
    defaults = np.asarray(getattr(character, "morph_weights", None) if len(targets) else np.zeros(0), dtype=np.float64)
    if defaults.shape != (len(targets),):
        raise ValueError(f"morph_weights must be ({len(targets)},), got {defaults.shape}")
    weights = np.repeat(defaults[None], len(times), axis=0)
    for channel in getattr(character, "weight_channels", None) or []:
        weights[:, channel.first : channel.first + channel.count] = sample_channel(channel, times)
    return weights


def apply_morph_targets(positions: np.ndarray, normals: np.ndarray, targets: Sequence, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bind-pose mesh plus weighted morph target displacements (glTF 2.0 section 3.7.2.2).

    positions, normals (V, 3); targets: N objects with start, positions (n, 3), normals (n, 3) or None
    (see SkinnedCharacter); weights (N,) -> positions (V, 3) float32 = positions + sum_i w_i * delta_i,
    normals (V, 3) float32, renormalised where a normal displacement moved them.
    """
    weights = np.asarray(weights, dtype=np.float64).reshape(-1)
    if len(weights) != len(targets):
        raise ValueError(f"{len(targets)} morph targets but {len(weights)} weights")
    out_positions = np.asarray(positions, dtype=np.float64).copy()
    out_normals = np.asarray(normals, dtype=np.float64).copy()
    moved = np.zeros(len(out_normals), dtype=bool)
    for target, weight in zip(targets, weights):
        if weight == 0.0:
            continue
        rows = slice(target.start, target.start + len(target.positions))
        out_positions[rows] += weight * np.asarray(target.positions, dtype=np.float64)
        if target.normals is not None:
            out_normals[rows] += weight * np.asarray(target.normals, dtype=np.float64)
            moved[rows] = True
    if moved.any():
        length = np.linalg.norm(out_normals[moved], axis=1, keepdims=True)
        out_normals[moved] = np.divide(out_normals[moved], length, out=np.zeros_like(out_normals[moved]), where=length > 0)
    return out_positions.astype(np.float32), out_normals.astype(np.float32)


def pose_at_times(character: SkinnedCharacter, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The skinned mesh at times (F,) seconds -> positions, normals (F, V, 3) float32: morph targets
    applied to the bind pose at each time's weights, then linear blend skinning."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    matrices = joint_matrices(character, times)
    targets = getattr(character, "morph_targets", None) or []
    if not targets:
        return skin(character.positions, character.normals, character.joints, character.weights, matrices)
    weights = morph_weights(character, times)
    out_positions = np.empty((len(times), len(character.positions), 3), dtype=np.float32)
    out_normals = np.empty_like(out_positions)
    # Frames that share their weights (a constant or STEP channel) are morphed once and skinned together.
    rows, which = np.unique(weights, axis=0, return_inverse=True)
    for row_index, row in enumerate(rows):
        frames = np.flatnonzero(which.reshape(-1) == row_index)
        positions, normals = apply_morph_targets(character.positions, character.normals, targets, row)
        out_positions[frames], out_normals[frames] = skin(positions, normals, character.joints, character.weights, matrices[frames])
    return out_positions, out_normals


def pose_character(
    character: SkinnedCharacter, fps: float, frame_count: int, start_time: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Skinned mesh at times start_time + k / fps, k = 0..frame_count-1 -> positions, normals (F, V, 3) float32.

    Times past the animation's last key clamp to it; wrap them yourself for a looping walk. Morph
    targets are applied before skinning (see pose_at_times).
    """
    if fps <= 0 or frame_count < 1:
        raise ValueError(f"fps {fps} must be positive and frame_count {frame_count} at least 1")
    return pose_at_times(character, start_time + np.arange(frame_count, dtype=np.float64) / fps)
