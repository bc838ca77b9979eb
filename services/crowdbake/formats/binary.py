"""Binary files of a bundle (shared_formats/SPEC.md): CBPC pose caches and CBTX texture arrays.

Both start with the common header (magic, version, header_size, file_size). Decoders check
the header in the order the spec gives, so every strict prefix of a valid file is reported
as `truncated`, and never allocate more than the bytes they were handed.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.formats import pose_codec
from crowdbake.formats.errors import FormatError
from crowdbake.formats.texel_codecs import check_uvblock

POSE_CACHE_MAGIC = b"CBPC"
TEXTURE_MAGIC = b"CBTX"
POSE_CACHE_VERSION = 1  # float32 positions and normals
QUANTIZED_POSE_CACHE_VERSION = 2  # 16-bit positions within per-frame bounds, 2 x 16-bit octahedral normals
TEXTURE_VERSION = 1

_COMMON = struct.Struct("<4sIII")  # magic, version, header_size, file_size
_POSE_FIELDS = struct.Struct("<IIIIf3f3fI")  # vertex_count, index_count, frame_count, flags, fps, bmin, bmax, reserved
_TEXTURE_FIELDS = struct.Struct("<IIII")  # width, height, layer_count, pixel_format
POSE_CACHE_HEADER_SIZE = _COMMON.size + _POSE_FIELDS.size
TEXTURE_HEADER_SIZE = _COMMON.size + _TEXTURE_FIELDS.size
assert POSE_CACHE_HEADER_SIZE == 64 and TEXTURE_HEADER_SIZE == 32

# Normals are stored as float32 but computed from float32 positions; the spec allows 1e-3.
NORMAL_LENGTH_TOLERANCE = 1e-3
# Bounds are float32 too; a position may sit this far (metres) outside them from rounding.
BOUNDS_TOLERANCE = 1e-4

PIXEL_FORMATS = {1: "rgba8", 2: "rgba16", 3: "bc1", 4: "bc2", 5: "uv32", 6: "uvblock", 7: "bc5"}
PIXEL_FORMAT_CODES = {name: code for code, name in PIXEL_FORMATS.items()}


def layer_size(pixel_format: str, width: int, height: int) -> int:
    """Bytes of one layer of `width` × `height` texels in `pixel_format`."""
    if pixel_format == "rgba8":
        return 4 * width * height
    if pixel_format == "rgba16":
        return 8 * width * height
    if pixel_format == "uv32":
        return 4 * width * height
    if pixel_format in ("bc1", "bc2", "bc5", "uvblock"):
        if width % 4 or height % 4:
            raise ValueError(f"{pixel_format} needs sizes that are multiples of 4, got {width}x{height}")
        return {"bc1": 8, "bc2": 16, "bc5": 16, "uvblock": 24}[pixel_format] * (width // 4) * (height // 4)
    raise ValueError(f"unknown pixel format {pixel_format!r}")


def _check_common(data: bytes, magic: bytes, supported_version: int, header_size: int, where: str, total_size: int | None = None) -> None:
    """Check the common header at the start of `data`; total_size: the whole file's size when `data` is
    only its header (a reader that maps one frame or one layer), else len(data)."""
    size = len(data) if total_size is None else total_size
    if len(data) < _COMMON.size:
        raise FormatError("truncated", f"{len(data)} bytes is shorter than the 16-byte common header", where)
    got_magic, version, declared_header, file_size = _COMMON.unpack_from(data)
    if got_magic != magic:
        raise FormatError("bad_magic", f"magic is {got_magic!r}, expected {magic!r}", where)
    if version > supported_version or version == 0:
        raise FormatError("unsupported_version", f"version {version}, this reader supports up to {supported_version}", where)
    if declared_header != header_size:
        raise FormatError("invalid_header", f"header_size is {declared_header}, expected {header_size}", where)
    if size < file_size:
        raise FormatError("truncated", f"{size} bytes, header says {file_size}", where)
    if size > file_size:
        raise FormatError("size_mismatch", f"{size} bytes, header says {file_size}", where)
    if file_size < header_size:
        raise FormatError("invalid_header", f"file_size {file_size} is smaller than the header", where)


@dataclass(frozen=True)
class PoseCache:
    """One mesh part at one LOD over every frame of the cycle.

    indices: (T, 3) uint32; uvs: (V, 2) float32; positions, normals: (F, V, 3) float32, metres (a
    version-2 file's decoded: within pose_codec's bounds of what the bake stored).
    """

    indices: np.ndarray
    uvs: np.ndarray
    positions: np.ndarray
    normals: np.ndarray
    frames_per_second: float
    version: int = POSE_CACHE_VERSION

    @property
    def vertex_count(self) -> int:
        return int(self.uvs.shape[0])

    @property
    def frame_count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def triangle_count(self) -> int:
        return int(self.indices.shape[0])


def _pose_arrays(indices, uvs, positions, normals, frames_per_second) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Little-endian copies of a pose cache's arrays; ValueError naming what breaks the spec's rules."""
    indices = np.ascontiguousarray(indices, dtype="<u4").reshape(-1)
    uvs = np.ascontiguousarray(uvs, dtype="<f4")
    positions = np.ascontiguousarray(positions, dtype="<f4")
    normals = np.ascontiguousarray(normals, dtype="<f4")
    if positions.ndim != 3 or positions.shape[2] != 3 or normals.shape != positions.shape:
        raise ValueError(f"positions and normals must be (F, V, 3) alike, got {positions.shape} and {normals.shape}")
    frame_count, vertex_count, _ = positions.shape
    if uvs.shape != (vertex_count, 2):
        raise ValueError(f"uvs must be ({vertex_count}, 2), got {uvs.shape}")
    if indices.size == 0 or indices.size % 3 or frame_count == 0 or vertex_count == 0:
        raise ValueError("a pose cache needs at least one triangle, one vertex and one frame")
    if int(indices.max()) >= vertex_count:
        raise ValueError(f"index {int(indices.max())} out of range for {vertex_count} vertices")
    for name, array in (("uvs", uvs), ("positions", positions), ("normals", normals)):
        if not np.isfinite(array).all():
            raise ValueError(f"{name} contain NaN or infinity")
    if not frames_per_second > 0:
        raise ValueError("frames_per_second must be positive")
    return indices, uvs, positions, normals


def _pose_payload_size(version: int, index_count: int, vertex_count: int, frame_count: int) -> int:
    """Bytes of a CBPC file of these counts (SPEC.md: version 1's float frames, version 2's quantized ones)."""
    frames = 24 * vertex_count * frame_count if version == POSE_CACHE_VERSION else 24 * frame_count + 10 * vertex_count * frame_count
    return POSE_CACHE_HEADER_SIZE + 4 * index_count + 8 * vertex_count + frames


def _pose_header(version: int, indices: np.ndarray, vertex_count: int, frame_count: int, fps: float,
                 bounds_min: np.ndarray, bounds_max: np.ndarray) -> bytes:
    file_size = _pose_payload_size(version, indices.size, vertex_count, frame_count)
    return _COMMON.pack(POSE_CACHE_MAGIC, version, POSE_CACHE_HEADER_SIZE, file_size) + _POSE_FIELDS.pack(
        vertex_count, indices.size, frame_count, 0, float(fps), *bounds_min, *bounds_max, 0)


def encode_pose_cache(
    indices: np.ndarray, uvs: np.ndarray, positions: np.ndarray, normals: np.ndarray, frames_per_second: float
) -> bytes:
    """Serialise a version-1 pose cache (float32 frames). indices (T, 3) or (3T,) int; uvs (V, 2);
    positions, normals (F, V, 3)."""
    indices, uvs, positions, normals = _pose_arrays(indices, uvs, positions, normals, frames_per_second)
    flat = positions.reshape(-1, 3)
    header = _pose_header(POSE_CACHE_VERSION, indices, positions.shape[1], positions.shape[0], frames_per_second,
                          flat.min(axis=0), flat.max(axis=0))
    return b"".join([header, indices.tobytes(), uvs.tobytes(), positions.tobytes(), normals.tobytes()])


def encode_quantized_pose_cache(
    indices: np.ndarray, uvs: np.ndarray, positions: np.ndarray, normals: np.ndarray, frames_per_second: float
) -> bytes:
    """Serialise a version-2 pose cache: each frame's positions as 16-bit codes within that frame's bounds,
    normals as 2 x 16-bit octahedral codes (pose_codec). Arguments as encode_pose_cache; ValueError where a
    decoded position would pass pose_codec.MAX_POSITION_ERROR_M."""
    indices, uvs, positions, normals = _pose_arrays(indices, uvs, positions, normals, frames_per_second)
    bounds = pose_codec.frame_bounds(positions)
    header = _pose_header(QUANTIZED_POSE_CACHE_VERSION, indices, positions.shape[1], positions.shape[0], frames_per_second,
                          bounds[:, 0].min(axis=0), bounds[:, 1].max(axis=0))
    position_codes = pose_codec.quantize_positions(positions, bounds).astype("<u2")
    pose_codec.check_position_error(positions, pose_codec.dequantize_positions(position_codes, bounds))
    normal_codes = pose_codec.encode_octahedral(normals).astype("<u2")
    return b"".join([header, indices.tobytes(), uvs.tobytes(), bounds.astype("<f4").tobytes(), normal_codes.tobytes(),
                     position_codes.tobytes()])


def _check_pose_fields(fields: tuple, where: str) -> None:
    """The header fields' own rules (SPEC.md "Pose cache"), `invalid_header` on the first broken one."""
    vertex_count, index_count, frame_count, flags, fps = fields[:5]
    if vertex_count == 0 or frame_count == 0 or index_count == 0 or index_count % 3:
        raise FormatError(
            "invalid_header",
            f"vertex_count {vertex_count}, index_count {index_count}, frame_count {frame_count}: "
            "all must be positive and index_count a multiple of 3",
            where,
        )
    if flags != 0 or fields[11] != 0:
        raise FormatError("invalid_header", "flags and reserved must be 0", where)
    if not (np.isfinite(fps) and fps > 0):
        raise FormatError("invalid_header", f"frames_per_second {fps} must be positive", where)


def _check_frame_bounds(frame_bounds: np.ndarray, bounds_min: np.ndarray, bounds_max: np.ndarray, where: str) -> None:
    """A version-2 file's (F, 2, 3) per-frame bounds: finite, min <= max, inside the header's bounds."""
    if not np.isfinite(frame_bounds).all():
        raise FormatError("invalid_data", "frame bounds contain NaN or infinity", where)
    inverted = np.argwhere(frame_bounds[:, 0] > frame_bounds[:, 1])
    if inverted.size:
        raise FormatError("invalid_data", f"frame {int(inverted[0][0])}'s bounds have a minimum above the maximum", where)
    outside = (frame_bounds[:, 0] < bounds_min - BOUNDS_TOLERANCE).any(axis=1) | (frame_bounds[:, 1] > bounds_max + BOUNDS_TOLERANCE).any(axis=1)
    if outside.any():
        raise FormatError("invalid_data", f"frame {int(np.argmax(outside))}'s bounds reach outside the header's bounds", where)


def _decode_float_frames(data: bytes, offset: int, vertex_count: int, frame_count: int, bounds_min: np.ndarray,
                         bounds_max: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Version 1's positions and normals, checked: finite, unit normals, positions inside the bounds."""
    values = 3 * vertex_count * frame_count
    positions = np.frombuffer(data, "<f4", values, offset).reshape(frame_count, vertex_count, 3)
    normals = np.frombuffer(data, "<f4", values, offset + 4 * values).reshape(frame_count, vertex_count, 3)
    for name, array in (("positions", positions), ("normals", normals)):
        if not np.isfinite(array).all():
            raise FormatError("invalid_data", f"{name} contain NaN or infinity", where)
    lengths = np.linalg.norm(normals, axis=-1)
    if np.abs(lengths - 1.0).max() > NORMAL_LENGTH_TOLERANCE:
        raise FormatError("invalid_data", "normals are not unit length", where)
    flat = positions.reshape(-1, 3)
    if (flat.min(axis=0) < bounds_min - BOUNDS_TOLERANCE).any() or (flat.max(axis=0) > bounds_max + BOUNDS_TOLERANCE).any():
        raise FormatError("invalid_data", "positions lie outside the header's bounds", where)
    return positions, normals


def _decode_quantized_frames(data: bytes, offset: int, vertex_count: int, frame_count: int, bounds_min: np.ndarray,
                             bounds_max: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Version 2's frame bounds, checked, then its codes decoded to float32 (every code decodes inside them)."""
    frame_bounds = np.frombuffer(data, "<f4", 6 * frame_count, offset).reshape(frame_count, 2, 3)
    _check_frame_bounds(frame_bounds, bounds_min, bounds_max, where)
    offset += 24 * frame_count
    normal_codes = np.frombuffer(data, "<u2", 2 * vertex_count * frame_count, offset).reshape(frame_count, vertex_count, 2)
    offset += 4 * vertex_count * frame_count
    position_codes = np.frombuffer(data, "<u2", 3 * vertex_count * frame_count, offset).reshape(frame_count, vertex_count, 3)
    return pose_codec.dequantize_positions(position_codes, frame_bounds), pose_codec.decode_octahedral(normal_codes)


def decode_pose_cache(data: bytes, where: str = "pose cache") -> PoseCache:
    """Parse and validate a CBPC file of version 1 or 2; raises FormatError with the spec's error code.
    A version-2 file's frames come back decoded to float32."""
    _check_common(data, POSE_CACHE_MAGIC, QUANTIZED_POSE_CACHE_VERSION, POSE_CACHE_HEADER_SIZE, where)
    version = _COMMON.unpack_from(data)[1]
    fields = _POSE_FIELDS.unpack_from(data, _COMMON.size)
    _check_pose_fields(fields, where)
    vertex_count, index_count, frame_count, _, fps = fields[:5]
    bounds_min, bounds_max = np.array(fields[5:8]), np.array(fields[8:11])
    expected = _pose_payload_size(version, index_count, vertex_count, frame_count)
    if expected != len(data):
        raise FormatError("size_mismatch", f"counts imply {expected} bytes, file has {len(data)}", where)

    offset = POSE_CACHE_HEADER_SIZE
    indices = np.frombuffer(data, "<u4", index_count, offset).reshape(-1, 3)
    offset += 4 * index_count
    uvs = np.frombuffer(data, "<f4", 2 * vertex_count, offset).reshape(vertex_count, 2)
    offset += 8 * vertex_count
    if int(indices.max()) >= vertex_count:
        raise FormatError("invalid_data", f"index {int(indices.max())} >= vertex_count {vertex_count}", where)
    for name, array in (("uvs", uvs), ("bounds", fields[5:11])):
        if not np.isfinite(array).all():
            raise FormatError("invalid_data", f"{name} contain NaN or infinity", where)
    decode_frames = _decode_float_frames if version == POSE_CACHE_VERSION else _decode_quantized_frames
    positions, normals = decode_frames(data, offset, vertex_count, frame_count, bounds_min, bounds_max, where)
    return PoseCache(indices, uvs, positions, normals, float(fps), version)


def read_pose_frame(path: str | os.PathLike, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame of a CBPC file: (indices (T, 3) uint32, uvs (V, 2), positions (V, 3), normals (V, 3) float32).

    Checks the header (magic, version, sizes) like decode_pose_cache, then memory-maps only what the
    frame needs, not the whole cycle. Raises FormatError on a bad header, IndexError for a frame outside.
    """
    path = Path(path)
    where = path.name
    total = path.stat().st_size
    with open(path, "rb") as handle:
        header = handle.read(POSE_CACHE_HEADER_SIZE)
    _check_common(header, POSE_CACHE_MAGIC, QUANTIZED_POSE_CACHE_VERSION, POSE_CACHE_HEADER_SIZE, where, total_size=total)
    if len(header) < POSE_CACHE_HEADER_SIZE:
        raise FormatError("truncated", f"{len(header)} bytes is shorter than the pose cache header", where)
    version = _COMMON.unpack_from(header)[1]
    vertex_count, index_count, frame_count = _POSE_FIELDS.unpack_from(header, _COMMON.size)[:3]
    expected = _pose_payload_size(version, index_count, vertex_count, frame_count)
    if expected != total or vertex_count == 0 or index_count == 0 or index_count % 3:
        raise FormatError("size_mismatch", f"counts imply {expected} bytes, file has {total}", where)
    if not 0 <= frame < frame_count:
        raise IndexError(f"{where}: frame {frame} outside its {frame_count} frames")
    data = np.memmap(path, dtype=np.uint8, mode="r")

    def take(dtype: str, count: int, start: int) -> np.ndarray:
        return np.frombuffer(data[start : start + np.dtype(dtype).itemsize * count], dtype=dtype).copy()

    offset = POSE_CACHE_HEADER_SIZE
    indices = take("<u4", index_count, offset).reshape(-1, 3)
    offset += 4 * index_count
    uvs = take("<f4", 2 * vertex_count, offset).reshape(-1, 2)
    offset += 8 * vertex_count
    if version == POSE_CACHE_VERSION:
        frame_floats = 3 * vertex_count
        positions = take("<f4", frame_floats, offset + 4 * frame_floats * frame).reshape(-1, 3)
        offset += 4 * frame_floats * frame_count
        normals = take("<f4", frame_floats, offset + 4 * frame_floats * frame).reshape(-1, 3)
        return indices, uvs, positions, normals
    bounds = take("<f4", 6, offset + 24 * frame).reshape(1, 2, 3)
    offset += 24 * frame_count
    normal_codes = take("<u2", 2 * vertex_count, offset + 4 * vertex_count * frame).reshape(1, -1, 2)
    offset += 4 * vertex_count * frame_count
    position_codes = take("<u2", 3 * vertex_count, offset + 6 * vertex_count * frame).reshape(1, -1, 3)
    return indices, uvs, pose_codec.dequantize_positions(position_codes, bounds)[0], pose_codec.decode_octahedral(normal_codes)[0]


@dataclass(frozen=True)
class TextureArray:
    """Equally sized layers; `layers[k]` is the raw bytes of layer k (texels or BC blocks)."""

    width: int
    height: int
    pixel_format: str
    layers: tuple[bytes, ...]

    def texels(self, layer: int) -> np.ndarray:
        """Layer as (H, W, 4) uint8 (rgba8) or uint16 (rgba16), or (H, W) uint32 words (uv32, see
        unpack_uv32); block formats need a decoder (uvblock: unpack_uvblock)."""
        if self.pixel_format == "uv32":
            return np.frombuffer(self.layers[layer], "<u4").reshape(self.height, self.width)
        if self.pixel_format == "rgba8":
            return np.frombuffer(self.layers[layer], np.uint8).reshape(self.height, self.width, 4)
        if self.pixel_format == "rgba16":
            return np.frombuffer(self.layers[layer], "<u2").reshape(self.height, self.width, 4)
        raise ValueError(f"{self.pixel_format} layers are blocks; decode them with crowdbake.bake.compression")


def encode_texture_array(width: int, height: int, pixel_format: str, layers: list[bytes] | np.ndarray) -> bytes:
    """Serialise a CBTX file. `layers`: raw bytes per layer, an (L, H, W, 4) uint8/uint16 array
    (rgba8/rgba16) or an (L, H, W) uint32 array (uv32)."""
    if isinstance(layers, np.ndarray) and pixel_format == "uv32":
        if layers.shape[1:] != (height, width):
            raise ValueError(f"an array of uv32 layers must be (L, {height}, {width}), got {layers.shape}")
        layers = [np.ascontiguousarray(layer, dtype="<u4").tobytes() for layer in layers]
    if isinstance(layers, np.ndarray):
        dtype = {"rgba8": np.uint8, "rgba16": np.dtype("<u2")}.get(pixel_format)
        if dtype is None or layers.shape[1:] != (height, width, 4):
            raise ValueError(f"an array of layers must be (L, {height}, {width}, 4) for rgba8/rgba16, got {layers.shape}")
        layers = [np.ascontiguousarray(layer, dtype=dtype).tobytes() for layer in layers]
    size = layer_size(pixel_format, width, height)
    if not layers or any(len(layer) != size for layer in layers):
        raise ValueError(f"each of the {len(layers)} layers must be {size} bytes")
    file_size = TEXTURE_HEADER_SIZE + size * len(layers)
    header = _COMMON.pack(TEXTURE_MAGIC, TEXTURE_VERSION, TEXTURE_HEADER_SIZE, file_size) + _TEXTURE_FIELDS.pack(
        width, height, len(layers), PIXEL_FORMAT_CODES[pixel_format]
    )
    return header + b"".join(layers)


def decode_texture_array(data: bytes, where: str = "texture") -> TextureArray:
    """Parse and validate a CBTX file; raises FormatError with the spec's error code."""
    _check_common(data, TEXTURE_MAGIC, TEXTURE_VERSION, TEXTURE_HEADER_SIZE, where)
    width, height, layer_count, format_code = _TEXTURE_FIELDS.unpack_from(data, _COMMON.size)
    pixel_format = PIXEL_FORMATS.get(format_code)
    if pixel_format is None:
        raise FormatError("invalid_header", f"unknown pixel_format {format_code}", where)
    if width == 0 or height == 0 or layer_count == 0:
        raise FormatError("invalid_header", f"width {width}, height {height}, layer_count {layer_count} must be positive", where)
    try:
        size = layer_size(pixel_format, width, height)
    except ValueError as error:
        raise FormatError("invalid_header", str(error), where) from None
    expected = TEXTURE_HEADER_SIZE + size * layer_count
    if expected != len(data):
        raise FormatError("size_mismatch", f"sizes imply {expected} bytes, file has {len(data)}", where)
    layers = tuple(
        bytes(data[TEXTURE_HEADER_SIZE + k * size : TEXTURE_HEADER_SIZE + (k + 1) * size]) for k in range(layer_count)
    )
    if pixel_format == "uvblock":
        for k, layer in enumerate(layers):
            try:
                check_uvblock(layer, width, height)
            except ValueError as error:
                raise FormatError("invalid_data", f"layer {k}: {error}", where) from None
    return TextureArray(width, height, pixel_format, layers)


def read_texture_layer(path: str | os.PathLike, layer: int) -> tuple[str, int, int, int, bytes]:
    """(pixel_format, width, height, layer_count, bytes of `layer`) of a CBTX file, reading one layer only.

    Checks the header (magic, version, sizes, pixel format). Raises FormatError (a ValueError) for a
    header it cannot read or a truncated layer, IndexError for a layer outside the file.
    """
    path = Path(path)
    where = path.name
    total = path.stat().st_size
    with open(path, "rb") as handle:
        header = handle.read(TEXTURE_HEADER_SIZE)
        _check_common(header, TEXTURE_MAGIC, TEXTURE_VERSION, TEXTURE_HEADER_SIZE, where, total_size=total)
        if len(header) != TEXTURE_HEADER_SIZE:
            raise FormatError("truncated", f"{len(header)} bytes is shorter than the texture header", where)
        width, height, layer_count, code = _TEXTURE_FIELDS.unpack_from(header, _COMMON.size)
        if code not in PIXEL_FORMATS:
            raise FormatError("invalid_header", f"pixel format code {code} is not one of {sorted(PIXEL_FORMATS)}", where)
        if not 0 <= layer < layer_count:
            raise IndexError(f"layer {layer} is outside 0..{layer_count - 1}")
        pixel_format = PIXEL_FORMATS[code]
        size = layer_size(pixel_format, width, height)
        handle.seek(TEXTURE_HEADER_SIZE + layer * size)
        data = handle.read(size)
        if len(data) != size:
            raise FormatError("truncated", f"layer {layer} is truncated", where)
    return pixel_format, width, height, layer_count, data
