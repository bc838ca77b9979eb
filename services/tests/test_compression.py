"""Block compression (crowdbake.bake.compression): real encoders, verified by independent decoders.

BC1 blocks are checked against texture2ddecoder's decoder, BC2 blocks against Pillow's DDS (DXT3) reader,
and the decoded error of smooth and hard content is held to stated bounds.
"""
from __future__ import annotations

import io
import struct

import numpy as np
import pytest

from crowdbake.bake import compression
from crowdbake.formats.texel_codecs import region_alpha, region_codes

# Error bounds measured on the synthetic images below with some margin; they would catch an encoder that
# dropped a channel, swapped RGB/BGR, broke block order or let 3-colour blocks through.
SMOOTH_PSNR_DB = 38.0  # gentle gradients: DXT1 is close to lossless (measured 41.7 dB)
SMOOTH_MEAN_ABS = 2.5  # 8-bit levels (measured 1.66; RGB565 alone costs up to 4 levels in red and blue)
SMOOTH_MAX_ABS = 12  # measured 7
NOISE_PSNR_DB = 13.0  # independent random texels are DXT's worst case (measured 13.7 dB; 13.3 with the etcpak path)


def smooth_image(height: int = 64, width: int = 96) -> np.ndarray:
    """(H, W, 4) uint8: slow gradients in RGB and region codes 0..15 in 8x8 patches in alpha."""
    y, x = np.mgrid[0:height, 0:width]
    image = np.zeros((height, width, 4), dtype=np.uint8)
    image[..., 0] = np.rint(40 + 160 * x / width)
    image[..., 1] = np.rint(30 + 190 * y / height)
    image[..., 2] = np.rint(120 + 60 * np.sin(x / 17.0) * np.cos(y / 13.0))
    image[..., 3] = region_alpha(((x // 8) + 3 * (y // 8)) % 16)
    return image


def noise_image(seed: int = 0, size: int = 64) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, size=(size, size, 4), dtype=np.uint8)
    image[..., 3] = region_alpha(rng.integers(0, 16, size=(size, size)))
    return image


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a[..., :3].astype(np.float64) - b[..., :3]) ** 2)
    return float(10 * np.log10(255.0**2 / mse))


def dds_dxt3(data: bytes, width: int, height: int) -> bytes:
    """A minimal DDS file around BC2 blocks, for Pillow's reader."""
    flags = 0x1 | 0x2 | 0x4 | 0x1000 | 0x80000  # caps, height, width, pixel format, linear size
    pixel_format = struct.pack("<II4s5I", 32, 0x4, b"DXT3", 0, 0, 0, 0, 0)
    header = struct.pack("<7I", 124, flags, height, width, len(data), 0, 0) + b"\0" * 44 + pixel_format
    header += struct.pack("<5I", 0x1000, 0, 0, 0, 0)
    assert len(header) == 124
    return b"DDS " + header + data


def test_bc1_matches_texture2ddecoder_exactly():
    texture2ddecoder = pytest.importorskip("texture2ddecoder")
    image = noise_image(1)
    data = compression.encode_bc1(image)
    assert len(data) == 8 * (64 // 4) ** 2
    ours = compression.decode_bc1(data, 64, 64)
    theirs = np.frombuffer(texture2ddecoder.decode_bc1(data, 64, 64), np.uint8).reshape(64, 64, 4)[..., [2, 1, 0, 3]]
    np.testing.assert_array_equal(ours, theirs)
    assert (ours[..., 3] == 255).all(), "normal maps are opaque: no block may decode in punch-through mode"


def test_bc2_matches_pillow_dds_reader_and_keeps_region_codes_exactly():
    from PIL import Image

    image = smooth_image()
    data = compression.encode_bc2(image)
    assert len(data) == 16 * (96 // 4) * (64 // 4)
    ours = compression.decode_bc2(data, 96, 64)
    with Image.open(io.BytesIO(dds_dxt3(data, 96, 64))) as dds:
        theirs = np.array(dds.convert("RGBA"))
    # Decoders round the 1/3 and 2/3 interpolants differently by at most one step.
    assert np.abs(ours.astype(int) - theirs).max() <= 1
    np.testing.assert_array_equal(ours[..., 3], theirs[..., 3])
    np.testing.assert_array_equal(region_codes(ours[..., 3]), region_codes(image[..., 3]))
    np.testing.assert_array_equal(ours[..., 3], image[..., 3])


@pytest.mark.parametrize("encode, decode", [(compression.encode_bc1, compression.decode_bc1), (compression.encode_bc2, compression.decode_bc2)])
def test_decoded_error_of_smooth_content_is_small(encode, decode):
    image = smooth_image()
    decoded = decode(encode(image), 96, 64)
    errors = compression.compression_error(image, decoded)
    assert errors["rgb_psnr_db"] >= SMOOTH_PSNR_DB
    assert errors["rgb_mean_abs"] <= SMOOTH_MEAN_ABS
    assert errors["rgb_max"] <= SMOOTH_MAX_ABS


def test_compression_error_is_the_plain_statistics_of_the_differences():
    """compression_error's histogram sums against the statistics written out in float64, on random layers
    with and without a mask, equal layers and an empty mask."""
    rng = np.random.default_rng(3)
    for trial in range(60):
        height, width = rng.integers(1, 24, 2)
        original = rng.integers(0, 256, (height, width, 4), dtype=np.uint8)
        spread = int(rng.integers(0, 256))
        decoded = np.clip(original + rng.integers(-spread, spread + 1, original.shape), 0, 255).astype(np.uint8)
        mask = None if trial % 3 == 0 else rng.random((height, width)) < 0.5
        errors = compression.compression_error(original, decoded, mask)
        chosen = np.ones((height, width), bool) if mask is None else mask
        if not chosen.any():
            assert errors["rgb_max"] == 0.0 and errors["rgb_psnr_db"] == float("inf")
            continue
        difference = np.abs(decoded[chosen].astype(np.float64) - original[chosen].astype(np.float64))
        assert errors["rgb_max"] == difference[:, :3].max() and errors["alpha_max"] == difference[:, 3].max()
        assert errors["rgb_mean_abs"] == pytest.approx(difference[:, :3].mean(), rel=1e-12)
        assert errors["rgb_rmse"] == pytest.approx(np.sqrt(np.mean(difference[:, :3] ** 2)), rel=1e-12)
    same = compression.compression_error(original, original)
    assert same["rgb_rmse"] == 0.0 and same["rgb_psnr_db"] == float("inf")


def texture2ddecoder_colour(colour_blocks: bytes, width: int, height: int, four_colour_always: bool) -> np.ndarray:
    """texture2ddecoder's RGB of 8-byte colour blocks: as BC1 (3-colour mode where color0 <= color1), or
    in 4-colour mode always, as the colour half of BC3 (behind an opaque BC4 alpha block) - what BC2/BC3
    decoders do with their colour blocks."""
    texture2ddecoder = pytest.importorskip("texture2ddecoder")
    if four_colour_always:
        blocks = np.frombuffer(colour_blocks, np.uint8).reshape(-1, 8)
        opaque_alpha = np.tile(np.array([255, 255, 0, 0, 0, 0, 0, 0], np.uint8), (len(blocks), 1))
        bgra = texture2ddecoder.decode_bc3(np.concatenate([opaque_alpha, blocks], axis=1).tobytes(), width, height)
    else:
        bgra = texture2ddecoder.decode_bc1(colour_blocks, width, height)
    return np.frombuffer(bgra, np.uint8).reshape(height, width, 4)[..., [2, 1, 0]]


def flat_blocks_image(seed: int = 4, size: int = 32) -> np.ndarray:
    """(size, size, 4) uint8 whose every 4x4 block is one colour: random ones plus black, white and pure
    primaries, the blocks for which an encoder is most tempted to write color0 == color1."""
    rng = np.random.default_rng(seed)
    colours = rng.integers(0, 256, size=((size // 4) ** 2, 3), dtype=np.uint8)
    colours[:5] = [(0, 0, 0), (255, 255, 255), (255, 0, 0), (0, 255, 0), (0, 0, 255)]
    blocks = np.empty((len(colours), 16, 4), np.uint8)
    blocks[..., :3] = colours[:, None]
    blocks[..., 3] = 255
    return compression.from_blocks(blocks, size, size)


def test_noise_is_the_worst_case_and_stays_above_its_bound():
    image = noise_image(2)
    decoded = compression.decode_bc1(compression.encode_bc1(image), 64, 64)
    assert psnr(image, decoded) >= NOISE_PSNR_DB


@pytest.mark.parametrize("image", [smooth_image(), noise_image(5), flat_blocks_image()], ids=["smooth", "noise", "flat"])
def test_every_colour_block_is_written_in_four_colour_mode(image):
    """Regression: a block with color0 <= color1 decodes in 3-colour mode in BC1 (index 2 = midpoint,
    index 3 = transparent black) but in 4-colour mode in BC2, so the same bytes meant two pictures. The
    encoder must write color0 > color1 in every block (flat ones included); then texture2ddecoder's BC1
    decoder, its always-4-colour decoder and ours agree texel for texel."""
    height, width = image.shape[:2]
    for colour in (compression.encode_bc1(image), np.frombuffer(compression.encode_bc2(image), np.uint8).reshape(-1, 16)[:, 8:].tobytes()):
        colour0, colour1, _ = compression._split_colour_blocks(np.frombuffer(colour, np.uint8).reshape(-1, 8))
        assert (colour0 > colour1).all()
        as_bc1 = texture2ddecoder_colour(colour, width, height, four_colour_always=False)
        as_bc2 = texture2ddecoder_colour(colour, width, height, four_colour_always=True)
        np.testing.assert_array_equal(as_bc1, as_bc2)
        np.testing.assert_array_equal(compression.decode_bc1(colour, width, height)[..., :3], as_bc1)


def test_flat_blocks_decode_within_one_level():
    """A one-colour block is the encoder's easy case: the best endpoint pair reaches every 8-bit colour to
    within one level (565 endpoints blended by thirds), where a bounding-box encoder was off by up to 7."""
    image = flat_blocks_image()
    decoded = compression.decode_bc2(compression.encode_bc2(image), 32, 32)
    assert np.abs(decoded.astype(int) - image).max() <= 1


def test_encoding_is_deterministic():
    image = noise_image(6)
    assert compression.encode_bc2(image) == compression.encode_bc2(image.copy())
    assert compression.encode_bc1(image) == compression.encode_bc1(image.copy())


def test_bc2_alpha_nibbles_follow_the_block_layout():
    """Texel k of a block (row k // 4, column k % 4) sits in byte k // 2, low nibble for even k."""
    alpha = np.arange(64, dtype=np.uint8).reshape(8, 8) * 4  # every texel its own value
    blocks = compression.encode_bc2_alpha(alpha)
    texels = compression.to_blocks(alpha[..., None])[..., 0]  # (4, 16) in block order
    expected = (texels.astype(int) * 15 + 127) // 255
    unpacked = np.stack([blocks & 15, blocks >> 4], axis=-1).reshape(-1, 16)
    np.testing.assert_array_equal(unpacked, expected)


def test_uniform_blocks_decode_exactly_in_both_modes():
    image = np.zeros((8, 8, 4), dtype=np.uint8)
    image[..., :3] = (255, 0, 255)  # exactly representable in RGB565
    image[..., 3] = region_alpha(np.full((8, 8), 7))
    np.testing.assert_array_equal(compression.decode_bc1(compression.encode_bc1(image), 8, 8)[..., :3], image[..., :3])
    np.testing.assert_array_equal(compression.decode_bc2(compression.encode_bc2(image), 8, 8), image)


def test_sizes_must_be_multiples_of_four_and_formats_known():
    with pytest.raises(ValueError, match="multiples of 4"):
        compression.encode_bc1(np.zeros((6, 8, 4), np.uint8))
    with pytest.raises(ValueError, match="needs"):
        compression.decode_bc2(b"\0" * 15, 4, 4)
    with pytest.raises(ValueError, match="no encoder"):
        compression.encode(np.zeros((4, 4, 4), np.uint8), "rgba16")
    raw = noise_image(3, 8)
    np.testing.assert_array_equal(compression.decode(compression.encode(raw, "rgba8"), "rgba8", 8, 8), raw)
