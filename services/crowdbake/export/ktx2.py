"""KTX 2.0 containers for uncompressed texture arrays: pure bytes in, bytes out.

No maintained KTX2 encoder installs here (the libktx binding `pyktx` builds only against a system
libktx, and Debian 12 packages neither libktx nor `toktx`), so this module writes the container
itself, following the Khronos KTX 2.0 specification:

- one mip level, no supercompression (`supercompressionScheme` 0), one face, `pixelDepth` 0;
- `layerCount` = the number of layers for an array texture, 0 for a single 2D image;
- a Basic Data Format Descriptor whose samples describe `vkFormat` exactly (one sample a channel);
- key/value data: `KTXorientation` = `rd` (rows top first, as the bundle stores them) and
  `KTXwriter`;
- the level's data: layer 0, layer 1, ..., each rows top first, texels as `vkFormat` lays them out
  (little-endian words).

The texels are the bundle's texels, not re-encoded: block-compressed bundle textures are decoded
(crowdbake.bake.compression) to RGBA8 first, so a KTX2 file decodes back to exactly what a runtime
decoding the bundle sees. The test suite reads every file back with `ktx-parse` (the parser three.js
uses) as an independent check.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from crowdbake import __version__

IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
_HEADER = struct.Struct("<12s9I")  # identifier, vkFormat, typeSize, width, height, depth, layers, faces, levels, scheme
_INDEX = struct.Struct("<4I2Q")  # dfd offset/length, kvd offset/length, sgd offset/length
_LEVEL = struct.Struct("<3Q")  # byteOffset, byteLength, uncompressedByteLength
HEADER_BYTES = _HEADER.size + _INDEX.size  # 80

# Vulkan format numbers (VkFormat) of the layouts this exporter writes.
VK_FORMAT_R8G8B8A8_UNORM = 37
VK_FORMAT_R8G8B8A8_SRGB = 43
VK_FORMAT_R16G16B16A16_UNORM = 91
VK_FORMAT_R32_UINT = 98

# Data Format Descriptor constants (Khronos Data Format Specification 1.3).
_KHR_DF_MODEL_RGBSDA = 1
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


def encode_ktx2(vk_format: int, layers: np.ndarray, array: bool = True, writer: str | None = None) -> bytes:
    """A KTX2 file holding `layers`: (L, H, W, C) array of the format's texel type.

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
    level = np.ascontiguousarray(layers, dtype=layout.dtype).tobytes()

    dfd = _data_format_descriptor(layout)
    kvd = _key_values(writer or f"crowdbake {__version__}")
    dfd_offset = HEADER_BYTES + _LEVEL.size
    kvd_offset = dfd_offset + len(dfd)
    # Level data starts on a multiple of lcm(texel block size, 4) (the spec's mip level alignment).
    level_offset = kvd_offset + len(kvd)
    level_offset += -level_offset % math.lcm(layout.texel_bytes, 4)
    header = _HEADER.pack(
        IDENTIFIER, vk_format, layout.bits // 8, width, height, 0, layer_count if array else 0, 1, 1, 0
    ) + _INDEX.pack(dfd_offset, len(dfd), kvd_offset, len(kvd), 0, 0)
    level_index = _LEVEL.pack(level_offset, len(level), len(level))
    padding = b"\0" * (level_offset - kvd_offset - len(kvd))
    return header + level_index + dfd + kvd + padding + level


@dataclass(frozen=True)
class Ktx2Image:
    """A decoded single-level KTX2 file: texels (L, H, W, C) and what the header said."""

    vk_format: int
    texels: np.ndarray
    layer_count: int  # the header's value: 0 for a plain 2D texture
    key_values: dict[str, str]


def decode_ktx2(data: bytes) -> Ktx2Image:
    """Read back a file `encode_ktx2` wrote (one level, no supercompression, a known vkFormat).

    Raises ValueError naming what does not match; meant for round-trip checks and tools, not as a
    general KTX2 reader.
    """
    if len(data) < HEADER_BYTES + _LEVEL.size or data[:12] != IDENTIFIER:
        raise ValueError("not a KTX2 file (identifier or size)")
    _, vk_format, _, width, height, depth, layers, faces, levels, scheme = _HEADER.unpack_from(data)
    dfd_offset, dfd_length, kvd_offset, kvd_length, _, _ = _INDEX.unpack_from(data, _HEADER.size)
    if vk_format not in LAYOUTS or depth or faces != 1 or levels != 1 or scheme:
        raise ValueError(f"unsupported KTX2 layout: vkFormat {vk_format}, depth {depth}, faces {faces}, levels {levels}, scheme {scheme}")
    layout = LAYOUTS[vk_format]
    offset, length, _ = _LEVEL.unpack_from(data, HEADER_BYTES)
    count = max(layers, 1)
    if length != count * height * width * layout.texel_bytes or offset + length > len(data):
        raise ValueError("level size disagrees with the header")
    texels = np.frombuffer(data, layout.dtype, count * height * width * layout.channels, offset)
    key_values = {}
    position, end = kvd_offset, kvd_offset + kvd_length
    while position < end:
        (size,) = struct.unpack_from("<I", data, position)
        key, _, value = data[position + 4 : position + 4 + size].partition(b"\0")
        key_values[key.decode()] = value.rstrip(b"\0").decode()
        position += 4 + size + (-size % 4)
    return Ktx2Image(vk_format, texels.reshape(count, height, width, layout.channels), layers, key_values)
