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
from crowdbake.formats.binary import region_alpha, region_codes

# Error bounds measured on the synthetic images below with some margin; they would catch an encoder that
# dropped a channel, swapped RGB/BGR, broke block order or let 3-colour blocks through.
SMOOTH_PSNR_DB = 38.0  # gentle gradients: DXT1 is close to lossless (measured 41.0 dB)
SMOOTH_MEAN_ABS = 2.5  # 8-bit levels (measured 1.77; RGB565 alone costs up to 4 levels in red and blue)
SMOOTH_MAX_ABS = 12  # measured 9
NOISE_PSNR_DB = 12.5  # independent random texels are DXT's worst case (measured 13.3 dB; 12.1 before refinement)


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


def test_noise_is_the_worst_case_and_refinement_only_helps():
    image = noise_image(2)
    texels = compression.to_blocks(image)
    raw = compression.force_four_colour(compression._etcpak_colour_blocks(image), texels)
    refined = compression.refine_colour_blocks(raw, texels)
    source = texels[:, :, :3].astype(np.float32)
    before = compression._block_errors(raw, source)
    after = compression._block_errors(refined, source)
    assert (after <= before).all(), "refinement must never make a block worse"
    assert after.sum() < 0.9 * before.sum(), "least squares should cut the error of noisy blocks"
    decoded = compression.decode_bc1(refined.tobytes(), 64, 64)
    assert psnr(image, decoded) >= NOISE_PSNR_DB


def test_three_colour_blocks_are_rewritten_for_bc2():
    """Regression: a BC1 block with colour0 < colour1 means 3-colour mode (index 2 = midpoint), but BC2
    decodes every colour block in 4-colour mode, where index 2 is 2/3·c0 + 1/3·c1. Left as it is, such a
    block decodes to the wrong colour in a DXT3 texture."""
    red, blue = 0xF800, 0x001F  # RGB565
    colour0, colour1 = blue, red  # colour0 < colour1: 3-colour mode in BC1
    indices = np.array([[2] * 8 + [0] * 4 + [1] * 4], dtype=np.uint8)  # half the block on the midpoint
    block = compression._join_colour_blocks(np.array([colour0], np.uint16), np.array([colour1], np.uint16), indices)
    texels = compression._decode_colour(block, four_colour_always=False)[:, :, :3].astype(np.uint8)  # what the encoder meant
    wrong = compression._decode_colour(block, four_colour_always=True)[:, :, :3]
    assert np.abs(wrong.astype(int) - texels).max() > 40, "the unfixed block really decodes wrongly in 4-colour mode"
    fixed = compression.force_four_colour(block, texels)
    c0, c1, _ = compression._split_colour_blocks(fixed)
    assert c0[0] > c1[0]
    right = compression._decode_colour(fixed, four_colour_always=True)[:, :, :3]
    bc1_view = compression._decode_colour(fixed, four_colour_always=False)[:, :, :3]
    np.testing.assert_array_equal(right, bc1_view)  # canonical: BC1 and BC2 decoders agree
    # The midpoint is not in the 4-colour palette; the nearest entry is a third of the way (85 of 255).
    assert np.abs(right.astype(int) - texels).max() <= 43


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
