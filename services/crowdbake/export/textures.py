"""Bundle textures as plain texel arrays and as KTX2 files (pure: arrays and bytes).

Block-compressed layers (bc1, bc2) are decoded with the same decoder the bake's tests check against
texture2ddecoder, so the exported texels are the ones a runtime shows from the bundle.
"""
from __future__ import annotations

import numpy as np

from crowdbake.bake import compression
from crowdbake.export import ktx2
from crowdbake.formats.binary import TextureArray


def rgba8_layers(texture: TextureArray) -> np.ndarray:
    """(L, H, W, 4) uint8 texels of an rgba8, bc1 or bc2 texture array."""
    if texture.pixel_format not in ("rgba8", "bc1", "bc2"):
        raise ValueError(f"rgba8_layers: {texture.pixel_format} is not a colour format")
    return np.stack([compression.decode(layer, texture.pixel_format, texture.width, texture.height) for layer in texture.layers])


def uv_map_layers(texture: TextureArray) -> tuple[int, np.ndarray]:
    """(vkFormat, texels) of an impostor UV map, bit for bit: uv32 words as R32_UINT (L, H, W),
    rgba16 as R16G16B16A16_UNORM (L, H, W, 4); uvblock (a block code no engine samples) decoded into
    uv32 words, which hold its 12-bit coordinates exactly enough (crowdbake.bake.impostor_maps.uvblock_to_uv32)."""
    if texture.pixel_format == "uvblock":
        from crowdbake.bake.impostor_maps import uvblock_to_uv32

        words = [uvblock_to_uv32(layer, texture.width, texture.height) for layer in texture.layers]
        return ktx2.VK_FORMAT_R32_UINT, np.stack(words).astype(np.uint32)
    if texture.pixel_format == "uv32":
        return ktx2.VK_FORMAT_R32_UINT, np.stack([texture.texels(k) for k in range(len(texture.layers))]).astype(np.uint32)
    if texture.pixel_format == "rgba16":
        return ktx2.VK_FORMAT_R16G16B16A16_UNORM, np.stack([texture.texels(k) for k in range(len(texture.layers))]).astype(np.uint16)
    raise ValueError(f"uv_map_layers: a UV map is uv32 or rgba16, got {texture.pixel_format}")


def region_codes_used(diffuse_layers: list[np.ndarray]) -> list[int]:
    """Region codes (SPEC.md: alpha = 17·r) that appear in any of the (L, H, W, 4) uint8 arrays."""
    codes: set[int] = set()
    for layers in diffuse_layers:
        codes.update(int(c) for c in np.unique(np.rint(layers[..., 3].astype(np.float32) / 17.0)))
    return sorted(codes)
