"""Block compression of textures: DXT1/BC1 for RGB, DXT3/BC2 for RGBA, as in the paper (section 6).

Dobbyn et al. 2006 compress every RGBA image with DXT3 (4:1) and every RGB image with DXT1 (6:1 against
24-bit RGB). The colour blocks come from **quicktex**'s BC1 encoder (a C++ port of rgbcx, among the
highest-quality BC1 encoders) in its **four-colour-only** mode:

- BC1 decodes a block whose endpoints satisfy color0 <= color1 in 3-colour mode (index 2 = midpoint,
  index 3 = transparent black), but BC2/BC3 decode every colour block in 4-colour mode. In four-colour
  mode the encoder writes color0 > color1 in every block (a flat block too: its endpoints then differ by
  one step and all indices point at the exact colour), so a block decodes to the same texels as BC1 and as
  the colour half of BC2, and a normal map never decodes as punch-through black.
- quicktex's default interpolator is the exact 1/3, 2/3 blend of the expanded endpoints, the one the
  decoders below (and texture2ddecoder) implement.
- Nothing runs over the blocks afterwards in Python: the encoder writes the final bytes.

BC2's explicit alpha is 4 bits per texel, `round(a * 15 / 255)`, written here: a region code stored as
`17 * r` (SPEC.md) survives it exactly.

BC5 (RGTC2, core OpenGL 3.0) holds two channels, each a BC4 block of two 8-bit endpoints and 3-bit
indices: 1 byte a texel. The impostor normal map uses it for the normal's two in-view components
(SPEC.md pixel format 7), from quicktex's BC5 encoder.

Decoders are plain numpy (the runtime's GPU does the real decoding); the tests check them against
texture2ddecoder and Pillow's DDS reader. Everything here is pure: bytes and arrays in and out.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

BLOCK = 4  # texels per block side
BC1_BLOCK_BYTES = 8
BC2_BLOCK_BYTES = 16
BC5_BLOCK_BYTES = 16
# quicktex's preset level (0 fastest .. 18 slowest). On the sample bake's own layers (8 diffuse 1024²,
# 10 normal and 10 detail atlases) level 5 encodes 10x faster than the previous etcpak + least-squares
# path with lower error in every kind; level 12 lowers the mean error by another 0.03..0.14 levels for
# 5x the time (services/benchmarks/bench_compression.py, figures in docs/bake.md).
BC1_LEVEL = 5


def _check_rgba(rgba: np.ndarray, name: str) -> np.ndarray:
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
        raise ValueError(f"{name}: expected (H, W, 4) uint8 RGBA, got {rgba.shape} {rgba.dtype}")
    height, width = rgba.shape[:2]
    if height == 0 or width == 0 or height % BLOCK or width % BLOCK:
        raise ValueError(f"{name}: width and height must be positive multiples of 4, got {width}x{height}")
    return np.ascontiguousarray(rgba)


def to_blocks(image: np.ndarray) -> np.ndarray:
    """(H, W, C) -> (H/4 * W/4, 16, C): texels of each 4x4 block in row-major block order, rows inside."""
    height, width, channels = image.shape
    blocks = image.reshape(height // BLOCK, BLOCK, width // BLOCK, BLOCK, channels).transpose(0, 2, 1, 3, 4)
    return blocks.reshape(-1, BLOCK * BLOCK, channels)


def from_blocks(blocks: np.ndarray, width: int, height: int) -> np.ndarray:
    """Inverse of to_blocks: (H/4 * W/4, 16, C) -> (H, W, C)."""
    channels = blocks.shape[-1]
    grid = blocks.reshape(height // BLOCK, width // BLOCK, BLOCK, BLOCK, channels).transpose(0, 2, 1, 3, 4)
    return grid.reshape(height, width, channels)


def _expand565(colour: np.ndarray) -> np.ndarray:
    """(N,) uint16 RGB565 -> (N, 3) int32 RGB888, replicating the high bits into the low ones."""
    colour = colour.astype(np.int32)
    red = (colour >> 11) & 31
    green = (colour >> 5) & 63
    blue = colour & 31
    return np.stack([(red << 3) | (red >> 2), (green << 2) | (green >> 4), (blue << 3) | (blue >> 2)], axis=-1)


def _palette(colour0: np.ndarray, colour1: np.ndarray, four_colour: np.ndarray) -> np.ndarray:
    """(N, 4, 4) int32 RGBA palettes. four_colour (N,) bool: 4-colour mode, else 3 colours + transparent black."""
    c0 = _expand565(colour0)
    c1 = _expand565(colour1)
    count = len(c0)
    palette = np.empty((count, 4, 4), dtype=np.int32)
    palette[:, 0, :3] = c0
    palette[:, 1, :3] = c1
    palette[:, :, 3] = 255
    four = four_colour[:, None]
    palette[:, 2, :3] = np.where(four, (2 * c0 + c1) // 3, (c0 + c1) // 2)
    palette[:, 3, :3] = np.where(four, (c0 + 2 * c1) // 3, 0)
    palette[:, 3, 3] = np.where(four_colour, 255, 0)
    return palette


def _split_colour_blocks(colour_blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 8) uint8 -> colour0 (N,) uint16, colour1 (N,) uint16, indices (N, 16) uint8 (texel order)."""
    words = colour_blocks.view("<u2")
    colour0, colour1 = words[:, 0].copy(), words[:, 1].copy()
    bits = colour_blocks[:, 4:8].view("<u4")[:, 0]
    indices = ((bits[:, None] >> (2 * np.arange(16, dtype=np.uint32))) & 3).astype(np.uint8)
    return colour0, colour1, indices


def _join_colour_blocks(colour0: np.ndarray, colour1: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Inverse of _split_colour_blocks: (N, 8) uint8."""
    out = np.empty((len(colour0), 8), dtype=np.uint8)
    out[:, 0:4].view("<u2")[:, 0] = colour0
    out[:, 0:4].view("<u2")[:, 1] = colour1
    bits = (indices.astype(np.uint32) << (2 * np.arange(16, dtype=np.uint32))).sum(axis=1, dtype=np.uint32)
    out[:, 4:8].view("<u4")[:, 0] = bits
    return out


@lru_cache(maxsize=1)
def _bc1_encoder():
    """The shared quicktex BC1 encoder (four-colour mode, BC1_LEVEL); imported here so that decoding needs only numpy."""
    from quicktex.s3tc.bc1 import BC1Encoder

    return BC1Encoder(BC1_LEVEL, BC1Encoder.ColorMode.FourColor)


def _colour_blocks(rgba: np.ndarray) -> bytes:
    """Four-colour-mode BC1 blocks of an (H, W, 4) uint8 RGBA image (alpha ignored), in row-major block order."""
    from quicktex import RawTexture

    height, width = rgba.shape[:2]
    return _bc1_encoder().encode(RawTexture.frombytes(rgba.tobytes(), width, height)).tobytes()


def encode_bc1(rgba: np.ndarray) -> bytes:
    """DXT1/BC1 blocks of (H, W, 4) uint8 RGBA (alpha ignored, decodes opaque): 8 bytes per 4x4 block."""
    return _colour_blocks(_check_rgba(rgba, "encode_bc1"))


def encode_bc2_alpha(alpha: np.ndarray) -> np.ndarray:
    """(H, W) uint8 alpha -> (H/4 * W/4, 8) uint8 explicit 4-bit alpha blocks, row-major block order,
    texel 0 of each block in the low nibble of its first byte."""
    alpha = np.asarray(alpha)
    height, width = alpha.shape
    nibbles = (alpha.astype(np.uint16) * 15 + 127) // 255  # round(a * 15 / 255)
    pairs = (nibbles[:, 0::2] | (nibbles[:, 1::2] << 4)).astype(np.uint8)  # (H, W/2): two texels a byte
    # Byte k of a block holds texels 2k, 2k+1: row k // 2 of the block, columns 2 (k % 2) .. +1.
    return pairs.reshape(height // BLOCK, BLOCK, width // BLOCK, 2).transpose(0, 2, 1, 3).reshape(-1, 8)


def encode_bc2(rgba: np.ndarray) -> bytes:
    """DXT3/BC2 blocks of (H, W, 4) uint8 RGBA: 8 bytes explicit alpha + 8 bytes 4-colour RGB per block."""
    rgba = _check_rgba(rgba, "encode_bc2")
    colour = np.frombuffer(_colour_blocks(rgba), dtype=np.uint8).reshape(-1, BC1_BLOCK_BYTES)
    blocks = np.empty((len(colour), BC2_BLOCK_BYTES), dtype=np.uint8)
    blocks[:, :8] = encode_bc2_alpha(rgba[..., 3])
    blocks[:, 8:] = colour
    return blocks.tobytes()


def encode_bc5(rgba: np.ndarray) -> bytes:
    """BC5/RGTC2 blocks of the R and G channels of (H, W, 4) uint8 RGBA: two BC4 blocks (R, then G) of 8 bytes."""
    from quicktex import RawTexture
    from quicktex.s3tc.bc5 import BC5Encoder

    rgba = _check_rgba(rgba, "encode_bc5")
    height, width = rgba.shape[:2]
    return BC5Encoder(0, 1).encode(RawTexture.frombytes(rgba.tobytes(), width, height)).tobytes()


def _decode_bc4(blocks: np.ndarray) -> np.ndarray:
    """(N, 8) uint8 BC4 blocks -> (N, 16) uint8 values: endpoints r0 > r1 interpolate 6 values between them
    in sevenths; otherwise 4 in fifths, then 0 and 255 (the RGTC unsigned rules), rounded to nearest."""
    r0, r1 = blocks[:, 0].astype(np.int32), blocks[:, 1].astype(np.int32)
    seven = (r0 > r1)[:, None]
    steps = np.arange(1, 7, dtype=np.int32)
    sevenths = ((7 - steps) * r0[:, None] + steps * r1[:, None] + 3) // 7  # (N, 6)
    fifths = np.concatenate([((5 - steps[:4]) * r0[:, None] + steps[:4] * r1[:, None] + 2) // 5,
                             np.zeros((len(blocks), 1), np.int32), np.full((len(blocks), 1), 255, np.int32)], axis=1)
    palette = np.empty((len(blocks), 8), dtype=np.uint8)
    palette[:, 0], palette[:, 1] = r0, r1
    palette[:, 2:] = np.where(seven, sevenths, fifths)
    # The 48 index bits, little-endian in bytes 2..7: 16 three-bit indices.
    bits = np.zeros(len(blocks), dtype=np.uint64)
    bits.view(np.uint8).reshape(-1, 8)[:, :6] = blocks[:, 2:8]
    if not np.little_endian:
        bits = bits.byteswap()
    indices = (bits[:, None] >> (np.uint64(3) * np.arange(16, dtype=np.uint64))) & np.uint64(7)
    return np.take_along_axis(palette, indices.astype(np.intp), axis=1)


def decode_bc5(data: bytes, width: int, height: int) -> np.ndarray:
    """BC5 bytes -> (H, W, 4) uint8: R and G decoded, B = 0, A = 255 (as OpenGL returns an RG texture)."""
    _block_count(data, width, height, BC5_BLOCK_BYTES, "decode_bc5")
    blocks = np.frombuffer(data, dtype=np.uint8).reshape(-1, BC5_BLOCK_BYTES)
    texels = np.zeros((len(blocks), 16, 4), dtype=np.uint8)
    texels[:, :, 0] = _decode_bc4(np.ascontiguousarray(blocks[:, :8]))
    texels[:, :, 1] = _decode_bc4(np.ascontiguousarray(blocks[:, 8:]))
    texels[:, :, 3] = 255
    return from_blocks(texels, width, height).astype(np.uint8)


def _block_count(data: bytes, width: int, height: int, block_bytes: int, name: str) -> int:
    if width <= 0 or height <= 0 or width % BLOCK or height % BLOCK:
        raise ValueError(f"{name}: width and height must be positive multiples of 4, got {width}x{height}")
    count = (width // BLOCK) * (height // BLOCK)
    if len(data) != count * block_bytes:
        raise ValueError(f"{name}: {width}x{height} needs {count * block_bytes} bytes, got {len(data)}")
    return count


def _decode_colour(colour_blocks: np.ndarray, four_colour_always: bool) -> np.ndarray:
    """(N, 8) uint8 colour blocks -> (N, 16, 4) uint8 texels. The palette is gathered as one uint32 per
    RGBA colour (a quarter of the work of gathering channels)."""
    colour0, colour1, indices = _split_colour_blocks(colour_blocks)
    four = np.ones(len(colour0), dtype=bool) if four_colour_always else colour0 > colour1
    palette = np.ascontiguousarray(_palette(colour0, colour1, four).astype(np.uint8)).view("<u4")[..., 0]  # (N, 4)
    texels = np.take_along_axis(palette, indices.astype(np.intp), axis=1)  # (N, 16) uint32
    return texels.view(np.uint8).reshape(len(colour0), 16, 4)


def decode_bc1(data: bytes, width: int, height: int) -> np.ndarray:
    """BC1 bytes -> (H, W, 4) uint8 RGBA, honouring 3-colour mode (index 3 = transparent black)."""
    _block_count(data, width, height, BC1_BLOCK_BYTES, "decode_bc1")
    blocks = np.frombuffer(data, dtype=np.uint8).reshape(-1, BC1_BLOCK_BYTES)
    return from_blocks(_decode_colour(blocks, False), width, height).astype(np.uint8)


def decode_bc2(data: bytes, width: int, height: int) -> np.ndarray:
    """BC2 bytes -> (H, W, 4) uint8 RGBA (colour always 4-colour mode, alpha = nibble * 17)."""
    _block_count(data, width, height, BC2_BLOCK_BYTES, "decode_bc2")
    blocks = np.frombuffer(data, dtype=np.uint8).reshape(-1, BC2_BLOCK_BYTES)
    texels = _decode_colour(np.ascontiguousarray(blocks[:, 8:]), True)
    packed = blocks[:, :8].astype(np.int32)
    nibbles = np.stack([packed & 15, packed >> 4], axis=-1).reshape(-1, 16)
    texels[:, :, 3] = nibbles * 17
    return from_blocks(texels, width, height).astype(np.uint8)


def encode(rgba: np.ndarray, pixel_format: str) -> bytes:
    """One layer in a CBTX pixel format: rgba8 (raw), bc1, bc2 or bc5 (R and G only). rgba: (H, W, 4) uint8."""
    if pixel_format == "rgba8":
        return np.ascontiguousarray(rgba, dtype=np.uint8).tobytes()
    if pixel_format == "bc1":
        return encode_bc1(rgba)
    if pixel_format == "bc2":
        return encode_bc2(rgba)
    if pixel_format == "bc5":
        return encode_bc5(rgba)
    raise ValueError(f"encode: no encoder for pixel format {pixel_format!r}")


def decode(data: bytes, pixel_format: str, width: int, height: int) -> np.ndarray:
    """One CBTX layer back to texels: (H, W, 4) uint8 for rgba8/bc1/bc2/bc5, uint16 for rgba16."""
    if pixel_format == "rgba8":
        return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 4)
    if pixel_format == "rgba16":
        return np.frombuffer(data, dtype="<u2").reshape(height, width, 4)
    if pixel_format == "bc1":
        return decode_bc1(data, width, height)
    if pixel_format == "bc2":
        return decode_bc2(data, width, height)
    if pixel_format == "bc5":
        return decode_bc5(data, width, height)
    raise ValueError(f"decode: unknown pixel format {pixel_format!r}")


def _texels_of(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """(H, W, 4) uint8 -> (N, 4) uint8: every texel, or those where mask (H, W) is True, in row-major order.
    The masked texels are gathered as one uint32 word each: a quarter of the elements to select."""
    texels = np.ascontiguousarray(image).reshape(-1, 4)
    if mask is None:
        return texels
    return texels.view(np.uint32)[np.asarray(mask).ravel(), 0].view(np.uint8).reshape(-1, 4)


def compression_error(original: np.ndarray, decoded: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Per-channel error of a decoded layer against its source, both (H, W, 4) uint8.

    mask (H, W) bool restricts the statistics to texels that matter (e.g. covered ones). Returns
    rgb_max, rgb_mean_abs, rgb_rmse, rgb_psnr_db (8-bit scale), alpha_max.
    """
    original = np.asarray(original)
    decoded = np.asarray(decoded)
    if original.shape != decoded.shape:
        raise ValueError(f"compression_error: shapes differ, {original.shape} vs {decoded.shape}")
    if mask is not None and not mask.any():
        return {"rgb_max": 0.0, "rgb_mean_abs": 0.0, "rgb_rmse": 0.0, "rgb_psnr_db": float("inf"), "alpha_max": 0.0}
    a, b = (_texels_of(image, mask) for image in (original, decoded))
    # |a - b| of 8-bit values, exact in uint8, then the sums from a histogram of the 256 possible
    # differences (exact integers): a few passes over bytes instead of widening every texel twice.
    absolute = np.maximum(a, b) - np.minimum(a, b)
    histogram = np.bincount(absolute[:, :3].ravel(), minlength=256).astype(np.int64)
    steps = np.arange(256, dtype=np.int64)
    count = 3 * len(absolute)
    rmse = float(np.sqrt(int(histogram @ (steps * steps)) / count))
    return {
        "rgb_max": float(np.flatnonzero(histogram)[-1]),
        "rgb_mean_abs": int(histogram @ steps) / count,
        "rgb_rmse": rmse,
        "rgb_psnr_db": float(20 * np.log10(255.0 / rmse)) if rmse > 0 else float("inf"),
        "alpha_max": float(absolute[:, 3].max()),
    }
