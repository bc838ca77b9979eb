"""Meshes: every triangle primitive of the chosen skin's meshes (and rigid meshes under a joint) merged into one.

Primitives may be Draco-compressed (decoded by crowdbake.formats.gltf.compression), strips or fans;
up to eight skin influences per vertex are cut to the four strongest; weights and normals that are off
are renormalised (only those, so valid files round-trip bit for bit). A primitive without NORMAL gets
area-weighted vertex normals. Morph targets are kept per mesh (crowdbake.formats.gltf.morphs) on the
vertices the mesh became.
"""
from __future__ import annotations

import logging

import numpy as np
import pygltflib

from crowdbake.formats.gltf.accessors import COMPONENT_TYPES, accessor_values
from crowdbake.formats.gltf.compression import DRACO, decode_draco_mesh
from crowdbake.formats.gltf.document import _Document, extension
from crowdbake.formats.gltf.materials import read_material
from crowdbake.formats.gltf.model import Material, MorphTarget
from crowdbake.formats.gltf.morphs import default_weights, mesh_targets, primitive_targets
from crowdbake.geometry import vertex_normals

logger = logging.getLogger(__name__)

# Primitive modes read as triangles (points and lines are skipped with a warning).
MODE_TRIANGLES, MODE_TRIANGLE_STRIP, MODE_TRIANGLE_FAN = pygltflib.TRIANGLES, pygltflib.TRIANGLE_STRIP, pygltflib.TRIANGLE_FAN
# Two skins over one skeleton are one skin when their bind matrices agree to this (relative): float32 files.
BIND_TOLERANCE = 1e-4
# Skin weights are normalised on load; a vertex whose weights sum below this is unskinned (a file error).
MIN_WEIGHT_SUM = 1e-6
# Weight rows summing further than this from 1 are renormalised on load (glTF asks for sums of 1).
WEIGHT_SUM_TOLERANCE = 1e-5
# Normals further than this from unit length (e.g. quantised to bytes) are renormalised on load.
NORMAL_LENGTH_TOLERANCE = 1e-4


def _triangles(mode: int, indices: np.ndarray) -> np.ndarray:
    if mode == MODE_TRIANGLES:
        return indices[: len(indices) // 3 * 3].reshape(-1, 3)
    if mode == MODE_TRIANGLE_STRIP:
        k = np.arange(len(indices) - 2)
        even = k % 2 == 0  # odd triangles swap two corners to keep the winding
        a, b, c = indices[k], indices[k + 1], indices[k + 2]
        return np.stack([a, np.where(even, b, c), np.where(even, c, b)], axis=1)
    k = np.arange(1, len(indices) - 1)
    return np.stack([np.full_like(k, indices[0]), indices[k], indices[k + 1]], axis=1)


def _draco_attributes(doc: _Document, primitive, where: str) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Decode a KHR_draco_mesh_compression primitive -> ({attribute: values}, indices), each attribute
    checked against its accessor's count and converted as that accessor says."""
    ext = extension(primitive, DRACO)
    data, _ = doc.view_bytes(ext.get("bufferView"))
    mesh = decode_draco_mesh(bytes(data), where)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1)
    decoded: dict[str, np.ndarray] = {}
    for name, unique_id in (ext.get("attributes") or {}).items():
        attribute = mesh.get_attribute_by_unique_id(unique_id)
        if attribute is None:
            raise ValueError(f"{where}: {DRACO} names attribute {name} id {unique_id}, which the stream lacks")
        values = np.asarray(attribute["data"])
        accessor = doc.item("accessors", primitive.attributes[name])
        if values.shape[0] != accessor.count:
            raise ValueError(f"{where}: {DRACO} {name} has {values.shape[0]} values, its accessor says {accessor.count}")
        # Draco keeps integers as stored; a normalised accessor maps them to 0..1 as glTF does.
        dtype = COMPONENT_TYPES.get(accessor.componentType)
        if dtype is not None and dtype.kind != "f" and values.dtype.kind != "f":
            values = values.astype(dtype)
        decoded[name] = accessor_values(values.reshape(len(values), -1), bool(accessor.normalized), f"{where}: {name}")
    return decoded, faces


def _read_primitive(doc: _Document, primitive, mesh_index: int, where: str, joint_count: int, uv_set: int,
                    rigid_joint: int | None) -> dict:
    """One triangle primitive -> positions, normals, uvs, faces (local), joints, weights, and its morph
    targets as [(position deltas, normal deltas or None)] (crowdbake.formats.gltf.morphs)."""
    attributes = primitive.attributes or {}
    decoded, draco_indices = _draco_attributes(doc, primitive, where) if extension(primitive, DRACO) is not None else ({}, None)

    def attribute(name: str) -> np.ndarray | None:
        if name in decoded:
            return decoded[name]
        return doc.accessor(attributes[name]) if name in attributes else None

    required = ("POSITION",) if rigid_joint is not None else ("POSITION", "JOINTS_0", "WEIGHTS_0")
    for name in required:
        if name not in attributes:
            raise ValueError(f"{where} has no {name}")
    positions = attribute("POSITION").astype(np.float32)
    count = len(positions)
    if positions.shape[1] != 3:
        raise ValueError(f"{where}: POSITION must be VEC3")

    def sized(name: str, width: int) -> np.ndarray | None:
        values = attribute(name)
        if values is not None and values.shape != (count, width):
            raise ValueError(f"{where}: {name} is {values.shape}, expected ({count}, {width})")
        return values

    if draco_indices is not None:
        indices = draco_indices
    elif primitive.indices is not None:
        indices = doc.accessor(primitive.indices)
        if indices.shape[1] != 1 or indices.dtype.kind != "i":
            raise ValueError(f"{where}: indices must be unsigned integer scalars")
        indices = indices[:, 0]
    else:
        indices = np.arange(count, dtype=np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= count):
        raise ValueError(f"{where}: index {indices.max()} is out of range for {count} vertices")
    faces = _triangles(primitive.mode if primitive.mode is not None else MODE_TRIANGLES, indices)

    if rigid_joint is None:
        # Up to two sets of 4 influences; keep the 4 strongest and renormalise.
        joint_sets = [sized(f"JOINTS_{k}", 4) for k in range(2)]
        weight_sets = [sized(f"WEIGHTS_{k}", 4) for k in range(2)]
        joints = np.concatenate([j for j in joint_sets if j is not None], axis=1)
        weights = np.concatenate([w for w in weight_sets if w is not None], axis=1).astype(np.float64)
        if joints.shape != weights.shape:
            raise ValueError(f"{where}: JOINTS_n and WEIGHTS_n sets do not pair up")
        if joints.dtype.kind != "i":
            raise ValueError(f"{where}: JOINTS_0 must be unsigned integers")
        if joints.shape[1] > 4:
            order = np.argsort(-weights, axis=1, kind="stable")[:, :4]
            joints = np.take_along_axis(joints, order, axis=1)
            weights = np.take_along_axis(weights, order, axis=1)
            logger.info("%s: kept the 4 strongest of 8 influences per vertex", where)
        weights = np.clip(weights, 0.0, None)
        used = weights > 0
        if joints[used].size and (joints[used].min() < 0 or joints[used].max() >= joint_count):
            raise ValueError(f"{where}: a joint index exceeds the skin's {joint_count} joints")
        joints = np.where(used, joints, 0)
        total = weights.sum(axis=1, keepdims=True)
        if (total < MIN_WEIGHT_SUM).any():
            raise ValueError(f"{where}: {int((total < MIN_WEIGHT_SUM).sum())} vertices have no skin weight")
        # Renormalise only rows that need it, so valid files round-trip bit for bit.
        weights = np.where(np.abs(total - 1.0) > WEIGHT_SUM_TOLERANCE, weights / total, weights)
    else:
        joints = np.zeros((count, 4), np.int64)
        joints[:, 0] = rigid_joint
        weights = np.zeros((count, 4))
        weights[:, 0] = 1.0
    normals = sized("NORMAL", 3)
    uvs = sized(f"TEXCOORD_{uv_set}", 2)
    targets = primitive_targets(doc, primitive, mesh_index, where, count, draco_indices is not None)
    return {
        "targets": targets,
        "positions": positions,
        "normals": normals.astype(np.float32) if normals is not None else vertex_normals(positions, faces).astype(np.float32),
        "uvs": uvs.astype(np.float32) if uvs is not None else np.zeros((count, 2), np.float32),
        "faces": faces,
        "joints": joints,
        "weights": weights,
    }


def _mesh_primitives(doc: _Document, mesh_index: int, rigid_joint: int | None):
    """(primitive, where, rigid joint) for each triangle primitive of meshes[mesh_index]."""
    out = []
    for number, primitive in enumerate(doc.item("meshes", mesh_index).primitives or []):
        where = f"{doc.where}: meshes[{mesh_index}].primitives[{number}]"
        mode = primitive.mode if primitive.mode is not None else MODE_TRIANGLES
        if mode not in (MODE_TRIANGLES, MODE_TRIANGLE_STRIP, MODE_TRIANGLE_FAN):
            logger.warning("%s: skipping a primitive of mode %s (not triangles)", where, mode)
            continue
        out.append((primitive, where, rigid_joint))
    return out


def skin_inverse_binds(doc: _Document, skin_index: int) -> np.ndarray:
    """skins[skin_index]'s inverse bind matrices, (J, 4, 4) float32 (identity when the file gives none)."""
    skin = doc.item("skins", skin_index)
    count = len(skin.joints or [])
    if skin.inverseBindMatrices is None:
        return np.tile(np.eye(4, dtype=np.float32), (count, 1, 1))
    ibm = doc.accessor(skin.inverseBindMatrices)
    if ibm.shape != (count, 16):
        raise ValueError(f"{doc.where}: skins[{skin_index}].inverseBindMatrices is {ibm.shape}, expected ({count}, 16) MAT4")
    return ibm.reshape(count, 4, 4).transpose(0, 2, 1).astype(np.float32)


def _other_skin(doc: _Document, other: int, node_to_joint: dict[int, int], inverse_bind: np.ndarray):
    """(joint map, bind matrix) that re-expresses skins[other]'s meshes in the chosen skin, or None when
    its joints are not all joints of the chosen skin. A second skin over the same skeleton (RobotExpressive's
    left hand) binds each joint j with its own inverse bind matrix; when inverse(chosen(j)) @ other(j) is
    one matrix for all its joints (the identity when both skins were bound in one pose), that matrix
    moves its vertices into the chosen skin's bind space, and the joint indices are remapped."""
    joints = doc.item("skins", other).joints or []
    if not joints or any(node not in node_to_joint for node in joints):
        return None
    mapping = np.array([node_to_joint[node] for node in joints], np.int64)
    corrections = np.linalg.inv(inverse_bind[mapping].astype(np.float64)) @ skin_inverse_binds(doc, other).astype(np.float64)
    if np.abs(corrections - corrections[:1]).max() > BIND_TOLERANCE * max(1.0, np.abs(corrections).max()):
        raise ValueError(f"{doc.where}: skins[{other}] shares the skeleton but was bound in another pose than the chosen skin; "
                         "re-export the character with one skin")
    return mapping, corrections[0]


def read_meshes(doc: _Document, skin_index: int, joint_count: int, anchor: np.ndarray, between: np.ndarray,
                 local: np.ndarray, inverse_bind: np.ndarray,
                 node_to_joint: dict[int, int] | None = None) -> tuple[dict[str, np.ndarray], list[Material], dict]:
    """Merge every primitive of the skinned meshes (those of other skins over the same joints too, see
    _other_skin) and of rigid meshes under a joint into one mesh -> (arrays, materials, morphs), morphs
    holding "targets" (list of MorphTarget), "weights" ((N,) defaults) and "node_targets" (node ->
    (first target, count), what the weights channels are resolved by)."""
    nodes = doc.gltf.nodes
    wanted: list[tuple[int, int, int | None, np.ndarray | None]] = []  # (node, mesh, rigid joint, bind matrix)
    remaps: dict[int, np.ndarray] = {}  # mesh of another skin -> its joint indices in the chosen skin
    seen_skinned: set[int] = set()
    for index, node in enumerate(nodes):
        if node.mesh is None:
            continue
        if node.skin == skin_index:
            if node.mesh not in seen_skinned:
                seen_skinned.add(node.mesh)
                wanted.append((index, node.mesh, None, None))
        elif node.skin is not None:
            shared = _other_skin(doc, node.skin, node_to_joint or {}, inverse_bind)
            if shared is None:
                logger.warning("%s: nodes[%d] uses skins[%d], whose joints are not all joints of the chosen skin %d; left out",
                               doc.where, index, node.skin, skin_index)
            elif node.mesh not in seen_skinned:
                seen_skinned.add(node.mesh)
                remaps[node.mesh] = shared[0]
                wanted.append((index, node.mesh, None, None if np.allclose(shared[1], np.eye(4)) else shared[1]))
        elif anchor[index] >= 0:
            joint = int(anchor[index])
            # A rigid mesh under joint j sits at world(j) @ between @ local(node) @ p; in bind space that is
            # inverse(inverseBind(j)) @ between @ local(node) @ p, which skinning by j alone maps back.
            bind = np.linalg.inv(inverse_bind[joint].astype(np.float64)) @ between[index] @ local[index]
            wanted.append((index, node.mesh, joint, bind))
        else:
            logger.warning("%s: nodes[%d] holds a mesh with no skin and no joint above it; left out", doc.where, index)
    parts: dict[str, list[np.ndarray]] = {key: [] for key in ("positions", "normals", "uvs", "faces", "joints", "weights", "materials")}
    materials: list[Material] = []
    uv_sets: list[int] = []  # the TEXCOORD_n set each material's base colour texture reads
    material_slots: dict[int | None, int] = {}
    images: dict[int, np.ndarray] = {}
    base = 0
    morph_targets: list[MorphTarget] = []
    morph_weights: list[np.ndarray] = []
    node_targets: dict[int, tuple[int, int]] = {}  # node -> (its mesh's first target, count)
    for node_index, mesh_index, rigid_joint, bind in wanted:
        mesh_start = base
        primitive_deltas = []
        for primitive, where, joint in _mesh_primitives(doc, mesh_index, rigid_joint):
            if primitive.material not in material_slots:
                material, uv_set = read_material(doc, primitive.material, images)
                material_slots[primitive.material] = len(materials)
                materials.append(material)
                uv_sets.append(uv_set)
            slot = material_slots[primitive.material]
            remap = remaps.get(mesh_index)
            part = _read_primitive(doc, primitive, mesh_index, where, joint_count if remap is None else len(remap), uv_sets[slot], joint)
            if remap is not None:
                part["joints"] = remap[part["joints"]]
            if bind is not None:
                part["positions"] = (part["positions"].astype(np.float64) @ bind[:3, :3].T + bind[:3, 3]).astype(np.float32)
                normal_matrix = np.linalg.inv(bind[:3, :3]).T
                part["normals"] = (part["normals"].astype(np.float64) @ normal_matrix.T).astype(np.float32)
                # Displacements are directions: the bind matrix's linear part moves them, not its translation.
                part["targets"] = [
                    ((p.astype(np.float64) @ bind[:3, :3].T).astype(np.float32),
                     None if n is None else (n.astype(np.float64) @ normal_matrix.T).astype(np.float32))
                    for p, n in part["targets"]
                ]
            primitive_deltas.append(part["targets"])
            for key in ("positions", "normals", "uvs", "joints", "weights"):
                parts[key].append(part[key])
            parts["faces"].append(part["faces"] + base)
            parts["materials"].append(np.full(len(part["positions"]), slot, np.uint16))
            base += len(part["positions"])
        targets = mesh_targets(doc, mesh_index, mesh_start, primitive_deltas, f"{doc.where}: nodes[{node_index}]")
        if targets:
            node_targets[node_index] = (len(morph_targets), len(targets))
            morph_targets.extend(targets)
            morph_weights.append(default_weights(doc, mesh_index, len(targets), f"{doc.where}: nodes[{node_index}]"))
            logger.info("%s: meshes[%d] has %d morph targets (%s), applied when posed", doc.where, mesh_index, len(targets),
                        ", ".join(t.name for t in targets))
    if not parts["positions"]:
        raise ValueError(f"{doc.where}: no triangle mesh uses skins[{skin_index}]")
    merged = {key: np.concatenate(values) for key, values in parts.items()}
    # Renormalise only normals that are off (quantised files), so valid files round-trip bit for bit.
    lengths = np.linalg.norm(merged["normals"].astype(np.float64), axis=1, keepdims=True)
    off = (np.abs(lengths - 1.0) > NORMAL_LENGTH_TOLERANCE) & (lengths > 0)
    merged["normals"] = np.where(off, merged["normals"] / np.where(lengths > 0, lengths, 1.0), merged["normals"])
    morphs = {
        "targets": morph_targets,
        "weights": np.concatenate(morph_weights) if morph_weights else np.zeros(0, np.float32),
        "node_targets": node_targets,
    }
    return merged, materials, morphs
