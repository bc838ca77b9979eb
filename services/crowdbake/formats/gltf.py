"""Skinned, animated glTF 2.0 characters: read (.glb, .gltf) and write (.glb), with json + numpy only.

What is read (`load_character`):
  * every triangle primitive of every mesh node that uses the chosen skin, merged into one mesh;
  * the skin's joints in `skin.joints` order (so JOINTS_0 indices are joint indices), their parents,
    rest TRS and inverse bind matrices;
  * one animation's channels that target joints (translation / rotation / scale, LINEAR, STEP or
    CUBICSPLINE samplers);
  * the base colour texture of the first textured primitive, decoded to RGBA8 with Pillow.

Transforms, as the glTF spec defines skinning: a skinned vertex is
``sum_k w_k * world(joint_k) @ inverseBind(joint_k) @ p``; the transform of the node that holds the
mesh is ignored, but the transforms of nodes *above* the skeleton (CesiumMan's Z-up to Y-up root,
for instance) are part of world(joint). `Character.joint_parent_transforms[j]` holds the static product
of the non-joint nodes between joint j and its parent joint (or the scene root), so
``world(j) = world(parent(j)) @ joint_parent_transforms[j] @ local(j)``. Animations of non-joint nodes
are not followed (a warning says so).

Texture coordinates are kept in glTF's convention: (0, 0) is the top-left of the image, v grows down.

Every offset and length in the file is checked before it is used, so truncated or garbled files
raise ValueError naming the file and the problem instead of reading past a buffer.
"""
from __future__ import annotations

import base64
import io
import json
import logging
import os
import struct
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crowdbake.bake.skinning import quaternion_matrices

logger = logging.getLogger(__name__)

GLB_MAGIC = b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

_COMPONENT_TYPES = {
    5120: np.dtype("i1"),
    5121: np.dtype("u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    5125: np.dtype("<u4"),
    5126: np.dtype("<f4"),
}
_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
MODE_TRIANGLES, MODE_TRIANGLE_STRIP, MODE_TRIANGLE_FAN = 4, 5, 6

INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
PATH_WIDTHS = {"translation": 3, "rotation": 4, "scale": 3}

# Skin weights are normalised on load; a vertex whose weights sum below this is unskinned (a file error).
MIN_WEIGHT_SUM = 1e-6
# Weight rows summing further than this from 1 are renormalised on load (glTF asks for sums of 1).
WEIGHT_SUM_TOLERANCE = 1e-5
# Normals further than this from unit length (e.g. quantised to bytes) are renormalised on load.
NORMAL_LENGTH_TOLERANCE = 1e-4


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
class Character:
    """A skinned character in its bind pose plus one animation (see the module docstring for transforms).

    positions (V, 3) float32 metres, normals (V, 3) float32 unit, uvs (V, 2) float32 (glTF convention;
    zeros when the file has none), faces (T, 3) uint32, joints (V, 4) uint16 joint indices,
    weights (V, 4) float32 summing to 1 per vertex.
    joint_names: J names; joint_parents (J,) int64, -1 for a root; joint_parent_transforms (J, 4, 4)
    float64; inverse_bind_matrices (J, 4, 4) float32; rest_translations (J, 3), rest_rotations (J, 4)
    (x, y, z, w), rest_scales (J, 3) float64: each joint's local TRS when no channel animates it.
    channels: the animation; animation_duration: seconds (0 without animation).
    texture: (H, W, 4) uint8 base colour or None.
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

    @property
    def vertex_count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def joint_count(self) -> int:
        return int(self.joint_parents.shape[0])


# ----------------------------------------------------------------------------------------------
# Small math helpers (column vectors, glTF's column-major matrices)


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> (4,) unit quaternion (x, y, z, w) with w >= 0 (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def trs_matrix(translation: np.ndarray, rotation: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(..., 3), (..., 4) xyzw, (..., 3) -> (..., 4, 4) float64 matrices T @ R @ S."""
    translation = np.asarray(translation, dtype=np.float64)
    rotation_matrix = quaternion_matrices(rotation)
    out = np.zeros(rotation_matrix.shape[:-2] + (4, 4))
    out[..., :3, :3] = rotation_matrix * np.asarray(scale, dtype=np.float64)[..., None, :]
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def decompose_matrix(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(4, 4) affine matrix without shear -> translation (3,), rotation (4,) xyzw, scale (3,)."""
    m = np.asarray(m, dtype=np.float64)
    translation = m[:3, 3].copy()
    scale = np.linalg.norm(m[:3, :3], axis=0)
    if np.any(scale == 0):
        raise ValueError("matrix has a zero scale and cannot be decomposed")
    rotation = m[:3, :3] / scale
    if np.linalg.det(rotation) < 0:  # a mirror: put it in the x scale
        scale[0] = -scale[0]
        rotation[:, 0] = -rotation[:, 0]
    return translation, matrix_to_quaternion(rotation), scale


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals: positions (V, 3), faces (T, 3) -> (V, 3) float32 unit (0 for unused)."""
    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    face_normals = np.cross(positions[faces[:, 1]] - positions[faces[:, 0]], positions[faces[:, 2]] - positions[faces[:, 0]])
    normals = np.zeros_like(positions)
    for corner in range(3):
        for axis in range(3):
            normals[:, axis] += np.bincount(faces[:, corner], face_normals[:, axis], minlength=len(positions))
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Container parsing


def parse_glb(data: bytes, where: str) -> tuple[dict, bytes | None]:
    """GLB bytes -> (JSON document, BIN chunk or None). Checks magic, version, length and every chunk."""
    if len(data) < 12:
        raise ValueError(f"{where}: truncated GLB: {len(data)} bytes, the header alone is 12")
    magic, version, length = struct.unpack_from("<4sII", data)
    if magic != GLB_MAGIC:
        raise ValueError(f"{where}: not a GLB file: magic is {magic!r}, expected {GLB_MAGIC!r}")
    if version != GLB_VERSION:
        raise ValueError(f"{where}: GLB version {version} is not supported (only 2)")
    if length != len(data):
        kind = "truncated GLB" if length > len(data) else "trailing bytes after the GLB"
        raise ValueError(f"{where}: {kind}: header length is {length}, file has {len(data)} bytes")
    chunks: list[tuple[int, bytes]] = []
    offset = 12
    while offset < length:
        if offset + 8 > length:
            raise ValueError(f"{where}: truncated GLB chunk header at byte {offset}")
        chunk_length, chunk_type = struct.unpack_from("<II", data, offset)
        if offset + 8 + chunk_length > length:
            raise ValueError(
                f"{where}: GLB chunk {len(chunks)} claims {chunk_length} bytes at byte {offset + 8}, "
                f"only {length - offset - 8} remain"
            )
        chunks.append((chunk_type, data[offset + 8 : offset + 8 + chunk_length]))
        offset += 8 + chunk_length
    if not chunks or chunks[0][0] != CHUNK_JSON:
        raise ValueError(f"{where}: the first GLB chunk must be JSON")
    document = _parse_json(chunks[0][1], where)
    binary = next((payload for kind, payload in chunks[1:] if kind == CHUNK_BIN), None)
    return document, binary


def _parse_json(text: bytes, where: str) -> dict:
    try:
        document = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{where}: the glTF JSON does not parse: {error}") from None
    if not isinstance(document, dict):
        raise ValueError(f"{where}: the glTF JSON must be an object")
    version = str(document.get("asset", {}).get("version", ""))
    if not version.startswith("2."):
        raise ValueError(f"{where}: asset.version is {version!r}; only glTF 2.x is supported")
    return document


def _decode_uri(uri: str, base: Path, where: str) -> bytes:
    """Bytes behind a buffer/image URI: a base64 data URI or a file relative to the glTF."""
    if uri.startswith("data:"):
        header, _, payload = uri.partition(",")
        if not header.endswith(";base64"):
            raise ValueError(f"{where}: only base64 data URIs are supported, got {header!r}")
        try:
            return base64.b64decode(payload, validate=True)
        except ValueError as error:
            raise ValueError(f"{where}: bad base64 in a data URI: {error}") from None
    relative = urllib.parse.unquote(uri)
    if "://" in relative or Path(relative).is_absolute():
        raise ValueError(f"{where}: external URI {uri!r} is not a relative file path")
    path = base / relative
    if not path.is_file():
        raise ValueError(f"{where}: external file {uri!r} not found next to the glTF ({path})")
    return path.read_bytes()


class _Document:
    """The parsed JSON plus its buffers, with checked accessor reads."""

    def __init__(self, gltf: dict, buffers: list[bytes], where: str, base: Path):
        self.gltf = gltf
        self.buffers = buffers
        self.where = where
        self.base = base

    def item(self, kind: str, index) -> dict:
        items = self.gltf.get(kind, [])
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise ValueError(f"{self.where}: {kind}[{index}] does not exist ({len(items)} defined)")
        return items[index]

    def view_bytes(self, view_index: int) -> tuple[memoryview, int | None]:
        view = self.item("bufferViews", view_index)
        buffer_index = view.get("buffer")
        if not isinstance(buffer_index, int) or not 0 <= buffer_index < len(self.buffers):
            raise ValueError(f"{self.where}: bufferViews[{view_index}] names buffer {buffer_index}, which does not exist")
        buffer = self.buffers[buffer_index]
        offset, length = int(view.get("byteOffset", 0)), int(view.get("byteLength", -1))
        if offset < 0 or length < 0 or offset + length > len(buffer):
            raise ValueError(
                f"{self.where}: bufferViews[{view_index}] (bytes {offset}..{offset + length}) lies outside "
                f"buffer {buffer_index} ({len(buffer)} bytes)"
            )
        return memoryview(buffer)[offset : offset + length], view.get("byteStride")

    def accessor(self, index: int) -> np.ndarray:
        """Accessor `index` as (count, width) array: float32 for floats and normalised ints, else int64."""
        accessor = self.item("accessors", index)
        where = f"{self.where}: accessors[{index}]"
        dtype = _COMPONENT_TYPES.get(accessor.get("componentType"))
        width = _TYPE_WIDTHS.get(accessor.get("type"))
        count = accessor.get("count")
        if dtype is None or width is None:
            raise ValueError(f"{where}: unknown componentType {accessor.get('componentType')} or type {accessor.get('type')}")
        if not isinstance(count, int) or count < 1:
            raise ValueError(f"{where}: count {count!r} must be a positive integer")
        if accessor.get("type") in ("MAT2", "MAT3") and dtype.itemsize < 4:
            raise ValueError(f"{where}: padded {accessor['type']} of {dtype} components is not supported")
        element_size = dtype.itemsize * width
        if "bufferView" in accessor:
            data, stride = self.view_bytes(accessor["bufferView"])
            stride = int(stride or element_size)
            offset = int(accessor.get("byteOffset", 0))
            if stride < element_size or offset < 0:
                raise ValueError(f"{where}: byteStride {stride} is smaller than an element ({element_size} bytes)")
            end = offset + stride * (count - 1) + element_size
            if end > len(data):
                raise ValueError(
                    f"{where}: {count} elements of {element_size} bytes (stride {stride}) from byte {offset} need "
                    f"{end} bytes, its bufferView has {len(data)}"
                )
            values = np.ndarray((count, width), dtype=dtype, buffer=data, offset=offset, strides=(stride, dtype.itemsize)).copy()
        else:
            values = np.zeros((count, width), dtype=dtype)
        if "sparse" in accessor:
            values = self._apply_sparse(accessor["sparse"], values, dtype, width, where)
        if dtype.kind == "f":
            result = values.astype(np.float32)
        elif accessor.get("normalized"):
            # glTF 2.0 section 3.11: signed values map with max(c / (2^(n-1) - 1), -1), unsigned with c / (2^n - 1).
            info = np.iinfo(dtype)
            result = np.maximum(values.astype(np.float64) / info.max, -1.0).astype(np.float32)
        else:
            result = values.astype(np.int64)
        if result.dtype.kind == "f" and not np.isfinite(result).all():
            raise ValueError(f"{where}: contains NaN or infinity")
        return result

    def _apply_sparse(self, sparse: dict, values: np.ndarray, dtype, width: int, where: str) -> np.ndarray:
        count = sparse.get("count", 0)
        indices_info, values_info = sparse.get("indices", {}), sparse.get("values", {})
        index_dtype = _COMPONENT_TYPES.get(indices_info.get("componentType"))
        if not isinstance(count, int) or count < 1 or index_dtype is None or index_dtype.kind != "u":
            raise ValueError(f"{where}: malformed sparse block")
        for info, item_dtype, item_width, label in ((indices_info, index_dtype, 1, "indices"), (values_info, dtype, width, "values")):
            data, _ = self.view_bytes(info.get("bufferView"))
            offset = int(info.get("byteOffset", 0))
            if offset < 0 or offset + count * item_dtype.itemsize * item_width > len(data):
                raise ValueError(f"{where}: sparse {label} lie outside their bufferView")
            array = np.frombuffer(data, dtype=item_dtype, count=count * item_width, offset=offset).reshape(count, item_width)
            if label == "indices":
                sparse_indices = array[:, 0].astype(np.int64)
                if sparse_indices.max() >= len(values):
                    raise ValueError(f"{where}: sparse index {sparse_indices.max()} >= count {len(values)}")
            else:
                values = values.copy()
                values[sparse_indices] = array
        return values


def _open_document(path: Path) -> _Document:
    where = str(path)
    data = path.read_bytes()
    if data[:4] == GLB_MAGIC or path.suffix.lower() == ".glb":
        gltf, binary = parse_glb(data, where)
    else:
        gltf, binary = _parse_json(data, where), None
    buffers: list[bytes] = []
    for index, buffer in enumerate(gltf.get("buffers", [])):
        declared = buffer.get("byteLength")
        if "uri" in buffer:
            payload = _decode_uri(buffer["uri"], path.parent, f"{where}: buffers[{index}]")
        elif index == 0 and binary is not None:
            payload = binary
        else:
            raise ValueError(f"{where}: buffers[{index}] has no uri and there is no GLB BIN chunk for it")
        if not isinstance(declared, int) or declared < 0 or declared > len(payload):
            raise ValueError(f"{where}: buffers[{index}] declares {declared} bytes but only {len(payload)} are present")
        buffers.append(bytes(payload[:declared]))
    return _Document(gltf, buffers, where, path.parent)


# ----------------------------------------------------------------------------------------------
# Scene graph


def _local_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        values = np.asarray(node["matrix"], dtype=np.float64)
        if values.shape != (16,) or not np.isfinite(values).all():
            raise ValueError(f"node matrix must be 16 finite numbers, got {node['matrix']!r}")
        return values.reshape(4, 4).T  # glTF stores column-major
    return trs_matrix(node.get("translation", [0, 0, 0]), node.get("rotation", [0, 0, 0, 1]), node.get("scale", [1, 1, 1]))


def _node_parents(doc: _Document) -> np.ndarray:
    nodes = doc.gltf.get("nodes", [])
    parents = np.full(len(nodes), -1, dtype=np.int64)
    for index, node in enumerate(nodes):
        for child in node.get("children", []):
            if not isinstance(child, int) or not 0 <= child < len(nodes):
                raise ValueError(f"{doc.where}: nodes[{index}] has child {child}, which does not exist")
            if parents[child] != -1:
                raise ValueError(f"{doc.where}: nodes[{child}] has two parents ({parents[child]} and {index})")
            parents[child] = index
    for start in range(len(nodes)):  # a cycle would loop forever when walking up
        seen, node = 0, start
        while node != -1:
            node, seen = parents[node], seen + 1
            if seen > len(nodes):
                raise ValueError(f"{doc.where}: the node hierarchy has a cycle through nodes[{start}]")
    return parents


def _load_texture(doc: _Document, primitives: list[dict]) -> np.ndarray | None:
    texture_indices = []
    for primitive in primitives:
        if "material" in primitive:
            material = doc.item("materials", primitive["material"])
            info = material.get("pbrMetallicRoughness", {}).get("baseColorTexture")
            if info is not None:
                texture_indices.append(info.get("index"))
    if not texture_indices:
        return None
    if len(set(texture_indices)) > 1:
        logger.warning("%s: primitives use %d base colour textures; keeping the first", doc.where, len(set(texture_indices)))
    texture = doc.item("textures", texture_indices[0])
    if "source" not in texture:
        logger.warning("%s: texture %d has no source image (extension-only textures are not read)", doc.where, texture_indices[0])
        return None
    image = doc.item("images", texture["source"])
    if "bufferView" in image:
        data, _ = doc.view_bytes(image["bufferView"])
        data = bytes(data)
    elif "uri" in image:
        data = _decode_uri(image["uri"], doc.base, f"{doc.where}: images[{texture['source']}]")
    else:
        raise ValueError(f"{doc.where}: images[{texture['source']}] has neither bufferView nor uri")
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as picture:
            return np.asarray(picture.convert("RGBA"), dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError) as error:
        raise ValueError(f"{doc.where}: images[{texture['source']}] does not decode: {error}") from None


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


def _skinned_primitives(doc: _Document, skin_index: int) -> list[dict]:
    primitives = []
    for node in doc.gltf.get("nodes", []):
        if node.get("skin") == skin_index and "mesh" in node:
            for primitive in doc.item("meshes", node["mesh"]).get("primitives", []):
                mode = primitive.get("mode", MODE_TRIANGLES)
                if mode not in (MODE_TRIANGLES, MODE_TRIANGLE_STRIP, MODE_TRIANGLE_FAN):
                    logger.warning("%s: skipping a primitive of mode %s (not triangles)", doc.where, mode)
                    continue
                if primitive.get("targets"):
                    logger.warning("%s: morph targets are ignored", doc.where)
                primitives.append(primitive)
    return primitives


def _read_mesh(doc: _Document, primitives: list[dict], joint_count: int) -> dict[str, np.ndarray]:
    parts: dict[str, list[np.ndarray]] = {key: [] for key in ("positions", "normals", "uvs", "faces", "joints", "weights")}
    base = 0
    for number, primitive in enumerate(primitives):
        where = f"{doc.where}: skinned primitive {number}"
        attributes = primitive.get("attributes", {})
        for required in ("POSITION", "JOINTS_0", "WEIGHTS_0"):
            if required not in attributes:
                raise ValueError(f"{where} has no {required}")
        positions = doc.accessor(attributes["POSITION"])
        count = len(positions)
        if positions.shape[1] != 3:
            raise ValueError(f"{where}: POSITION must be VEC3")

        def attribute(name: str, width: int) -> np.ndarray | None:
            if name not in attributes:
                return None
            values = doc.accessor(attributes[name])
            if values.shape != (count, width):
                raise ValueError(f"{where}: {name} is {values.shape}, expected ({count}, {width})")
            return values

        if "indices" in primitive:
            indices = doc.accessor(primitive["indices"])
            if indices.shape[1] != 1 or indices.dtype.kind != "i":
                raise ValueError(f"{where}: indices must be unsigned integer scalars")
            indices = indices[:, 0]
        else:
            indices = np.arange(count, dtype=np.int64)
        if indices.size and (indices.min() < 0 or indices.max() >= count):
            raise ValueError(f"{where}: index {indices.max()} is out of range for {count} vertices")
        faces = _triangles(primitive.get("mode", MODE_TRIANGLES), indices)

        # Up to two sets of 4 influences; keep the 4 strongest and renormalise.
        joint_sets = [attribute(f"JOINTS_{k}", 4) for k in range(2)]
        weight_sets = [attribute(f"WEIGHTS_{k}", 4) for k in range(2)]
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
        normals = attribute("NORMAL", 3)
        uvs = attribute("TEXCOORD_0", 2)
        parts["positions"].append(positions)
        parts["normals"].append(normals if normals is not None else vertex_normals(positions, faces))
        parts["uvs"].append(uvs if uvs is not None else np.zeros((count, 2), np.float32))
        parts["faces"].append(faces + base)
        parts["joints"].append(joints)
        # Renormalise only rows that need it, so valid files round-trip bit for bit.
        parts["weights"].append(np.where(np.abs(total - 1.0) > WEIGHT_SUM_TOLERANCE, weights / total, weights))
        base += count
    merged = {key: np.concatenate(values) for key, values in parts.items()}
    # Renormalise only normals that are off (quantised files), so valid files round-trip bit for bit.
    lengths = np.linalg.norm(merged["normals"].astype(np.float64), axis=1, keepdims=True)
    off = (np.abs(lengths - 1.0) > NORMAL_LENGTH_TOLERANCE) & (lengths > 0)
    merged["normals"] = np.where(off, merged["normals"] / np.where(lengths > 0, lengths, 1.0), merged["normals"])
    return merged


def _read_animation(doc: _Document, animation_index: int, node_to_joint: dict[int, int], joint_ancestors: set[int]):
    animations = doc.gltf.get("animations", [])
    if not animations:
        return [], 0.0
    animation = doc.item("animations", animation_index)
    samplers = animation.get("samplers", [])
    channels: list[AnimationChannel] = []
    duration = 0.0
    for number, channel in enumerate(animation.get("channels", [])):
        where = f"{doc.where}: animations[{animation_index}].channels[{number}]"
        target = channel.get("target", {})
        path, node = target.get("path"), target.get("node")
        sampler_index = channel.get("sampler")
        if not isinstance(sampler_index, int) or not 0 <= sampler_index < len(samplers):
            raise ValueError(f"{where}: sampler {sampler_index} does not exist")
        sampler = samplers[sampler_index]
        interpolation = sampler.get("interpolation", "LINEAR")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"{where}: unknown interpolation {interpolation!r}")
        times = doc.accessor(sampler.get("input"))
        if times.shape[1] != 1 or times.dtype.kind != "f":
            raise ValueError(f"{where}: sampler input must be float scalars")
        times = times[:, 0]
        if len(times) > 1 and not (np.diff(times) > 0).all():
            raise ValueError(f"{where}: keyframe times must increase strictly")
        duration = max(duration, float(times[-1]))
        if node not in node_to_joint:
            if node in joint_ancestors and path in PATH_WIDTHS:
                logger.warning("%s: animates node %s above the skeleton; only its rest transform is used", where, node)
            continue
        if path not in PATH_WIDTHS:
            logger.debug("%s: ignoring %r channel", where, path)
            continue
        values = doc.accessor(sampler.get("output")).astype(np.float32)
        width = PATH_WIDTHS[path]
        keys = 3 * len(times) if interpolation == "CUBICSPLINE" else len(times)
        if values.shape != (keys, width):
            raise ValueError(f"{where}: {path} output is {values.shape}, expected ({keys}, {width})")
        if interpolation == "CUBICSPLINE":
            values = values.reshape(len(times), 3, width)
        channels.append(AnimationChannel(node_to_joint[node], path, times.astype(np.float32), values, interpolation))
    return channels, duration


def _unit_quaternions(q: np.ndarray, where: str) -> np.ndarray:
    """Normalise quaternions that are off unit length (kept bit for bit otherwise); reject zero ones."""
    length = np.linalg.norm(q, axis=1, keepdims=True)
    if (length < 1e-6).any():
        raise ValueError(f"{where}: a joint rotation is the zero quaternion")
    return np.where(np.abs(length - 1.0) > NORMAL_LENGTH_TOLERANCE, q / length, q)


def _mesh_name(doc: _Document, skin_index: int) -> str:
    for node in doc.gltf.get("nodes", []):
        if node.get("skin") == skin_index and "mesh" in node:
            return str(doc.item("meshes", node["mesh"]).get("name", ""))
    return ""


# What a glTF whose JSON has the wrong shape (null where an object belongs, a list as an index, nesting
# deep enough to exhaust the parser's recursion) raises while it is walked. The reader's contract is
# ValueError for every bad file, so these are turned into one at this boundary.
_MALFORMED_STRUCTURE = (TypeError, AttributeError, KeyError, IndexError, OverflowError, RecursionError, ZeroDivisionError, struct.error)


def load_character(path: str | os.PathLike, skin: int = 0, animation: int = 0) -> Character:
    """Load skin `skin` of a .glb/.gltf (its meshes merged) and animation `animation` into a Character.

    Raises ValueError naming the file for anything the file gets wrong, its JSON's shape included."""
    try:
        return _load_character(Path(path), skin, animation)
    except _MALFORMED_STRUCTURE as error:
        raise ValueError(f"{path}: the glTF JSON does not have the structure glTF 2.0 requires ({type(error).__name__}: {error})") from None


def _load_character(path: Path, skin: int, animation: int) -> Character:
    doc = _open_document(path)
    gltf, where = doc.gltf, doc.where
    skin_info = doc.item("skins", skin) if gltf.get("skins") else None
    if skin_info is None:
        raise ValueError(f"{where}: the file has no skin; a character needs a skinned mesh")
    joint_nodes = skin_info.get("joints", [])
    nodes = gltf.get("nodes", [])
    if not joint_nodes or not all(isinstance(n, int) and 0 <= n < len(nodes) for n in joint_nodes):
        raise ValueError(f"{where}: skins[{skin}].joints must list existing nodes")
    if len(set(joint_nodes)) != len(joint_nodes):
        raise ValueError(f"{where}: skins[{skin}].joints lists a node twice")
    node_to_joint = {node: index for index, node in enumerate(joint_nodes)}
    joint_count = len(joint_nodes)

    parents = _node_parents(doc)
    joint_parents = np.full(joint_count, -1, dtype=np.int64)
    joint_parent_transforms = np.tile(np.eye(4), (joint_count, 1, 1))
    joint_ancestors: set[int] = set()
    rest = np.zeros((joint_count, 10))
    for joint, node_index in enumerate(joint_nodes):
        node = nodes[node_index]
        if "matrix" in node:
            translation, rotation, scale = decompose_matrix(_local_matrix(node))
        else:
            translation = node.get("translation", [0, 0, 0])
            rotation = node.get("rotation", [0, 0, 0, 1])
            scale = node.get("scale", [1, 1, 1])
        rest[joint] = np.concatenate([translation, rotation, scale])
        above = np.eye(4)
        ancestor = parents[node_index]
        while ancestor != -1 and ancestor not in node_to_joint:
            above = _local_matrix(nodes[ancestor]) @ above
            joint_ancestors.add(int(ancestor))
            ancestor = parents[ancestor]
        joint_parents[joint] = node_to_joint.get(int(ancestor), -1)
        joint_parent_transforms[joint] = above
    if not np.isfinite(rest).all():
        raise ValueError(f"{where}: a joint has a non-finite rest transform")

    if "inverseBindMatrices" in skin_info:
        ibm = doc.accessor(skin_info["inverseBindMatrices"])
        if ibm.shape != (joint_count, 16):
            raise ValueError(f"{where}: inverseBindMatrices is {ibm.shape}, expected ({joint_count}, 16) MAT4")
        inverse_bind = ibm.reshape(joint_count, 4, 4).transpose(0, 2, 1).astype(np.float32)
    else:
        inverse_bind = np.tile(np.eye(4, dtype=np.float32), (joint_count, 1, 1))

    primitives = _skinned_primitives(doc, skin)
    if not primitives:
        raise ValueError(f"{where}: no triangle mesh uses skins[{skin}]")
    mesh = _read_mesh(doc, primitives, joint_count)
    channels, duration = _read_animation(doc, animation, node_to_joint, joint_ancestors)
    names = [str(nodes[n].get("name", f"joint{k}")) for k, n in enumerate(joint_nodes)]
    logger.debug("%s: %d vertices, %d triangles, %d joints, %d channels, %.3f s", where,
                 len(mesh["positions"]), len(mesh["faces"]), joint_count, len(channels), duration)
    return Character(
        positions=mesh["positions"].astype(np.float32),
        normals=mesh["normals"].astype(np.float32),
        uvs=mesh["uvs"].astype(np.float32),
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
        texture=_load_texture(doc, primitives),
        name=_mesh_name(doc, skin) or path.stem,
    )


# ----------------------------------------------------------------------------------------------
# Writing


class _BinaryBuilder:
    """Accumulates 4-byte aligned bufferViews and accessors for one GLB buffer."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.length = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        padding = (-self.length) % 4
        if padding:
            self.chunks.append(b"\0" * padding)
            self.length += padding
        view = {"buffer": 0, "byteOffset": self.length, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        self.chunks.append(data)
        self.length += len(data)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, component: int, target: int | None = None, bounds: bool = False) -> int:
        dtype = _COMPONENT_TYPES[component]
        array = np.ascontiguousarray(array, dtype=dtype)
        count = array.shape[0]
        accessor = {"bufferView": self.view(array.tobytes(), target), "componentType": component, "count": count, "type": kind}
        if bounds:
            flat = array.reshape(count, -1)
            cast = float if dtype.kind == "f" else int
            accessor["min"] = [cast(v) for v in flat.min(axis=0)]
            accessor["max"] = [cast(v) for v in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def payload(self) -> bytes:
        return b"".join(self.chunks) + b"\0" * ((-self.length) % 4)


def _png_bytes(texture: np.ndarray) -> bytes:
    from PIL import Image

    texture = np.asarray(texture, dtype=np.uint8)
    if texture.ndim != 3 or texture.shape[2] != 4:
        raise ValueError(f"texture must be (H, W, 4) uint8, got {texture.shape}")
    out = io.BytesIO()
    Image.fromarray(texture, "RGBA").save(out, format="PNG", optimize=False, compress_level=6)
    return out.getvalue()


def encode_character(character: Character) -> bytes:
    """GLB bytes for a Character: one mesh, one skin, one animation, the texture embedded as PNG.

    Joints become nodes 0..J-1 in joint order; a non-identity joint_parent_transforms[j] becomes a
    helper node with that matrix between joint j and its parent. The output is deterministic.
    """
    c = character
    vertex_count, joint_count = c.vertex_count, c.joint_count
    for name, array, shape in (
        ("normals", c.normals, (vertex_count, 3)),
        ("uvs", c.uvs, (vertex_count, 2)),
        ("joints", c.joints, (vertex_count, 4)),
        ("weights", c.weights, (vertex_count, 4)),
        ("inverse_bind_matrices", c.inverse_bind_matrices, (joint_count, 4, 4)),
        ("joint_parent_transforms", c.joint_parent_transforms, (joint_count, 4, 4)),
    ):
        if np.shape(array) != shape:
            raise ValueError(f"{name} must be {shape}, got {np.shape(array)}")
    faces = np.asarray(c.faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.max() >= vertex_count:
        raise ValueError("faces must be (T, 3) indices into the vertices")
    if np.asarray(c.joints).max() >= joint_count:
        raise ValueError("a joint index exceeds the joint count")

    builder = _BinaryBuilder()
    nodes: list[dict] = []
    for j in range(joint_count):
        node: dict = {"name": c.joint_names[j] if j < len(c.joint_names) else f"joint{j}"}
        t, r, s = c.rest_translations[j], c.rest_rotations[j], c.rest_scales[j]
        if np.any(t != 0):
            node["translation"] = [float(v) for v in t]
        if np.any(r != np.array([0, 0, 0, 1])):
            node["rotation"] = [float(v) for v in r]
        if np.any(s != 1):
            node["scale"] = [float(v) for v in s]
        nodes.append(node)
    scene_roots: list[int] = []
    for j in range(joint_count):
        attach = j
        if not np.allclose(c.joint_parent_transforms[j], np.eye(4), atol=0, rtol=0):
            nodes.append({"name": f"{nodes[j]['name']}_parent", "matrix": [float(v) for v in c.joint_parent_transforms[j].T.reshape(-1)], "children": [j]})
            attach = len(nodes) - 1
        parent = int(c.joint_parents[j])
        if parent < 0:
            scene_roots.append(attach)
        else:
            nodes[parent].setdefault("children", []).append(attach)

    ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
    index_component = 5123 if vertex_count <= 65535 else 5125
    attributes = {
        "POSITION": builder.accessor(c.positions, "VEC3", 5126, ARRAY_BUFFER, bounds=True),
        "NORMAL": builder.accessor(c.normals, "VEC3", 5126, ARRAY_BUFFER),
        "TEXCOORD_0": builder.accessor(c.uvs, "VEC2", 5126, ARRAY_BUFFER),
        "JOINTS_0": builder.accessor(c.joints, "VEC4", 5123, ARRAY_BUFFER),
        "WEIGHTS_0": builder.accessor(c.weights, "VEC4", 5126, ARRAY_BUFFER),
    }
    indices = builder.accessor(faces.reshape(-1), "SCALAR", index_component, ELEMENT_ARRAY_BUFFER)
    primitive: dict = {"attributes": attributes, "indices": indices, "mode": MODE_TRIANGLES}
    gltf: dict = {"asset": {"version": "2.0", "generator": "crowdbake"}}
    if c.texture is not None:
        image_view = builder.view(_png_bytes(c.texture))
        gltf["images"] = [{"bufferView": image_view, "mimeType": "image/png"}]
        # Nearest filtering keeps alpha region codes exact where a viewer samples them.
        gltf["samplers"] = [{"magFilter": 9728, "minFilter": 9984, "wrapS": 33071, "wrapT": 33071}]
        gltf["textures"] = [{"sampler": 0, "source": 0}]
        # alphaMode stays OPAQUE: alpha carries colour-region codes, not coverage.
        gltf["materials"] = [{"name": "body", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 0.9}}]
        primitive["material"] = 0
    inverse_bind = builder.accessor(np.asarray(c.inverse_bind_matrices).transpose(0, 2, 1).reshape(joint_count, 16), "MAT4", 5126)

    if c.channels:
        samplers, channels = [], []
        time_accessors: dict[bytes, int] = {}
        for channel in c.channels:
            times = np.asarray(channel.times, dtype=np.float32)
            key = times.tobytes()
            if key not in time_accessors:
                time_accessors[key] = builder.accessor(times, "SCALAR", 5126, bounds=True)
            width = PATH_WIDTHS[channel.path]
            output = builder.accessor(np.asarray(channel.values, dtype=np.float32).reshape(-1, width), "VEC4" if width == 4 else "VEC3", 5126)
            samplers.append({"input": time_accessors[key], "output": output, "interpolation": channel.interpolation})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": int(channel.joint), "path": channel.path}})
        gltf["animations"] = [{"name": "cycle", "samplers": samplers, "channels": channels}]

    mesh_node = len(nodes)
    nodes.append({"name": c.name or "character", "mesh": 0, "skin": 0})
    gltf.update(
        {
            "scene": 0,
            "scenes": [{"nodes": scene_roots + [mesh_node]}],
            "nodes": nodes,
            "meshes": [{"name": c.name or "character", "primitives": [primitive]}],
            "skins": [{"joints": list(range(joint_count)), "inverseBindMatrices": inverse_bind}],
            "accessors": builder.accessors,
            "bufferViews": builder.views,
            "buffers": [{"byteLength": builder.length}],
        }
    )
    if len(scene_roots) == 1:
        gltf["skins"][0]["skeleton"] = scene_roots[0]
    json_bytes = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    json_bytes += b" " * ((-len(json_bytes)) % 4)
    binary = builder.payload()
    total = 12 + 8 + len(json_bytes) + 8 + len(binary)
    return b"".join(
        [
            struct.pack("<4sII", GLB_MAGIC, GLB_VERSION, total),
            struct.pack("<II", len(json_bytes), CHUNK_JSON),
            json_bytes,
            struct.pack("<II", len(binary), CHUNK_BIN),
            binary,
        ]
    )


def write_character(path: str | os.PathLike, character: Character) -> None:
    """Write a Character as a .glb (see encode_character)."""
    Path(path).write_bytes(encode_character(character))
