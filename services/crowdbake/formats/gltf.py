"""Skinned, animated glTF 2.0 characters: read (.glb, .gltf) and write (.glb).

The document model is pygltflib's (typed dataclasses for nodes, accessors, materials...); compressed
geometry is decoded by DracoPy (KHR_draco_mesh_compression) and meshoptimizer
(EXT_meshopt_compression, its vertex, index and filter decoders); images by Pillow. This module does
the parts no library does: checked accessor reads into numpy, the skin and its hierarchy, the
animation, and merging materials into what the bake consumes.

What is read (`load_character`):
  * every triangle primitive of every mesh node that uses the chosen skin, merged into one mesh (a mesh
    used by several nodes with that skin is read once: for a skinned mesh the node transform does not
    apply, so the copies would coincide); a mesh node *without* a skin that hangs under a joint (a hat
    under the head) is attached rigidly to that joint; other meshes are left out with a warning;
  * the skin's joints in `skin.joints` order (so JOINTS_0 indices are joint indices), their parents,
    rest TRS and inverse bind matrices;
  * one animation, chosen by index or name (`animation=`), its channels that target joints
    (translation / rotation / scale, LINEAR, STEP or CUBICSPLINE samplers);
  * every material the merged mesh uses: `Character.materials` (name, baseColorFactor, base colour
    texture) and `Character.vertex_materials` (index per vertex). `Character.texture` is what the bake
    samples: the one base colour texture times its factor when one material (or one texture and factor)
    covers the mesh, else an atlas of every material (texture times factor, or a flat tile of the
    factor's colour) with the UVs moved into each material's tile. None when nothing is textured and
    every factor is white (the bake's default colour then).

A required extension this reader cannot honour is refused by name (KHR_texture_basisu: KTX2 images
need libktx, see crowdbake.formats.images). Extensions that are only *used* are ignored.

Transforms, as the glTF spec defines skinning: a skinned vertex is
``sum_k w_k * world(joint_k) @ inverseBind(joint_k) @ p``; the transform of the node that holds the
mesh is ignored, but the transforms of nodes *above* the skeleton (CesiumMan's Z-up to Y-up root,
for instance) are part of world(joint). `Character.joint_parent_transforms[j]` holds the static product
of the non-joint nodes between joint j and its parent joint (or the scene root), so
``world(j) = world(parent(j)) @ joint_parent_transforms[j] @ local(j)``. Animations of non-joint nodes
are not followed (a warning says so).

Texture coordinates are kept in glTF's convention: (0, 0) is the top-left of the image, v grows down.

Every offset and length in the file is checked before it is used (accessor extents against their
bufferView before anything is allocated, decompressed sizes against MAX_DECODED_VIEW_BYTES), so
truncated or garbled files raise ValueError naming the file and the problem. The node hierarchy is
walked once (linear in the node count: a 16,000-node chain loads in milliseconds).
"""
from __future__ import annotations

import base64
import dataclasses
import io
import json
import logging
import os
import struct
import typing
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pygltflib

from crowdbake.bake.skinning import quaternion_matrices
from crowdbake.formats.images import KTX2_REFUSAL, decode_rgba

logger = logging.getLogger(__name__)

GLB_MAGIC = b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

_COMPONENT_TYPES = {
    pygltflib.BYTE: np.dtype("i1"),
    pygltflib.UNSIGNED_BYTE: np.dtype("u1"),
    pygltflib.SHORT: np.dtype("<i2"),
    pygltflib.UNSIGNED_SHORT: np.dtype("<u2"),
    pygltflib.UNSIGNED_INT: np.dtype("<u4"),
    pygltflib.FLOAT: np.dtype("<f4"),
}
_TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
MODE_TRIANGLES, MODE_TRIANGLE_STRIP, MODE_TRIANGLE_FAN = pygltflib.TRIANGLES, pygltflib.TRIANGLE_STRIP, pygltflib.TRIANGLE_FAN

INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
PATH_WIDTHS = {"translation": 3, "rotation": 4, "scale": 3}

DRACO = "KHR_draco_mesh_compression"
MESHOPT = "EXT_meshopt_compression"
BASISU = "KHR_texture_basisu"
# Required extensions this reader honours. KHR_mesh_quantization only widens the accessor types
# allowed for positions, normals and UVs, which the accessor reader handles anyway.
READABLE_REQUIRED_EXTENSIONS = frozenset({DRACO, MESHOPT, "KHR_mesh_quantization"})

# Skin weights are normalised on load; a vertex whose weights sum below this is unskinned (a file error).
MIN_WEIGHT_SUM = 1e-6
# Weight rows summing further than this from 1 are renormalised on load (glTF asks for sums of 1).
WEIGHT_SUM_TOLERANCE = 1e-5
# Normals further than this from unit length (e.g. quantised to bytes) are renormalised on load.
NORMAL_LENGTH_TOLERANCE = 1e-4
# A compressed bufferView may claim any decoded size; a character's biggest view (positions of a
# million vertices) is 12 MB, so 256 MiB refuses a lying count before it becomes an allocation.
MAX_DECODED_VIEW_BYTES = 1 << 28
# Components (count x width) of one accessor. Checked before anything is allocated, because a
# zero-filled accessor (no bufferView) costs the file nothing: "count 10^7 of MAT4" in 200 bytes of JSON
# would otherwise become 640 MB of zeros and twice that once converted. 2^24 components hold 4 million
# triangles' indices or 5.5 million positions, beyond any character a crowd needs, and cost at most
# 128 MiB as int64.
MAX_ACCESSOR_COMPONENTS = 1 << 24
# Pixels of empty border around each material's tile in a merged texture: bilinear and mipmapped
# sampling near a tile's edge then reads that tile's own (edge-replicated) colour.
ATLAS_GUTTER = 4
# Side of the flat tile that stands for an untextured material in a merged texture.
FLAT_TILE = 8


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


# pygltflib's own from_dict (dataclasses_json) costs about 0.35 ms per object: 16,000 nodes would take
# six seconds. The same dataclasses are built here directly, from a per-class plan of their type hints.
_PLANS: dict[type, dict[str, tuple[str, typing.Any]]] = {}
_FLAT_CLASSES: set[type] = set()


def _plan(cls: type) -> dict[str, tuple[str, typing.Any]]:
    """{field: (kind, dataclass)} with kind "plain", "object", "objects" (a list of them) or "dict"."""
    plan = _PLANS.get(cls)
    if plan is None:
        plan = {}
        hints = typing.get_type_hints(cls)
        for item in dataclasses.fields(cls):
            hint = hints[item.name]
            if typing.get_origin(hint) is typing.Union:
                hint = next(arg for arg in typing.get_args(hint) if arg is not type(None))
            many = typing.get_origin(hint) is list
            inner = typing.get_args(hint)[0] if many else hint
            if inner is pygltflib.Attributes:  # kept as a plain {name: accessor} dict: JOINTS_1, _CUSTOM...
                plan[item.name] = ("dicts" if many else "dict", None)
            elif dataclasses.is_dataclass(inner):
                plan[item.name] = ("objects" if many else "object", inner)
            else:
                plan[item.name] = ("plain", None)
        _PLANS[cls] = plan
        if all(kind == "plain" for kind, _ in plan.values()):
            _FLAT_CLASSES.add(cls)
    return plan


def _typed(cls: type, value, where: str):
    """A pygltflib dataclass `cls` from its JSON object; unknown members are dropped."""
    if not isinstance(value, dict):
        raise ValueError(f"{where} must be a JSON object, got {type(value).__name__}")
    plan = _plan(cls)
    if cls in _FLAT_CLASSES:  # nodes, buffer views...: nothing nested, the fast path for big files
        return cls(**{key: item for key, item in value.items() if key in plan})
    kwargs = {}
    for key, item in value.items():
        kind, inner = plan.get(key, (None, None))
        if kind is None:
            continue
        if item is None or kind == "plain":
            kwargs[key] = item
        elif kind == "object":
            kwargs[key] = _typed(inner, item, f"{where}.{key}")
        elif kind == "dict":
            if not isinstance(item, dict):
                raise ValueError(f"{where}.{key} must be a JSON object")
            kwargs[key] = item
        else:
            if not isinstance(item, list):
                raise ValueError(f"{where}.{key} must be a JSON array")
            if kind == "objects":
                kwargs[key] = [_typed(inner, element, f"{where}.{key}[{index}]") for index, element in enumerate(item)]
            else:
                kwargs[key] = item
    return cls(**kwargs)


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


def _extension(item, name: str):
    extensions = getattr(item, "extensions", None)
    return extensions.get(name) if isinstance(extensions, dict) else None


class _Document:
    """The typed glTF (pygltflib) plus its buffers, with checked accessor reads.

    gltf: a pygltflib.GLTF2 or its JSON dict; buffers: bytes per glTF buffer (None for a meshopt
    fallback buffer that has no data); base: the folder external URIs are relative to.
    """

    def __init__(self, gltf, buffers: list[bytes | None], where: str, base: Path | None):
        self.gltf = gltf if isinstance(gltf, pygltflib.GLTF2) else _typed(pygltflib.GLTF2, gltf, where)
        self.buffers = buffers
        self.where = where
        self.base = base
        self._decoded_views: dict[int, bytes] = {}

    def item(self, kind: str, index):
        items = getattr(self.gltf, kind) or []
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(items):
            raise ValueError(f"{self.where}: {kind}[{index}] does not exist ({len(items)} defined)")
        return items[index]

    def _buffer_slice(self, buffer_index, offset, length, what: str) -> memoryview:
        if not isinstance(buffer_index, int) or not 0 <= buffer_index < len(self.buffers):
            raise ValueError(f"{self.where}: {what} names buffer {buffer_index}, which does not exist")
        buffer = self.buffers[buffer_index]
        if buffer is None:
            raise ValueError(f"{self.where}: {what} reads buffers[{buffer_index}], a {MESHOPT} fallback that holds no data")
        offset, length = int(offset or 0), int(length if length is not None else -1)
        if offset < 0 or length < 0 or offset + length > len(buffer):
            raise ValueError(
                f"{self.where}: {what} (bytes {offset}..{offset + length}) lies outside buffer {buffer_index} ({len(buffer)} bytes)"
            )
        return memoryview(buffer)[offset : offset + length]

    def view_bytes(self, view_index: int) -> tuple[memoryview, int | None]:
        """The bytes of bufferViews[view_index] (decompressed for EXT_meshopt_compression) and its stride."""
        view = self.item("bufferViews", view_index)
        compressed = _extension(view, MESHOPT)
        if compressed is not None:
            return memoryview(self._meshopt_view(view_index, compressed)), compressed.get("byteStride")
        data = self._buffer_slice(view.buffer, view.byteOffset, view.byteLength, f"bufferViews[{view_index}]")
        return data, view.byteStride

    def _meshopt_view(self, view_index: int, ext: dict) -> bytes:
        """Decode an EXT_meshopt_compression bufferView (its ATTRIBUTES, TRIANGLES or INDICES mode and
        its NONE, OCTAHEDRAL, QUATERNION or EXPONENTIAL filter) with meshoptimizer's decoders."""
        if view_index in self._decoded_views:
            return self._decoded_views[view_index]
        import meshoptimizer

        what = f"bufferViews[{view_index}] ({MESHOPT})"
        source = bytes(self._buffer_slice(ext.get("buffer"), ext.get("byteOffset", 0), ext.get("byteLength"), what))
        count, stride = ext.get("count"), ext.get("byteStride")
        mode, filter_name = ext.get("mode"), ext.get("filter", "NONE")
        if not isinstance(count, int) or not isinstance(stride, int) or count < 1 or stride < 1:
            raise ValueError(f"{self.where}: {what}: count {count!r} and byteStride {stride!r} must be positive integers")
        if count * stride > MAX_DECODED_VIEW_BYTES:
            raise ValueError(f"{self.where}: {what} decodes to {count * stride} bytes, more than {MAX_DECODED_VIEW_BYTES}")
        try:
            if mode == "ATTRIBUTES":
                if stride % 4 or stride > 256:
                    raise ValueError(f"byteStride {stride} must be a multiple of 4 up to 256")
                # The float32 view the decoder returns is only a container: its bytes are the vertices.
                decoded = np.ascontiguousarray(meshoptimizer.decode_vertex_buffer(count, stride, source)).view(np.uint8)
                filters = {"OCTAHEDRAL": meshoptimizer.decode_filter_oct, "QUATERNION": meshoptimizer.decode_filter_quat,
                           "EXPONENTIAL": meshoptimizer.decode_filter_exp}
                if filter_name in filters:
                    decoded = filters[filter_name](decoded, count, stride)
                elif filter_name != "NONE":
                    raise ValueError(f"unknown filter {filter_name!r}")
                result = decoded.tobytes()
            elif mode in ("TRIANGLES", "INDICES"):
                if stride not in (2, 4) or (mode == "TRIANGLES" and count % 3):
                    raise ValueError(f"index byteStride {stride} must be 2 or 4 (and count a multiple of 3 for TRIANGLES)")
                decode = meshoptimizer.decode_index_buffer if mode == "TRIANGLES" else meshoptimizer.decode_index_sequence
                # The decoder writes count * stride bytes at the start of its uint32 array.
                result = decode(count, stride, source).tobytes()[: count * stride]
            else:
                raise ValueError(f"unknown mode {mode!r}")
        except (ValueError, RuntimeError) as error:
            raise ValueError(f"{self.where}: {what} does not decode: {error}") from None
        self._decoded_views[view_index] = result
        return result

    def accessor(self, index: int) -> np.ndarray:
        """Accessor `index` as (count, width) array: float32 for floats and normalised ints, else int64."""
        accessor = self.item("accessors", index)
        where = f"{self.where}: accessors[{index}]"
        dtype = _COMPONENT_TYPES.get(accessor.componentType)
        width = _TYPE_WIDTHS.get(accessor.type)
        count = accessor.count
        if dtype is None or width is None:
            raise ValueError(f"{where}: unknown componentType {accessor.componentType} or type {accessor.type}")
        if not isinstance(count, int) or count < 1:
            raise ValueError(f"{where}: count {count!r} must be a positive integer")
        if count * width > MAX_ACCESSOR_COMPONENTS:
            raise ValueError(f"{where}: {count} elements of {accessor.type} are {count * width} components, more than {MAX_ACCESSOR_COMPONENTS}")
        if accessor.type in ("MAT2", "MAT3") and dtype.itemsize < 4:
            raise ValueError(f"{where}: padded {accessor.type} of {dtype} components is not supported")
        element_size = dtype.itemsize * width
        if accessor.bufferView is not None:
            data, stride = self.view_bytes(accessor.bufferView)
            stride = int(stride or element_size)
            offset = int(accessor.byteOffset or 0)
            if stride < element_size or offset < 0:
                raise ValueError(f"{where}: byteStride {stride} is smaller than an element ({element_size} bytes)")
            end = offset + stride * (count - 1) + element_size
            if end > len(data):  # checked before numpy is asked for anything
                raise ValueError(
                    f"{where}: {count} elements of {element_size} bytes (stride {stride}) from byte {offset} need "
                    f"{end} bytes, its bufferView has {len(data)}"
                )
            values = np.ndarray((count, width), dtype=dtype, buffer=data, offset=offset, strides=(stride, dtype.itemsize)).copy()
        else:
            values = np.zeros((count, width), dtype=dtype)
        if accessor.sparse is not None:
            values = self._apply_sparse(accessor.sparse, values, dtype, width, where)
        return _accessor_values(values, bool(accessor.normalized), where)

    def _apply_sparse(self, sparse, values: np.ndarray, dtype, width: int, where: str) -> np.ndarray:
        count = sparse.count
        indices_info, values_info = sparse.indices, sparse.values
        index_dtype = _COMPONENT_TYPES.get(getattr(indices_info, "componentType", None))
        if not isinstance(count, int) or count < 1 or index_dtype is None or index_dtype.kind != "u" or values_info is None:
            raise ValueError(f"{where}: malformed sparse block")
        sparse_indices = None
        for info, item_dtype, item_width, label in ((indices_info, index_dtype, 1, "indices"), (values_info, dtype, width, "values")):
            data, _ = self.view_bytes(info.bufferView)
            offset = int(info.byteOffset or 0)
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


def _accessor_values(values: np.ndarray, normalized: bool, where: str) -> np.ndarray:
    """Raw accessor components -> float32 (floats; normalised integers) or int64 (other integers)."""
    if values.dtype.kind == "f":
        result = values.astype(np.float32)
    elif normalized:
        # glTF 2.0 section 3.11: signed values map with max(c / (2^(n-1) - 1), -1), unsigned with c / (2^n - 1).
        info = np.iinfo(values.dtype)
        result = np.maximum(values.astype(np.float64) / info.max, -1.0).astype(np.float32)
    else:
        result = values.astype(np.int64)
    if result.dtype.kind == "f" and not np.isfinite(result).all():
        raise ValueError(f"{where}: contains NaN or infinity")
    return result


def _open_document(path: Path) -> _Document:
    where = str(path)
    data = path.read_bytes()
    if data[:4] == GLB_MAGIC or path.suffix.lower() == ".glb":
        gltf, binary = parse_glb(data, where)
    else:
        gltf, binary = _parse_json(data, where), None
    document = _typed(pygltflib.GLTF2, gltf, where)
    _refuse_unreadable_extensions(document, where)
    buffers: list[bytes | None] = []
    for index, buffer in enumerate(document.buffers):
        declared = buffer.byteLength
        if buffer.uri is not None:
            payload = _decode_uri(buffer.uri, path.parent, f"{where}: buffers[{index}]")
        elif index == 0 and binary is not None:
            payload = binary
        elif (_extension(buffer, MESHOPT) or {}).get("fallback"):
            buffers.append(None)  # only compressed views point here; they decode from another buffer
            continue
        else:
            raise ValueError(f"{where}: buffers[{index}] has no uri and there is no GLB BIN chunk for it")
        if not isinstance(declared, int) or declared < 0 or declared > len(payload):
            raise ValueError(f"{where}: buffers[{index}] declares {declared} bytes but only {len(payload)} are present")
        buffers.append(bytes(payload[:declared]))
    return _Document(document, buffers, where, path.parent)


def _refuse_unreadable_extensions(document: pygltflib.GLTF2, where: str) -> None:
    required = document.extensionsRequired or []
    if BASISU in required:
        raise ValueError(f"{where}: requires {BASISU}: every texture {KTX2_REFUSAL}")
    unreadable = sorted(set(required) - READABLE_REQUIRED_EXTENSIONS)
    if unreadable:
        raise ValueError(f"{where}: requires the glTF extension(s) {', '.join(unreadable)}, which crowdbake cannot read")


# ----------------------------------------------------------------------------------------------
# Scene graph


def _local_matrices(doc: _Document) -> np.ndarray:
    """Every node's local transform -> (N, 4, 4) float64, TRS nodes converted in one vectorised call."""
    nodes = doc.gltf.nodes
    count = len(nodes)
    columns = {"translation": [[0.0] * 3] * count, "rotation": [[0.0, 0.0, 0.0, 1.0]] * count, "scale": [[1.0] * 3] * count}
    matrices: dict[int, list] = {}
    for index, node in enumerate(nodes):
        if node.matrix is not None:
            matrices[index] = node.matrix
            continue
        for name, column in columns.items():
            value = getattr(node, name)
            if value is not None:
                column[index] = value  # type: ignore[index]
    arrays = {}
    for name, width in (("translation", 3), ("rotation", 4), ("scale", 3)):
        try:
            arrays[name] = np.array(columns[name], dtype=np.float64)
        except (ValueError, TypeError):
            arrays[name] = np.zeros(0)
        if arrays[name].shape != (count, width) or not np.isfinite(arrays[name]).all():
            bad = next(k for k, v in enumerate(columns[name]) if not (isinstance(v, list) and len(v) == width and np.isfinite(np.asarray(v, dtype=float)).all()))
            raise ValueError(f"{doc.where}: nodes[{bad}].{name} must be {width} finite numbers")
    length = np.linalg.norm(arrays["rotation"], axis=1)
    if (length < 1e-6).any():
        raise ValueError(f"{doc.where}: nodes[{int(np.argmax(length < 1e-6))}] has the zero quaternion as rotation")
    local = trs_matrix(arrays["translation"], arrays["rotation"], arrays["scale"])
    for index, matrix in matrices.items():
        values = np.asarray(matrix, dtype=np.float64)
        if values.shape != (16,) or not np.isfinite(values).all():
            raise ValueError(f"{doc.where}: nodes[{index}].matrix must be 16 finite numbers")
        local[index] = values.reshape(4, 4).T  # glTF stores column-major
    return local


def _node_parents(doc: _Document) -> tuple[np.ndarray, list[int]]:
    """Each node's parent (-1 for roots) and the nodes in parent-before-child order.

    Linear in the node count. Raises ValueError for a missing child, a node with two parents, or a cycle
    (with one parent per node, a node no root reaches lies on or below a cycle)."""
    nodes = doc.gltf.nodes
    parents = np.full(len(nodes), -1, dtype=np.int64)
    for index, node in enumerate(nodes):
        for child in node.children or []:
            if not isinstance(child, int) or not 0 <= child < len(nodes):
                raise ValueError(f"{doc.where}: nodes[{index}] has child {child}, which does not exist")
            if parents[child] != -1 or child == index:
                raise ValueError(f"{doc.where}: nodes[{child}] has two parents ({parents[child]} and {index})")
            parents[child] = index
    order = [int(n) for n in np.flatnonzero(parents == -1)]
    cursor = 0
    while cursor < len(order):
        order.extend(nodes[order[cursor]].children or [])
        cursor += 1
    if len(order) != len(nodes):
        stranded = sorted(set(range(len(nodes))) - set(order))[0]
        raise ValueError(f"{doc.where}: the node hierarchy has a cycle through nodes[{stranded}]")
    return parents, order


def _joint_anchors(parents: np.ndarray, order: list[int], local: np.ndarray, node_to_joint: dict[int, int]):
    """For every node: its nearest joint ancestor (-1 if none) and the product of the non-joint nodes'
    local transforms strictly between that ancestor and the node (N, 4, 4). One pass, parents first."""
    anchor = np.full(len(parents), -1, dtype=np.int64)
    between = np.empty((len(parents), 4, 4))
    identity = np.eye(4)
    for node in order:
        parent = parents[node]
        if parent < 0:
            between[node] = identity
        elif parent in node_to_joint:
            anchor[node], between[node] = node_to_joint[parent], identity
        else:
            anchor[node], between[node] = anchor[parent], between[parent] @ local[parent]
    return anchor, between


# ----------------------------------------------------------------------------------------------
# Materials and textures


def _image_bytes(doc: _Document, image_index: int) -> bytes:
    image = doc.item("images", image_index)
    where = f"{doc.where}: images[{image_index}]"
    if image.mimeType == "image/ktx2":
        raise ValueError(f"{where} {KTX2_REFUSAL}")
    if image.bufferView is not None:
        data, _ = doc.view_bytes(image.bufferView)
        return bytes(data)
    if image.uri is not None:
        return _decode_uri(image.uri, doc.base, where)
    raise ValueError(f"{where} has neither bufferView nor uri")


def _texture_image(doc: _Document, texture_index: int, cache: dict[int, np.ndarray]) -> np.ndarray:
    texture = doc.item("textures", texture_index)
    source = texture.source
    if source is None:
        for name in ("EXT_texture_webp", "MSFT_texture_dds"):
            source = (_extension(texture, name) or {}).get("source", source)
        if source is None and _extension(texture, BASISU) is not None:
            raise ValueError(f"{doc.where}: textures[{texture_index}] {KTX2_REFUSAL}")
        if source is None:
            raise ValueError(f"{doc.where}: textures[{texture_index}] has no source image crowdbake can read")
    if source not in cache:
        cache[source] = decode_rgba(_image_bytes(doc, source), f"{doc.where}: images[{source}]")
    return cache[source]


def _read_material(doc: _Document, index: int | None, images: dict[int, np.ndarray]) -> tuple[Material, int]:
    """Material `index` (None: glTF's default material) -> (Material, TEXCOORD set of its base colour)."""
    if index is None:
        return Material("default", np.ones(4, np.float32)), 0
    material = doc.item("materials", index)
    pbr = material.pbrMetallicRoughness
    factor = np.asarray(pbr.baseColorFactor if pbr is not None and pbr.baseColorFactor else [1, 1, 1, 1], dtype=np.float64)
    if factor.shape != (4,) or not np.isfinite(factor).all():
        raise ValueError(f"{doc.where}: materials[{index}].baseColorFactor must be 4 finite numbers")
    info = pbr.baseColorTexture if pbr is not None else None
    texture = _texture_image(doc, info.index, images) if info is not None else None
    name = material.name or f"material{index}"
    return Material(name, np.clip(factor, 0.0, 1.0).astype(np.float32), texture), int(getattr(info, "texCoord", 0) or 0)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * np.power(np.clip(c, 0.0031308, None), 1 / 2.4) - 0.055)


def tinted_texture(material: Material) -> np.ndarray | None:
    """The material's base colour as the bake samples it: texture (sRGB) times baseColorFactor (linear,
    glTF 2.0 section 3.9.2), as (H, W, 4) uint8; a flat FLAT_TILE square for an untextured one.
    A white factor returns the texture itself, bit for bit; None for an untextured white material."""
    factor = np.asarray(material.base_color_factor, dtype=np.float64)
    if material.texture is None:
        if np.all(factor == 1.0):
            return None
        colour = np.concatenate([_linear_to_srgb(factor[:3]), factor[3:]])
        return np.broadcast_to(np.round(colour * 255).astype(np.uint8), (FLAT_TILE, FLAT_TILE, 4)).copy()
    if np.all(factor == 1.0):
        return material.texture
    texels = material.texture.astype(np.float64) / 255.0
    rgb = _linear_to_srgb(_srgb_to_linear(texels[..., :3]) * factor[:3])
    out = np.concatenate([rgb, texels[..., 3:] * factor[3]], axis=-1)
    return np.round(np.clip(out, 0, 1) * 255).astype(np.uint8)


def merge_material_textures(materials: list[Material], vertex_materials: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """One texture for a mesh of several materials, and its UVs moved into it.

    materials: M materials; vertex_materials (V,) int index into them; uvs (V, 2) float (glTF convention)
    -> (texture (H, W, 4) uint8 or None, uvs (V, 2) float32). One material (or one texture and factor
    shared by all): its tinted texture and the UVs unchanged. Several: the tinted textures side by side
    in one row, each with an ATLAS_GUTTER border of its own edge texels, UVs scaled into their tile
    (UVs outside 0..1 are wrapped first: a repeating texture cannot repeat inside an atlas).
    """
    uvs = np.asarray(uvs, dtype=np.float32)
    used = sorted(set(np.unique(vertex_materials).tolist())) if len(vertex_materials) else []
    tiles = {index: tinted_texture(materials[index]) for index in used}
    if all(tile is None for tile in tiles.values()):
        return None, uvs
    distinct = {(id(materials[i].texture), materials[i].base_color_factor.tobytes()) for i in used}
    if len(distinct) == 1:
        tile = tiles[used[0]]
        if materials[used[0]].texture is None:  # one flat colour: every UV may point anywhere in it
            return tile, np.full_like(uvs, 0.5)
        return tile, uvs
    for index in used:
        if tiles[index] is None:  # a white untextured material next to textured ones: a white tile
            tiles[index] = np.full((FLAT_TILE, FLAT_TILE, 4), 255, np.uint8)
    padded = {i: np.pad(t, ((ATLAS_GUTTER, ATLAS_GUTTER), (ATLAS_GUTTER, ATLAS_GUTTER), (0, 0)), mode="edge") for i, t in tiles.items()}
    height = max(tile.shape[0] for tile in padded.values())
    width = sum(tile.shape[1] for tile in padded.values())
    atlas = np.zeros((height, width, 4), np.uint8)
    out = uvs.copy()
    x = 0
    for index in used:
        tile = padded[index]
        atlas[: tile.shape[0], x : x + tile.shape[1]] = tile
        inner_h, inner_w = tiles[index].shape[:2]
        rows = vertex_materials == index
        local = out[rows]
        if materials[index].texture is None:
            local = np.full_like(local, 0.5)
        elif (local < 0).any() or (local > 1).any():
            logger.warning("material %r has UVs outside 0..1; wrapped into its atlas tile", materials[index].name)
            local = local - np.floor(local)
        out[rows, 0] = (x + ATLAS_GUTTER + local[:, 0] * inner_w) / width
        out[rows, 1] = (ATLAS_GUTTER + local[:, 1] * inner_h) / height
        x += tile.shape[1]
    return atlas, out.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Meshes


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
    """Decode a KHR_draco_mesh_compression primitive with DracoPy -> ({attribute: values}, indices)."""
    import DracoPy

    ext = _extension(primitive, DRACO)
    data, _ = doc.view_bytes(ext.get("bufferView"))
    try:
        mesh = DracoPy.decode(bytes(data))
    except Exception as error:  # DracoPy raises its own exception types for a bad stream
        raise ValueError(f"{where}: the {DRACO} data does not decode: {error}") from None
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
        dtype = _COMPONENT_TYPES.get(accessor.componentType)
        if dtype is not None and dtype.kind != "f" and values.dtype.kind != "f":
            values = values.astype(dtype)
        decoded[name] = _accessor_values(values.reshape(len(values), -1), bool(accessor.normalized), f"{where}: {name}")
    return decoded, faces


def _read_primitive(doc: _Document, primitive, where: str, joint_count: int, uv_set: int, rigid_joint: int | None) -> dict[str, np.ndarray]:
    """One triangle primitive -> positions, normals, uvs, faces (local), joints, weights."""
    attributes = primitive.attributes or {}
    decoded, draco_indices = _draco_attributes(doc, primitive, where) if _extension(primitive, DRACO) is not None else ({}, None)

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
    return {
        "positions": positions,
        "normals": normals.astype(np.float32) if normals is not None else vertex_normals(positions, faces),
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
        if primitive.targets:
            logger.warning("%s: morph targets are ignored", where)
        out.append((primitive, where, rigid_joint))
    return out


def _read_meshes(doc: _Document, skin_index: int, joint_count: int, anchor: np.ndarray, between: np.ndarray,
                 local: np.ndarray, inverse_bind: np.ndarray) -> tuple[dict[str, np.ndarray], list[Material]]:
    """Merge every primitive of the skinned meshes (and of rigid meshes under a joint) into one mesh."""
    nodes = doc.gltf.nodes
    wanted: list[tuple[int, int | None, np.ndarray | None]] = []  # (mesh, rigid joint, bind matrix)
    seen_skinned: set[int] = set()
    for index, node in enumerate(nodes):
        if node.mesh is None:
            continue
        if node.skin == skin_index:
            if node.mesh not in seen_skinned:
                seen_skinned.add(node.mesh)
                wanted.append((node.mesh, None, None))
        elif node.skin is not None:
            logger.warning("%s: nodes[%d] uses skins[%d], not the chosen skin %d; left out", doc.where, index, node.skin, skin_index)
        elif anchor[index] >= 0:
            joint = int(anchor[index])
            # A rigid mesh under joint j sits at world(j) @ between @ local(node) @ p; in bind space that is
            # inverse(inverseBind(j)) @ between @ local(node) @ p, which skinning by j alone maps back.
            bind = np.linalg.inv(inverse_bind[joint].astype(np.float64)) @ between[index] @ local[index]
            wanted.append((node.mesh, joint, bind))
        else:
            logger.warning("%s: nodes[%d] holds a mesh with no skin and no joint above it; left out", doc.where, index)
    parts: dict[str, list[np.ndarray]] = {key: [] for key in ("positions", "normals", "uvs", "faces", "joints", "weights", "materials")}
    materials: list[Material] = []
    uv_sets: list[int] = []  # the TEXCOORD_n set each material's base colour texture reads
    material_slots: dict[int | None, int] = {}
    images: dict[int, np.ndarray] = {}
    base = 0
    for mesh_index, rigid_joint, bind in wanted:
        for primitive, where, joint in _mesh_primitives(doc, mesh_index, rigid_joint):
            if primitive.material not in material_slots:
                material, uv_set = _read_material(doc, primitive.material, images)
                material_slots[primitive.material] = len(materials)
                materials.append(material)
                uv_sets.append(uv_set)
            slot = material_slots[primitive.material]
            part = _read_primitive(doc, primitive, where, joint_count, uv_sets[slot], joint)
            if bind is not None:
                part["positions"] = (part["positions"].astype(np.float64) @ bind[:3, :3].T + bind[:3, 3]).astype(np.float32)
                normal_matrix = np.linalg.inv(bind[:3, :3]).T
                part["normals"] = (part["normals"].astype(np.float64) @ normal_matrix.T).astype(np.float32)
            for key in ("positions", "normals", "uvs", "joints", "weights"):
                parts[key].append(part[key])
            parts["faces"].append(part["faces"] + base)
            parts["materials"].append(np.full(len(part["positions"]), slot, np.uint16))
            base += len(part["positions"])
    if not parts["positions"]:
        raise ValueError(f"{doc.where}: no triangle mesh uses skins[{skin_index}]")
    merged = {key: np.concatenate(values) for key, values in parts.items()}
    # Renormalise only normals that are off (quantised files), so valid files round-trip bit for bit.
    lengths = np.linalg.norm(merged["normals"].astype(np.float64), axis=1, keepdims=True)
    off = (np.abs(lengths - 1.0) > NORMAL_LENGTH_TOLERANCE) & (lengths > 0)
    merged["normals"] = np.where(off, merged["normals"] / np.where(lengths > 0, lengths, 1.0), merged["normals"])
    return merged, materials


# ----------------------------------------------------------------------------------------------
# Animation


def _animation_index(doc: _Document, animation: int | str) -> int | None:
    """The index of the chosen animation (by index or name); None when the file has none."""
    animations = doc.gltf.animations or []
    names = [a.name or f"animation{k}" for k, a in enumerate(animations)]
    if not animations:
        if isinstance(animation, str) or animation != 0:
            raise ValueError(f"{doc.where}: animation {animation!r} was asked for but the file has no animation")
        return None
    if isinstance(animation, str):
        if animation not in names:
            raise ValueError(f"{doc.where}: no animation named {animation!r}; the file has {', '.join(repr(n) for n in names)}")
        return names.index(animation)
    if not isinstance(animation, int) or not 0 <= animation < len(animations):
        raise ValueError(f"{doc.where}: animation {animation} does not exist; the file has {len(animations)}: {', '.join(repr(n) for n in names)}")
    if len(animations) > 1:
        logger.info("%s: %d animations (%s); using %r (choose another by name or index)", doc.where, len(animations),
                    ", ".join(repr(n) for n in names), names[animation])
    return animation


def _read_animation(doc: _Document, animation_index: int | None, node_to_joint: dict[int, int], joint_ancestors: set[int]):
    if animation_index is None:
        return [], 0.0
    animation = doc.item("animations", animation_index)
    samplers = animation.samplers or []
    channels: list[AnimationChannel] = []
    duration = 0.0
    for number, channel in enumerate(animation.channels or []):
        where = f"{doc.where}: animations[{animation_index}].channels[{number}]"
        target = channel.target
        path, node = (target.path, target.node) if target is not None else (None, None)
        sampler_index = channel.sampler
        if not isinstance(sampler_index, int) or not 0 <= sampler_index < len(samplers):
            raise ValueError(f"{where}: sampler {sampler_index} does not exist")
        sampler = samplers[sampler_index]
        interpolation = sampler.interpolation or "LINEAR"
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"{where}: unknown interpolation {interpolation!r}")
        times = doc.accessor(sampler.input)
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
        values = doc.accessor(sampler.output).astype(np.float32)
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
    doc = _open_document(path)
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

    parents, order = _node_parents(doc)
    local = _local_matrices(doc)
    anchor, between = _joint_anchors(parents, order, local, node_to_joint)
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

    mesh, materials = _read_meshes(doc, skin, joint_count, anchor, between, local, inverse_bind)
    animation_index = _animation_index(doc, animation)
    channels, duration = _read_animation(doc, animation_index, node_to_joint, joint_ancestors)
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
