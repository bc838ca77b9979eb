"""load_character: a skinned, animated .glb/.gltf into a Character (see crowdbake.formats.gltf for what is read).

This module does the skin (its joints in `skin.joints` order, their parents, rest TRS and inverse bind
matrices) and puts the parts together: the document (crowdbake.formats.gltf.document), the hierarchy
(.scene), the merged mesh (.meshes), the materials (.materials) and the animation (.animation).
"""
from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

import numpy as np

from crowdbake.formats.gltf.animation import choose_animation, read_animation
from crowdbake.formats.gltf.document import _Document, open_document
from crowdbake.formats.gltf.materials import merge_material_textures
from crowdbake.formats.gltf.meshes import NORMAL_LENGTH_TOLERANCE, read_meshes
from crowdbake.formats.gltf.model import Character
from crowdbake.formats.gltf.morphs import read_weight_channels
from crowdbake.formats.gltf.scene import decompose_matrix, joint_anchors, local_matrices, node_parents

logger = logging.getLogger(__name__)


def _unit_quaternions(q: np.ndarray, where: str) -> np.ndarray:
    """Normalise quaternions that are off unit length (kept bit for bit otherwise); reject zero ones."""
    length = np.linalg.norm(q, axis=1, keepdims=True)
    if (length < 1e-6).any():
        raise ValueError(f"{where}: a joint rotation is the zero quaternion")
    return np.where(np.abs(length - 1.0) > NORMAL_LENGTH_TOLERANCE, q / length, q)


def _mesh_name(doc: _Document, skin_index: int) -> str:
    for node in doc.gltf.nodes:
        if node.skin == skin_index and node.mesh is not None:
            return str(doc.item("meshes", node.mesh).name or "")
    return ""


# What a glTF whose JSON has the wrong shape (null where an object belongs, a list as an index, nesting
# deep enough to exhaust the parser's recursion) raises while it is walked. The reader's contract is
# ValueError for every bad file, so these are turned into one at this boundary.
_MALFORMED_STRUCTURE = (TypeError, AttributeError, KeyError, IndexError, OverflowError, RecursionError, ZeroDivisionError, struct.error)


def load_character(path: str | os.PathLike, skin: int = 0, animation: int | str = 0) -> Character:
    """Load skin `skin` of a .glb/.gltf (its meshes merged) and one animation (an index, or a name)
    into a Character.

    Raises ValueError naming the file for anything the file gets wrong, its JSON's shape included, and
    for a required extension it cannot read (named)."""
    try:
        return _load_character(Path(path), skin, animation)
    except _MALFORMED_STRUCTURE as error:
        raise ValueError(f"{path}: the glTF JSON does not have the structure glTF 2.0 requires ({type(error).__name__}: {error})") from None


def _load_character(path: Path, skin: int, animation: int | str) -> Character:
    doc = open_document(path)
    where = doc.where
    if not doc.gltf.skins:
        raise ValueError(f"{where}: the file has no skin; a character needs a skinned mesh")
    skin_info = doc.item("skins", skin)
    joint_nodes = skin_info.joints or []
    nodes = doc.gltf.nodes
    if not joint_nodes or not all(isinstance(n, int) and 0 <= n < len(nodes) for n in joint_nodes):
        raise ValueError(f"{where}: skins[{skin}].joints must list existing nodes")
    if len(set(joint_nodes)) != len(joint_nodes):
        raise ValueError(f"{where}: skins[{skin}].joints lists a node twice")
    node_to_joint = {node: index for index, node in enumerate(joint_nodes)}
    joint_count = len(joint_nodes)

    parents, order = node_parents(doc)
    local = local_matrices(doc)
    anchor, between = joint_anchors(parents, order, local, node_to_joint)
    joint_parents = anchor[joint_nodes].astype(np.int64)
    joint_parent_transforms = between[joint_nodes].copy()
    # Non-joint nodes above a joint: their animation is not followed (warned about when read).
    joint_ancestors: set[int] = set()
    for node_index in joint_nodes:
        ancestor = parents[node_index]
        while ancestor != -1 and ancestor not in node_to_joint and ancestor not in joint_ancestors:
            joint_ancestors.add(int(ancestor))
            ancestor = parents[ancestor]
    rest = np.zeros((joint_count, 10))
    for joint, node_index in enumerate(joint_nodes):
        node = nodes[node_index]
        if node.matrix is not None:
            translation, rotation, scale = decompose_matrix(local[node_index])
        else:
            translation = node.translation if node.translation is not None else [0, 0, 0]
            rotation = node.rotation if node.rotation is not None else [0, 0, 0, 1]
            scale = node.scale if node.scale is not None else [1, 1, 1]
        rest[joint] = np.concatenate([translation, rotation, scale])
    if not np.isfinite(rest).all():
        raise ValueError(f"{where}: a joint has a non-finite rest transform")

    if skin_info.inverseBindMatrices is not None:
        ibm = doc.accessor(skin_info.inverseBindMatrices)
        if ibm.shape != (joint_count, 16):
            raise ValueError(f"{where}: inverseBindMatrices is {ibm.shape}, expected ({joint_count}, 16) MAT4")
        inverse_bind = ibm.reshape(joint_count, 4, 4).transpose(0, 2, 1).astype(np.float32)
    else:
        inverse_bind = np.tile(np.eye(4, dtype=np.float32), (joint_count, 1, 1))

    mesh, materials, morphs = read_meshes(doc, skin, joint_count, anchor, between, local, inverse_bind, node_to_joint)
    animation_index = choose_animation(doc, animation)
    channels, duration = read_animation(doc, animation_index, node_to_joint, joint_ancestors)
    weight_channels = read_weight_channels(doc, animation_index, morphs["node_targets"])
    animation_names = [a.name or f"animation{k}" for k, a in enumerate(doc.gltf.animations or [])]
    texture, uvs = merge_material_textures(materials, mesh["materials"], mesh["uvs"])
    names = [str(nodes[n].name or f"joint{k}") for k, n in enumerate(joint_nodes)]
    logger.debug("%s: %d vertices, %d triangles, %d joints, %d materials, %d channels, %.3f s", where,
                 len(mesh["positions"]), len(mesh["faces"]), joint_count, len(materials), len(channels), duration)
    return Character(
        positions=mesh["positions"].astype(np.float32),
        normals=mesh["normals"].astype(np.float32),
        uvs=uvs.astype(np.float32),
        faces=mesh["faces"].astype(np.uint32),
        joints=mesh["joints"].astype(np.uint16),
        weights=mesh["weights"].astype(np.float32),
        joint_names=names,
        joint_parents=joint_parents,
        joint_parent_transforms=joint_parent_transforms,
        inverse_bind_matrices=inverse_bind,
        rest_translations=rest[:, 0:3].copy(),
        rest_rotations=_unit_quaternions(rest[:, 3:7], where),
        rest_scales=rest[:, 7:10].copy(),
        channels=channels,
        animation_duration=duration,
        texture=texture,
        name=_mesh_name(doc, skin) or path.stem,
        materials=materials,
        vertex_materials=mesh["materials"],
        animation_name=animation_names[animation_index] if animation_index is not None else "",
        animation_names=animation_names,
        morph_targets=morphs["targets"],
        morph_weights=morphs["weights"],
        weight_channels=weight_channels,
    )
