"""A body kept as skinning (shared_formats/SPEC.md "Skinned pose cache"): its rest mesh, four joint
influences a vertex and each joint's skinning matrix per pose frame, which a runtime skins in its vertex
shader. Unreal's AnimToTexture and Unity's GPU animation bakers store skinned bodies this way: a few KiB
a frame (48 bytes a joint) where vertex frames store every vertex again.

The matrices follow the vertex frames the bake would have stored: the same sample times, loop, root
motion and transition blends, each a linear operation, applied to matrices instead of positions (linear
blend skinning is linear in the matrices, and its weights sum to one). The caller skins them and keeps
them only where they agree with those vertex frames (`frames_disagreement`). Pure numpy, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.skinning import pose_character

# The skinned frames must match the vertex frames they replace this closely, or the body keeps vertex
# frames: 0.1 mm is a fifth of the quantized cloth's error bound (SPEC.md, 0.5 mm). Normals agree within
# 0.05 degrees outside a transition's blend; inside it both paths approximate a blend of two poses (the
# vertex frames mix each pose's unit normal, the matrices each joint's turn) and differ by up to 2.3
# degrees on the demo's clips sample, for a few frames: 3 degrees changes Lambert shading by under 5 %.
SKIN_POSITION_TOLERANCE_M = 1e-4
SKIN_NORMAL_TOLERANCE_DEG = 3.0


@dataclass(frozen=True)
class BodySkin:
    """rest_positions, rest_normals (V, 3) float32 (bind pose, metres); joints (V, 4) int; weights (V, 4)
    float (glTF's, each row summing to about 1); matrices (F, J, 3, 4) float32, the top rows of each joint's
    skinning matrix at each pose frame."""

    rest_positions: np.ndarray
    rest_normals: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    matrices: np.ndarray

    def subset(self, kept: np.ndarray) -> "BodySkin":
        """The skin of the vertices `kept` (a low LOD's, which the simplifier keeps from the high one)."""
        return BodySkin(self.rest_positions[kept], self.rest_normals[kept], self.joints[kept], self.weights[kept], self.matrices)


def pose_body_cycle(character, fps: float, start: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Body positions and normals (frames, V, 3) at cache frames start .. start+frames-1, animation looped.

    Cloth sample k is at animation time (k / fps) modulo the animation's duration (the walk repeats while
    the cloth is simulated).
    """
    duration = float(character.animation_duration)
    if duration <= 0:
        positions, normals = pose_character(character, fps, 1)
        return np.repeat(positions, frames, axis=0), np.repeat(normals, frames, axis=0)
    loop = duration * fps
    whole = int(round(loop))
    if whole >= 1 and abs(loop - whole) < 1e-3:
        positions, normals = pose_character(character, fps, whole)
        index = (start + np.arange(frames)) % whole
        return positions[index], normals[index]
    posed = [pose_character(character, fps, 1, start_time=((start + k) / fps) % duration) for k in range(frames)]
    return np.concatenate([p for p, _ in posed]), np.concatenate([n for _, n in posed])


def cycle_times(duration_s: float, fps: float, start: int, frames: int) -> np.ndarray:
    """(frames,) float64 animation times (seconds) of cache frames start .. start+frames-1 as
    pose_body_cycle poses them: the animation looped (a whole number of frames
    long: frame i at i / fps), or at time 0 when the animation has no length."""
    if duration_s <= 0:
        return np.zeros(frames)
    loop = duration_s * fps
    whole = int(round(loop))
    if whole >= 1 and abs(loop - whole) < 1e-3:
        return ((start + np.arange(frames)) % whole) / fps
    return ((start + np.arange(frames)) / fps) % duration_s


def without_root_offsets(matrices: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(F, J, 3, 4) matrices whose skinned positions are moved by -offsets (F, 3) metres: with weights
    summing to one, subtracting from every joint's translation subtracts from every vertex."""
    moved = np.array(matrices, dtype=np.float64)
    moved[..., 3] -= np.asarray(offsets, dtype=np.float64)[:, None, :]
    return moved.astype(np.float32)


def frames_disagreement(skinned_positions: np.ndarray, skinned_normals: np.ndarray, positions: np.ndarray,
                        normals: np.ndarray, no_normal: np.ndarray | None = None) -> tuple[float, float]:
    """Largest distance (metres) and angle (degrees) between skinned frames and the vertex frames they
    replace, all (F, V, 3) float32 (normals unit). no_normal: (F, V) bool, where the vertex frames had no
    normal of their own (crowdbake.bake.poses.FALLBACK_NORMAL: a join blending two poses whose normals
    nearly cancel), left out of the angle since any direction is as good there."""
    # float32 (the frames' own precision): float64 copies of a body's frames cost a hundred MB on the robot.
    distance = float(np.linalg.norm(np.subtract(skinned_positions, positions, dtype=np.float32), axis=-1).max())
    cosine = np.clip(np.einsum("fvi,fvi->fv", skinned_normals, normals, dtype=np.float32), -1.0, 1.0)
    had_normal = np.ones(cosine.shape, bool) if no_normal is None else ~np.asarray(no_normal, bool)
    return distance, float(np.degrees(np.arccos(cosine[had_normal].min()))) if had_normal.any() else 0.0
