"""The glTF container: GLB and JSON parsing, typed documents, buffers and URIs, and what is refused.

`_Document` is what every other part of the reader works on: the typed glTF (pygltflib's dataclasses,
built here directly because pygltflib's own from_dict is too slow for big node counts), its buffers as
bytes, and checked reads of bufferViews (meshopt-compressed ones decoded through
crowdbake.formats.gltf.compression) and accessors (crowdbake.formats.gltf.accessors). Every offset and
length is checked before it is used; a bad file raises ValueError naming the file and the problem.
"""
from __future__ import annotations

import base64
import dataclasses
import json
import struct
import typing
import urllib.parse
from pathlib import Path

import numpy as np
import pygltflib

from crowdbake.formats.gltf.accessors import TYPE_WIDTHS, read_accessor
from crowdbake.formats.gltf.compression import (
    DRACO, MAX_DECODED_DOCUMENT_BYTES, MESHOPT, claimed_meshopt_bytes, decode_meshopt_view,
)
from crowdbake.formats.basisu import KTX2_REFUSAL, basisu_tool

GLB_MAGIC = b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

BASISU = "KHR_texture_basisu"
# Required extensions this reader honours. KHR_mesh_quantization only widens the accessor types
# allowed for positions, normals and UVs, which the accessor reader handles anyway.
READABLE_REQUIRED_EXTENSIONS = frozenset({DRACO, MESHOPT, "KHR_mesh_quantization"})


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


def decode_uri(uri: str, base: Path, where: str) -> bytes:
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


def extension(item, name: str):
    """The JSON object of extension `name` on a typed glTF item, or None."""
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
        check_decode_budget(self.gltf, where)
        check_read_budget(self.gltf, where)

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

    def view_length(self, view_index: int) -> int:
        """The byte length bufferViews[view_index] has once decoded, without decoding it: what an
        accessor's extent is checked against before a compressed view is asked for its bytes."""
        view = self.item("bufferViews", view_index)
        compressed = extension(view, MESHOPT)
        if compressed is not None:
            return claimed_meshopt_bytes(compressed, f"{self.where}: bufferViews[{view_index}] ({MESHOPT})")
        return int(view.byteLength or 0)

    def view_stride(self, view_index: int) -> int | None:
        """The byteStride of bufferViews[view_index] (a meshopt view's decoded stride), or None."""
        view = self.item("bufferViews", view_index)
        compressed = extension(view, MESHOPT)
        return compressed.get("byteStride") if compressed is not None else view.byteStride

    def view_bytes(self, view_index: int) -> tuple[memoryview, int | None]:
        """The bytes of bufferViews[view_index] (decompressed for EXT_meshopt_compression) and its stride."""
        view = self.item("bufferViews", view_index)
        compressed = extension(view, MESHOPT)
        if compressed is not None:
            return memoryview(self._meshopt_view(view_index, compressed)), compressed.get("byteStride")
        data = self._buffer_slice(view.buffer, view.byteOffset, view.byteLength, f"bufferViews[{view_index}]")
        return data, view.byteStride

    def _meshopt_view(self, view_index: int, ext: dict) -> bytes:
        """The decoded bytes of an EXT_meshopt_compression bufferView (see compression.decode_meshopt_view),
        decoded once per document."""
        if view_index in self._decoded_views:
            return self._decoded_views[view_index]
        what = f"bufferViews[{view_index}] ({MESHOPT})"
        source = bytes(self._buffer_slice(ext.get("buffer"), ext.get("byteOffset", 0), ext.get("byteLength"), what))
        result = decode_meshopt_view(source, ext, f"{self.where}: {what}")
        self._decoded_views[view_index] = result
        return result

    def accessor(self, index: int) -> np.ndarray:
        """Accessor `index` as (count, width) array: float32 for floats and normalised ints, else int64
        (see crowdbake.formats.gltf.accessors.read_accessor)."""
        return read_accessor(self, index)


def check_decode_budget(gltf: pygltflib.GLTF2, where: str) -> None:
    """Refuse, before anything decodes, a document whose compressed geometry claims more than
    MAX_DECODED_DOCUMENT_BYTES decoded in all: every EXT_meshopt_compression view an accessor (or a
    sparse block, or a Draco primitive) reads, counted once however many accessors share it, plus each
    Draco primitive's attributes and indices at 4 bytes a component, as their accessors size them."""
    accessors, views = gltf.accessors or [], gltf.bufferViews or []
    used: set = set()
    for accessor in accessors:
        used.add(accessor.bufferView)
        if accessor.sparse is not None:
            used.update({getattr(accessor.sparse.indices, "bufferView", None), getattr(accessor.sparse.values, "bufferView", None)})
    claims: list[tuple[str, int]] = []
    for mesh_index, mesh in enumerate(gltf.meshes or []):
        for primitive_index, primitive in enumerate(mesh.primitives or []):
            draco = extension(primitive, DRACO)
            if not isinstance(draco, dict):
                continue
            used.add(draco.get("bufferView"))
            attributes = primitive.attributes or {}
            read = [attributes.get(name) for name in (draco.get("attributes") or {})] + [primitive.indices]
            claims.append((f"meshes[{mesh_index}].primitives[{primitive_index}] ({DRACO})", sum(_draco_claim(accessors, index) for index in read)))
    for index in sorted(view for view in used if isinstance(view, int) and 0 <= view < len(views)):
        compressed = extension(views[index], MESHOPT)
        if isinstance(compressed, dict):
            label = f"bufferViews[{index}] ({MESHOPT})"
            claims.append((label, claimed_meshopt_bytes(compressed, f"{where}: {label}")))
    total = sum(size for _, size in claims)
    if total > MAX_DECODED_DOCUMENT_BYTES:
        largest = ", ".join(f"{label} {size}" for label, size in sorted(claims, key=lambda claim: -claim[1])[:3])
        raise ValueError(
            f"{where}: the compressed geometry claims {total} decoded bytes in {len(claims)} parts, more than the "
            f"{MAX_DECODED_DOCUMENT_BYTES} one document may decode (largest: {largest})"
        )


# What reading a document may expand to in memory, every accessor counted each time something reads it:
# several morph targets, primitives or animation channels may all name one accessor (or one sampler), and
# an accessor with no bufferView is zeros of any count, so a 0.5 MB file could claim gigabytes (200 targets
# naming one million-vertex accessor: 3.6 GB). A million-vertex character with skin, UVs, normals and a
# dozen full-body targets reads about 200 MB; 256 MiB keeps an upload's check within the +300 MB target.
MAX_READ_DOCUMENT_BYTES = 1 << 28


def check_read_budget(gltf: pygltflib.GLTF2, where: str) -> None:
    """Refuse, before any accessor is read, a document whose reads would expand to more than
    MAX_READ_DOCUMENT_BYTES: every primitive attribute, index and morph-target accessor, every animation
    channel's sampler input and output, and every skin's inverse bind matrices, each counted each time it
    is named (as the readers read it), at the bytes they expand to (4 a float component, 8 an integer)."""
    accessors = gltf.accessors or []
    claims: dict[str, int] = {}

    def claim(label: str, index) -> None:
        if isinstance(index, int) and not isinstance(index, bool) and 0 <= index < len(accessors):
            claims[label] = claims.get(label, 0) + _read_bytes(accessors[index])

    for mesh_index, mesh in enumerate(gltf.meshes or []):
        label = f"meshes[{mesh_index}]"
        for primitive in mesh.primitives or []:
            for index in _attribute_indices(primitive.attributes):
                claim(label, index)
            claim(label, primitive.indices)
            for target in primitive.targets or []:
                for index in _attribute_indices(target):
                    claim(f"{label} morph targets", index)
    for animation_index, animation in enumerate(gltf.animations or []):
        samplers = animation.samplers or []
        for channel in animation.channels or []:
            sampler_index = getattr(channel, "sampler", None)
            if isinstance(sampler_index, int) and 0 <= sampler_index < len(samplers):
                claim(f"animations[{animation_index}]", samplers[sampler_index].input)
                claim(f"animations[{animation_index}]", samplers[sampler_index].output)
    for skin_index, skin in enumerate(gltf.skins or []):
        claim(f"skins[{skin_index}]", skin.inverseBindMatrices)
    total = sum(claims.values())
    if total > MAX_READ_DOCUMENT_BYTES:
        largest = ", ".join(f"{label} {size}" for label, size in sorted(claims.items(), key=lambda claim: -claim[1])[:3])
        raise ValueError(
            f"{where}: reading its accessors would take {total} bytes (each counted each time a primitive, morph target, "
            f"animation channel or skin names it), more than the {MAX_READ_DOCUMENT_BYTES} one document may take "
            f"(largest: {largest})"
        )


def _attribute_indices(attributes) -> list:
    """The accessor indices of a primitive's or morph target's attributes (a pygltflib object or a dict)."""
    if attributes is None:
        return []
    if isinstance(attributes, dict):
        return list(attributes.values())
    return [value for value in vars(attributes).values() if value is not None]


def _read_bytes(accessor) -> int:
    """Bytes an accessor expands to when read: count x width, 4 bytes a float component, 8 an integer one."""
    count, width = accessor.count, TYPE_WIDTHS.get(accessor.type, 16)
    if not isinstance(count, int) or count <= 0:
        return 0
    return count * width * (4 if accessor.componentType == pygltflib.FLOAT else 8)


def _draco_claim(accessors: list, index) -> int:
    """Decoded bytes a Draco primitive's accessor claims: count x width x 4 (Draco decodes 32-bit)."""
    if not isinstance(index, int) or not 0 <= index < len(accessors):
        return 0  # the primitive's reader names the missing accessor
    accessor = accessors[index]
    count, width = accessor.count, TYPE_WIDTHS.get(accessor.type, 16)
    return count * width * 4 if isinstance(count, int) and count > 0 else 0


def open_document(path: Path) -> _Document:
    """Read a .glb or .gltf file into a _Document: parsed, unreadable required extensions refused, every buffer
    resolved (GLB BIN chunk, data URI or file next to it) and checked against its declared byteLength."""
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
            payload = decode_uri(buffer.uri, path.parent, f"{where}: buffers[{index}]")
        elif index == 0 and binary is not None:
            payload = binary
        elif (extension(buffer, MESHOPT) or {}).get("fallback"):
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
    if BASISU in required and basisu_tool() is None:
        raise ValueError(f"{where}: requires {BASISU}: every texture {KTX2_REFUSAL}")
    unreadable = sorted(set(required) - READABLE_REQUIRED_EXTENSIONS - {BASISU})
    if unreadable:
        raise ValueError(f"{where}: requires the glTF extension(s) {', '.join(unreadable)}, which crowdbake cannot read")
