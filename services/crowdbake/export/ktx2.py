"""KTX 2.0 containers for texture arrays, uncompressed or BC1/BC2 blocks: pure bytes in, bytes out.

No maintained KTX2 encoder installs here (the libktx binding `pyktx` builds only against a system
libktx, and Debian 12 packages neither libktx nor `toktx`), so this module writes the container
itself, following the Khronos KTX 2.0 specification:

- one mip level, one face, `pixelDepth` 0;
- Zstandard supercompression (`supercompressionScheme` 2) of the level at ZSTD_LEVEL, or none (0) when
  asked (`zstd_level=None`): the level's byteLength is then the compressed size and
  uncompressedByteLength the texels' (libktx, three.js's KTX2Loader with its ZSTDDecoder and Godot read
  it; ktx-parse hands over the compressed level);
- `layerCount` = the number of layers for an array texture, 0 for a single 2D image;
- a Basic Data Format Descriptor whose samples describe `vkFormat` exactly (one sample a channel);
- key/value data: `KTXorientation` = `rd` (rows top first, as the bundle stores them) and
  `KTXwriter`;
- the level's data: layer 0, layer 1, ..., each rows top first, texels as `vkFormat` lays them out
  (little-endian words); for a block format (`encode_ktx2_blocks`) the 4x4 blocks in row-major block
  order, the layout BC1/BC2 (S3TC DXT1/DXT3) data has in a CBTX layer, in DDS and for glCompressedTexImage.

Nothing is re-encoded: a bundle's BC1/BC2 layers are copied block for block (their DFD is the Khronos
Data Format Specification's BC1A/BC2 model with 4x4 texel blocks), other layers as texels. The test
suite reads every file back with `ktx-parse` (the parser three.js uses) as an independent check and
decodes the blocks with texture2ddecoder.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

import zstandard

from crowdbake import __version__

IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
_HEADER = struct.Struct("<12s9I")  # identifier, vkFormat, typeSize, width, height, depth, layers, faces, levels, scheme
_INDEX = struct.Struct("<4I2Q")  # dfd offset/length, kvd offset/length, sgd offset/length
_LEVEL = struct.Struct("<3Q")  # byteOffset, byteLength, uncompressedByteLength
HEADER_BYTES = _HEADER.size + _INDEX.size  # 80
SUPERCOMPRESSION_NONE = 0
SUPERCOMPRESSION_ZSTD = 2
# zstd level of the export's textures. On the sample's 21 MB of KTX2: 1.5 s for 6.7 MB at 12, 4.8 s for
# 6.4 MB at 17, 17 s for 6.1 MB at 19 (services/benchmarks/bench_export_weight.py measures the export).
ZSTD_LEVEL = 12
LARGE_LEVEL_FROM_BYTES = 1 << 23
LARGE_LEVEL = 16
LONGEST_WINDOW_LOG = 27

# Vulkan format numbers (VkFormat) of the layouts this exporter writes.
VK_FORMAT_R8G8B8A8_UNORM = 37
VK_FORMAT_R8G8B8A8_SRGB = 43
VK_FORMAT_R16G16B16A16_UNORM = 91
VK_FORMAT_R32_UINT = 98
VK_FORMAT_BC1_RGB_UNORM_BLOCK = 131
VK_FORMAT_BC1_RGB_SRGB_BLOCK = 132
VK_FORMAT_BC2_UNORM_BLOCK = 135
VK_FORMAT_BC2_SRGB_BLOCK = 136

# Data Format Descriptor constants (Khronos Data Format Specification 1.3).
_KHR_DF_MODEL_RGBSDA = 1
_KHR_DF_MODEL_BC1A = 128
_KHR_DF_MODEL_BC2 = 129
_CHANNEL_BC_COLOUR, _CHANNEL_BC2_ALPHA = 0, 15  # BC1A_COLOR (no alpha), BC2_COLOR / BC2_ALPHA
_KHR_DF_PRIMARIES_BT709 = 1
_KHR_DF_TRANSFER_LINEAR = 1
_KHR_DF_TRANSFER_SRGB = 2
_KHR_DF_VERSION = 2
_CHANNEL_R, _CHANNEL_G, _CHANNEL_B, _CHANNEL_A = 0, 1, 2, 15
_QUALIFIER_LINEAR = 0x10  # this sample is linear even though the transfer function is sRGB (alpha)


@dataclass(frozen=True)
class VkLayout:
    """What a vkFormat means for one texel: channels, bits per channel, normalised or integer, sRGB."""

    name: str
    channels: int
    bits: int
    normalized: bool
    srgb: bool

    @property
    def texel_bytes(self) -> int:
        return self.channels * self.bits // 8

    @property
    def dtype(self) -> np.dtype:
        return np.dtype({8: np.uint8, 16: "<u2", 32: "<u4"}[self.bits])


LAYOUTS: dict[int, VkLayout] = {
    VK_FORMAT_R8G8B8A8_UNORM: VkLayout("R8G8B8A8_UNORM", 4, 8, True, False),
    VK_FORMAT_R8G8B8A8_SRGB: VkLayout("R8G8B8A8_SRGB", 4, 8, True, True),
    VK_FORMAT_R16G16B16A16_UNORM: VkLayout("R16G16B16A16_UNORM", 4, 16, True, False),
    VK_FORMAT_R32_UINT: VkLayout("R32_UINT", 1, 32, False, False),
}


@dataclass(frozen=True)
class BlockLayout:
    """What a block-compressed vkFormat means: 4x4 texels in `block_bytes` bytes, DFD colour model, sRGB."""

    name: str
    block_bytes: int
    model: int
    srgb: bool
    block_size: int = 4  # texels per block side


BLOCK_LAYOUTS: dict[int, BlockLayout] = {
    VK_FORMAT_BC1_RGB_UNORM_BLOCK: BlockLayout("BC1_RGB_UNORM_BLOCK", 8, _KHR_DF_MODEL_BC1A, False),
    VK_FORMAT_BC1_RGB_SRGB_BLOCK: BlockLayout("BC1_RGB_SRGB_BLOCK", 8, _KHR_DF_MODEL_BC1A, True),
    VK_FORMAT_BC2_UNORM_BLOCK: BlockLayout("BC2_UNORM_BLOCK", 16, _KHR_DF_MODEL_BC2, False),
    VK_FORMAT_BC2_SRGB_BLOCK: BlockLayout("BC2_SRGB_BLOCK", 16, _KHR_DF_MODEL_BC2, True),
}


def format_name(vk_format: int) -> str:
    """The VkFormat's name without the VK_FORMAT_ prefix, for either kind of layout."""
    return (LAYOUTS.get(vk_format) or BLOCK_LAYOUTS[vk_format]).name


def _block_data_format_descriptor(layout: BlockLayout) -> bytes:
    """The Basic DFD of a BC1 (no alpha) or BC2 format, as the Khronos Data Format Specification 1.3
    section 5.6 gives it: 4x4x1 blocks, one 64-bit sample for BC1's colour, two for BC2 (explicit alpha
    in bits 0..63, marked linear under sRGB; colour in bits 64..127), each spanning 0..0xFFFFFFFF."""
    samples = [(0, _CHANNEL_BC_COLOUR)] if layout.model == _KHR_DF_MODEL_BC1A else [(0, _CHANNEL_BC2_ALPHA), (64, _CHANNEL_BC_COLOUR)]
    block_size = 24 + 16 * len(samples)
    transfer = _KHR_DF_TRANSFER_SRGB if layout.srgb else _KHR_DF_TRANSFER_LINEAR
    last = layout.block_size - 1
    words = [
        0,
        _KHR_DF_VERSION | (block_size << 16),
        layout.model | (_KHR_DF_PRIMARIES_BT709 << 8) | (transfer << 16),
        last | (last << 8),  # texelBlockDimension0/1 = 4 - 1; depth and fourth dimension 1 - 1
        layout.block_bytes,
        0,
    ]
    for offset, channel in samples:
        qualifier = _QUALIFIER_LINEAR if (layout.srgb and channel == _CHANNEL_BC2_ALPHA) else 0
        words += [offset | (63 << 16) | ((channel | qualifier) << 24), 0, 0, 0xFFFFFFFF]
    body = struct.pack(f"<{len(words)}I", *words)
    return struct.pack("<I", 4 + len(body)) + body


def _data_format_descriptor(layout: VkLayout) -> bytes:
    """The Basic DFD (dfdTotalSize first) for an uncompressed, unsigned, one-plane format."""
    channel_ids = (_CHANNEL_R, _CHANNEL_G, _CHANNEL_B, _CHANNEL_A)[: layout.channels] if layout.channels == 4 else (_CHANNEL_R,)
    block_size = 24 + 16 * len(channel_ids)
    transfer = _KHR_DF_TRANSFER_SRGB if layout.srgb else _KHR_DF_TRANSFER_LINEAR
    words = [
        0,  # vendorId 0 (Khronos), descriptorType 0 (basic)
        _KHR_DF_VERSION | (block_size << 16),
        _KHR_DF_MODEL_RGBSDA | (_KHR_DF_PRIMARIES_BT709 << 8) | (transfer << 16),  # flags 0: straight alpha
        0,  # texelBlockDimension 1x1x1x1, stored minus one
        layout.texel_bytes,  # bytesPlane0
        0,  # bytesPlane4..7
    ]
    # Normalised samples span 0..2^bits-1; an unnormalised integer's sampleUpper is 1 (value 1 means 1).
    upper = (1 << layout.bits) - 1 if layout.normalized else 1
    for index, channel in enumerate(channel_ids):
        qualifier = _QUALIFIER_LINEAR if (layout.srgb and channel == _CHANNEL_A) else 0
        words += [(index * layout.bits) | ((layout.bits - 1) << 16) | ((channel | qualifier) << 24), 0, 0, upper]
    body = struct.pack(f"<{len(words)}I", *words)
    return struct.pack("<I", 4 + len(body)) + body


def _key_values(writer: str) -> bytes:
    """Key/value data, keys sorted as the spec requires, each entry padded to 4 bytes."""
    out = b""
    for key, value in sorted({"KTXorientation": "rd", "KTXwriter": writer}.items()):
        entry = key.encode() + b"\0" + value.encode() + b"\0"
        out += struct.pack("<I", len(entry)) + entry + b"\0" * (-len(entry) % 4)
    return out


def encode_ktx2(vk_format: int, layers: np.ndarray, array: bool = True, writer: str | None = None, zstd_level: int | None = ZSTD_LEVEL) -> bytes:
    """A KTX2 file holding `layers`: (L, H, W, C) array of the format's texel type, zstd-supercompressed at
    `zstd_level` (None: not supercompressed).

    C is the format's channel count (4, or 1 for R32_UINT, where (L, H, W) is also accepted);
    dtype uint8, uint16 or uint32 to match. `array` False writes L == 1 as a plain 2D texture
    (layerCount 0). Raises ValueError on a shape or dtype that does not fit `vk_format`.
    """
    if vk_format not in LAYOUTS:
        raise ValueError(f"vkFormat {vk_format} is not one this writer supports ({sorted(LAYOUTS)})")
    layout = LAYOUTS[vk_format]
    layers = np.asarray(layers)
    if layout.channels == 1 and layers.ndim == 3:
        layers = layers[..., None]
    if layers.ndim != 4 or layers.shape[3] != layout.channels or 0 in layers.shape:
        raise ValueError(f"{layout.name} needs (L, H, W, {layout.channels}) texels, got {layers.shape}")
    if layers.dtype.itemsize * 8 != layout.bits or layers.dtype.kind != "u":
        raise ValueError(f"{layout.name} needs uint{layout.bits} texels, got {layers.dtype}")
    if not array and layers.shape[0] != 1:
        raise ValueError(f"a non-array texture has one layer, got {layers.shape[0]}")
    layer_count, height, width, _ = layers.shape
    # The texels' own buffer, not a copy: _container copies it once, into the file's bytes.
    level = memoryview(np.ascontiguousarray(layers, dtype=layout.dtype)).cast("B")
    return _container(vk_format, layout.bits // 8, width, height, layer_count if array else 0, _data_format_descriptor(layout),
                      level, math.lcm(layout.texel_bytes, 4), writer, zstd_level)


def encode_ktx2_blocks(vk_format: int, width: int, height: int, layers: list[bytes], array: bool = True, writer: str | None = None,
                       zstd_level: int | None = ZSTD_LEVEL) -> bytes:
    """A KTX2 file holding block-compressed `layers` (one bytes object a layer) copied as they are, the level
    zstd-supercompressed at `zstd_level` (None: not supercompressed).

    width, height: texels, multiples of the 4-texel block; each layer holds (height/4)·(width/4) blocks in
    row-major block order. `array` False writes one layer as a plain 2D texture. Raises ValueError on a
    size that does not fit.
    """
    if vk_format not in BLOCK_LAYOUTS:
        raise ValueError(f"vkFormat {vk_format} is not a block format this writer supports ({sorted(BLOCK_LAYOUTS)})")
    layout = BLOCK_LAYOUTS[vk_format]
    if width <= 0 or height <= 0 or width % layout.block_size or height % layout.block_size:
        raise ValueError(f"{layout.name} needs sizes that are positive multiples of {layout.block_size}, got {width}x{height}")
    layer_bytes = (width // layout.block_size) * (height // layout.block_size) * layout.block_bytes
    if not layers or any(len(layer) != layer_bytes for layer in layers):
        raise ValueError(f"{layout.name} {width}x{height} needs layers of {layer_bytes} bytes, got {[len(layer) for layer in layers]}")
    if not array and len(layers) != 1:
        raise ValueError(f"a non-array texture has one layer, got {len(layers)}")
    # typeSize is 1 for block-compressed formats (KTX 2.0 section 3.2).
    return _container(vk_format, 1, width, height, len(layers) if array else 0, _block_data_format_descriptor(layout),
                      b"".join(bytes(layer) for layer in layers), math.lcm(layout.block_bytes, 4), writer, zstd_level)


def zstd_compress(data: bytes | memoryview, level: int) -> bytes:
    """A zstd frame of `data` at `level`. Data larger than the level's own window (8 MiB at 12; in an export,
    the impostor UV map) gets a window over all of it (at most 2^27 bytes, every decoder's default limit),
    long-distance matching and at least LARGE_LEVEL: its layers are frames of one motion, alike a layer
    apart (the robot's UV map, 38 MB: 1.01 MB at 12, 0.92 MB with the window, 0.78 MB at 16 in 1.8 s)."""
    if len(data) <= LARGE_LEVEL_FROM_BYTES:
        return zstandard.ZstdCompressor(level=level).compress(data)
    window_log = min(LONGEST_WINDOW_LOG, max(1, len(data) - 1).bit_length())
    parameters = zstandard.ZstdCompressionParameters.from_level(max(level, LARGE_LEVEL), source_size=len(data), window_log=window_log,
                                                                enable_ldm=True)
    return zstandard.ZstdCompressor(compression_params=parameters).compress(data)


def _container(vk_format: int, type_size: int, width: int, height: int, layer_count: int, dfd: bytes, level: bytes | memoryview,
               alignment: int, writer: str | None, zstd_level: int | None) -> bytes:
    """Header, level index, DFD, key/values and the one level, which starts on a multiple of `alignment`
    (the spec's mip level alignment: lcm(texel block size, 4); 1 for a supercompressed level)."""
    kvd = _key_values(writer or f"crowdbake {__version__}")
    uncompressed_length = len(level)
    scheme = SUPERCOMPRESSION_NONE
    if zstd_level is not None:
        level = zstd_compress(level, zstd_level)
        scheme, alignment = SUPERCOMPRESSION_ZSTD, 1
    dfd_offset = HEADER_BYTES + _LEVEL.size
    kvd_offset = dfd_offset + len(dfd)
    level_offset = kvd_offset + len(kvd)
    level_offset += -level_offset % alignment
    # typeSize is 1 for a supercompressed file (KTX 2.0 section 3.2)
    header = _HEADER.pack(IDENTIFIER, vk_format, 1 if scheme else type_size, width, height, 0, layer_count, 1, 1, scheme) + _INDEX.pack(
        dfd_offset, len(dfd), kvd_offset, len(kvd), 0, 0
    )
    level_index = _LEVEL.pack(level_offset, len(level), uncompressed_length)
    padding = b"\0" * (level_offset - kvd_offset - len(kvd))
    return header + level_index + dfd + kvd + padding + level


@dataclass(frozen=True)
class Ktx2Image:
    """A decoded single-level KTX2 file and what the header said: texels (L, H, W, C) for an uncompressed
    format, or for a block format blocks (L, H/4 · W/4 · block bytes) uint8 and texels None; the level
    as stored (supercompressed or not) and its scheme."""

    vk_format: int
    texels: np.ndarray | None
    layer_count: int  # the header's value: 0 for a plain 2D texture
    key_values: dict[str, str]
    width: int = 0
    height: int = 0
    blocks: np.ndarray | None = None
    supercompression: int = SUPERCOMPRESSION_NONE
    stored_level: bytes = b""


def decode_ktx2(data: bytes) -> Ktx2Image:
    """Read back a file `encode_ktx2` wrote (one level, no supercompression or zstd, a known vkFormat).

    Raises ValueError naming what does not match; meant for round-trip checks and tools, not as a
    general KTX2 reader.
    """
    if len(data) < HEADER_BYTES + _LEVEL.size or data[:12] != IDENTIFIER:
        raise ValueError("not a KTX2 file (identifier or size)")
    _, vk_format, _, width, height, depth, layers, faces, levels, scheme = _HEADER.unpack_from(data)
    dfd_offset, dfd_length, kvd_offset, kvd_length, _, _ = _INDEX.unpack_from(data, _HEADER.size)
    if (vk_format not in LAYOUTS and vk_format not in BLOCK_LAYOUTS) or depth or faces != 1 or levels != 1 or scheme not in (0, 2):
        raise ValueError(f"unsupported KTX2 layout: vkFormat {vk_format}, depth {depth}, faces {faces}, levels {levels}, scheme {scheme}")
    offset, length, uncompressed_length = _LEVEL.unpack_from(data, HEADER_BYTES)
    if offset + length > len(data):
        raise ValueError("level size disagrees with the header")
    container, stored = data, bytes(data[offset : offset + length])
    if scheme == SUPERCOMPRESSION_ZSTD:
        try:
            data = zstandard.ZstdDecompressor().decompress(stored, max_output_size=uncompressed_length)
        except zstandard.ZstdError as error:
            raise ValueError(f"the zstd level does not decompress: {error}") from None
        offset, length = 0, len(data)
        if length != uncompressed_length:
            raise ValueError("level size disagrees with the header")
    count = max(layers, 1)
    if vk_format in BLOCK_LAYOUTS:
        block = BLOCK_LAYOUTS[vk_format]
        layer_bytes = (width // block.block_size) * (height // block.block_size) * block.block_bytes
        if length != count * layer_bytes or offset + length > len(data):
            raise ValueError("level size disagrees with the header")
        texels, blocks = None, np.frombuffer(data, np.uint8, length, offset).reshape(count, layer_bytes)
    else:
        layout = LAYOUTS[vk_format]
        if length != count * height * width * layout.texel_bytes or offset + length > len(data):
            raise ValueError("level size disagrees with the header")
        blocks = None
        texels = np.frombuffer(data, layout.dtype, count * height * width * layout.channels, offset).reshape(count, height, width, layout.channels)
    key_values = {}
    position, end = kvd_offset, kvd_offset + kvd_length
    while position < end:
        (size,) = struct.unpack_from("<I", container, position)
        key, _, value = container[position + 4 : position + 4 + size].partition(b"\0")
        key_values[key.decode()] = value.rstrip(b"\0").decode()
        position += 4 + size + (-size % 4)
    return Ktx2Image(vk_format, texels, layers, key_values, width, height, blocks, scheme, stored)
