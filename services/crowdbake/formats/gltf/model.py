"""What the glTF reader returns and the writer takes: a skinned Character, its materials, its animation channels.

Plain dataclasses of numpy arrays (shapes and units in each docstring); see crowdbake.formats.gltf for
how transforms, skinning and texture coordinates are to be read.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class AnimationChannel:
    """Keyframes of one joint property.

    joint: index into the character's joints; path: "translation" | "rotation" | "scale";
    times: (K,) float32 seconds, strictly increasing; values: (K, C) float32 with C = 3, or 4 for
    rotations (unit quaternions x, y, z, w); for CUBICSPLINE, values is (K, 3, C): in-tangent,
    value, out-tangent per key, as glTF stores them.
    """

    joint: int
    path: str
    times: np.ndarray
    values: np.ndarray
    interpolation: str = "LINEAR"


@dataclass
class MorphTarget:
    """One glTF morph target of one mesh, on the vertices that mesh became in the merged Character.

    name: mesh.extras.targetNames[k] where the file names it, else "target<k>"; mesh: the glTF mesh
    index; start: the first of its vertices in Character.positions (a mesh's primitives are merged
    consecutively); positions: (n, 3) float32 metres, bind-space displacements of vertices
    start..start+n-1; normals: (n, 3) float32 displacements of their normals, or None.
    """

    name: str
    mesh: int
    start: int
    positions: np.ndarray
    normals: np.ndarray | None = None


@dataclass
class WeightsChannel:
    """Keyframes of one mesh's morph target weights (a glTF channel whose path is "weights").

    first: index into Character.morph_targets of the mesh's first target; its `count` targets follow;
    times: (K,) float32 seconds; values: (K, count) float32, or (K, 3, count) for CUBICSPLINE
    (in-tangent, value, out-tangent per key). `path` is always "weights" (what the samplers read).
    """

    first: int
    count: int
    times: np.ndarray
    values: np.ndarray
    interpolation: str = "LINEAR"
    path: str = "weights"


@dataclass
class Material:
    """One glTF material as the bake sees it: base_color_factor (4,) float32 linear RGBA; texture
    (H, W, 4) uint8 sRGB base colour image (not yet multiplied by the factor) or None."""

    name: str
    base_color_factor: np.ndarray
    texture: np.ndarray | None = None


@dataclass
class Character:
    """A skinned character in its bind pose plus one animation (see the module docstring for transforms).

    positions (V, 3) float32 metres, normals (V, 3) float32 unit, uvs (V, 2) float32 (glTF convention;
    zeros when the file has none; into `texture`, an atlas when several materials were merged),
    faces (T, 3) uint32, joints (V, 4) uint16 joint indices, weights (V, 4) float32 summing to 1 per vertex.
    joint_names: J names; joint_parents (J,) int64, -1 for a root; joint_parent_transforms (J, 4, 4)
    float64; inverse_bind_matrices (J, 4, 4) float32; rest_translations (J, 3), rest_rotations (J, 4)
    (x, y, z, w), rest_scales (J, 3) float64: each joint's local TRS when no channel animates it.
    channels: the animation; animation_duration: seconds (0 without animation); animation_name: its
    name; animation_names: every animation in the file, in order.
    texture: (H, W, 4) uint8 base colour or None. materials: the materials used, vertex_materials (V,)
    uint16 index into them (None for a character built in code).
    morph_targets: every mesh's morph targets (see MorphTarget); morph_weights: (N,) float32, the
    weight of each when no channel animates it (the node's or mesh's `weights`, else 0);
    weight_channels: the animation's channels on them. Posing adds sum_i w_i(t) * delta_i to the
    bind-space positions (and normals, renormalised) before skinning (crowdbake.bake.skinning).
    """

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    joint_names: list[str]
    joint_parents: np.ndarray
    joint_parent_transforms: np.ndarray
    inverse_bind_matrices: np.ndarray
    rest_translations: np.ndarray
    rest_rotations: np.ndarray
    rest_scales: np.ndarray
    channels: list[AnimationChannel] = field(default_factory=list)
    animation_duration: float = 0.0
    texture: np.ndarray | None = None
    name: str = ""
    materials: list[Material] = field(default_factory=list)
    vertex_materials: np.ndarray | None = None
    animation_name: str = ""
    animation_names: list[str] = field(default_factory=list)
    morph_targets: list[MorphTarget] = field(default_factory=list)
    morph_weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    weight_channels: list[WeightsChannel] = field(default_factory=list)

    @property
    def vertex_count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def joint_count(self) -> int:
        return int(self.joint_parents.shape[0])
