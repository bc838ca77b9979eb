"""Bundle textures as plain texel arrays and as KTX2 files (pure: arrays and bytes).

A colour or normal map goes into KTX2 in one of two modes (KTX2_MODES):

- "bc" (the default): a bundle's BC1/BC2 layers are copied block for block into a BC1/BC2 KTX2, so the
  file holds exactly the bytes crowdview uploads (no re-encode, no loss, 1/4 or 1/8 of RGBA8);
- "rgba8": every layer decoded to RGBA8 texels (the decoder the bake's tests check against
  texture2ddecoder), for targets without BC support.

Either way a KTX2 decodes to the texels a runtime shows from the bundle. rgba8 bundle layers are
written as RGBA8 in both modes.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from crowdbake.bake import compression
from crowdbake.export import ktx2
from crowdbake.formats.binary import TextureArray


KTX2_MODES = ("bc", "rgba8")  # the first is the default

# The bundle's block formats as KTX2 formats: (pixel format, holds colour) -> vkFormat. Colour (diffuse,
# detail) is authored in sRGB and tagged so, like the RGBA8 export; normals are data (UNORM). BC1 is
# the no-alpha variant: crowdview uploads it as GL_COMPRESSED_RGB_S3TC_DXT1_EXT and the bake's encoder
# writes four-colour blocks only, which decode the same either way.
_BLOCK_FORMATS = {
    ("bc1", False): ktx2.VK_FORMAT_BC1_RGB_UNORM_BLOCK,
    ("bc1", True): ktx2.VK_FORMAT_BC1_RGB_SRGB_BLOCK,
    ("bc2", False): ktx2.VK_FORMAT_BC2_UNORM_BLOCK,
    ("bc2", True): ktx2.VK_FORMAT_BC2_SRGB_BLOCK,
}


def colour_ktx2(texture: TextureArray, colour: bool, mode: str, array: bool = True) -> tuple[int, bytes]:
    """(vkFormat, KTX2 bytes) of an rgba8, bc1 or bc2 texture array.

    colour: sRGB-encoded colour (True) or data such as normals (False). mode: "bc" copies BC blocks,
    "rgba8" decodes them. array False: a plain 2D texture of the first layer.
    """
    if mode not in KTX2_MODES:
        raise ValueError(f"colour_ktx2: mode must be one of {KTX2_MODES}, got {mode!r}")
    if mode == "bc" and texture.pixel_format in ("bc1", "bc2"):
        vk_format = _BLOCK_FORMATS[(texture.pixel_format, colour)]
        layers = texture.layers if array else texture.layers[:1]
        return vk_format, ktx2.encode_ktx2_blocks(vk_format, texture.width, texture.height, list(layers), array)
    vk_format = ktx2.VK_FORMAT_R8G8B8A8_SRGB if colour else ktx2.VK_FORMAT_R8G8B8A8_UNORM
    layers = rgba8_layers(texture)
    return vk_format, ktx2.encode_ktx2(vk_format, layers if array else layers[:1], array)


def rgba8_layers(texture: TextureArray, prepared: "PreparedLayers | None" = None) -> np.ndarray:
    """(L, H, W, 4) uint8 texels of an rgba8, bc1 or bc2 texture array; prepared.rgba8 holds layers already decoded."""
    if texture.pixel_format not in ("rgba8", "bc1", "bc2"):
        raise ValueError(f"rgba8_layers: {texture.pixel_format} is not a colour format")
    done = prepared.rgba8 if prepared is not None and texture.pixel_format != "rgba8" else {}

    def decoded(layer: bytes) -> np.ndarray:
        texels = done.get(layer_digest(layer)) if done else None
        return texels if texels is not None else compression.decode(layer, texture.pixel_format, texture.width, texture.height)

    return np.stack([decoded(layer) for layer in texture.layers])


@dataclass(frozen=True)
class PreparedLayers:
    """Impostor layers already converted for the export, keyed by layer_digest of the bundle layer they came
    from: the bake's pack stage converts each frame as it encodes it, in parallel with other frames, so
    the export built beside publishing only looks them up. A layer missing here is converted as usual;
    a key is the digest of the layer's bytes, so a stale entry can never be used for other bytes.

    model_normal_bc1: bc5 normal layer -> BC1 blocks of its model-space codes (model_space_normal_bc1);
    uv32: uvblock layer -> (H, W) uint32 words (crowdbake.bake.map_codecs.uvblock_to_uv32);
    rgba8: bc1/bc2 diffuse layer -> (H, W, 4) uint8 texels as decoded (the poses stage decodes every diffuse
    layer it encodes)."""

    model_normal_bc1: dict[str, bytes] = field(default_factory=dict)
    uv32: dict[str, np.ndarray] = field(default_factory=dict)
    rgba8: dict[str, np.ndarray] = field(default_factory=dict)


NOTHING_PREPARED = PreparedLayers()


def layer_digest(layer: bytes) -> str:
    """SHA-256 (hex) of one layer's bytes, PreparedLayers' key."""
    return hashlib.sha256(layer).hexdigest()


def _layout(impostor: dict):
    from crowdbake.bake.atlas import AtlasLayout

    return AtlasLayout.from_manifest(impostor)


def model_space_codes(decoded_bc5: np.ndarray, layout) -> np.ndarray:
    """(H, W, 4) uint8 texels of a decoded bc5 impostor normal layer (two components in each tile's view,
    crowdbake.bake.map_codecs.view_xy_to_model_normals) -> (H, W, 4) uint8 model-space codes (RGB = (n + 1) / 2)."""
    from crowdbake.bake.map_codecs import model_normals_to_codes, view_xy_to_model_normals

    return model_normals_to_codes(view_xy_to_model_normals(decoded_bc5, layout))


def model_space_normal_bc1(decoded_bc5: np.ndarray, layout) -> bytes:
    """BC1 blocks of model_space_codes: one layer of model_space_normal_ktx2's "bc" file."""
    return compression.encode_bc1(model_space_codes(decoded_bc5, layout))


def model_space_normals(texture: TextureArray, impostor: dict) -> np.ndarray:
    """(L, H, W, 4) uint8 model-space normal codes (RGB = (n + 1) / 2) of a bc5 impostor normal map;
    impostor: the manifest's impostor section (the tile layout)."""
    layout = _layout(impostor)
    return np.stack([model_space_codes(compression.decode(layer, "bc5", texture.width, texture.height), layout) for layer in texture.layers])


def model_space_normal_ktx2(texture: TextureArray, impostor: dict, mode: str, prepared: PreparedLayers = NOTHING_PREPARED,
                            covered: np.ndarray | None = None) -> tuple[int, bytes]:
    """(vkFormat, KTX2 bytes) of a bc5 impostor normal map turned into model space, the encoding every other
    normal map of the export has: BC1 blocks in "bc" mode (the paper's DXT1, 0.5 byte a texel; a second
    lossy step, but the file an engine can sample as it samples the rest), RGBA8 texels in "rgba8" mode.
    prepared: layers already converted (PreparedLayers.model_normal_bc1), used in "bc" mode.
    covered: (L, H, W) bool, the texels the exported UV map covers (covered_texels): the only ones a reader
    takes a normal from (it draws nothing elsewhere), so the rest are written as 0, a texel in "rgba8" mode and
    a block with no covered texel in "bc" mode, which compresses them to almost nothing."""
    if mode not in KTX2_MODES:
        raise ValueError(f"model_space_normal_ktx2: mode must be one of {KTX2_MODES}, got {mode!r}")
    if covered is not None and np.shape(covered) != (len(texture.layers), texture.height, texture.width):
        raise ValueError(f"model_space_normal_ktx2: covered must be (L, H, W) = {(len(texture.layers), texture.height, texture.width)}, "
                         f"got {np.shape(covered)}")
    if mode == "rgba8":
        layers = model_space_normals(texture, impostor)
        if covered is not None:
            layers = np.where(np.asarray(covered)[..., None], layers, 0).astype(np.uint8)
        return ktx2.VK_FORMAT_R8G8B8A8_UNORM, ktx2.encode_ktx2(ktx2.VK_FORMAT_R8G8B8A8_UNORM, layers)
    layout = _layout(impostor)
    blocks = []
    for k, layer in enumerate(texture.layers):
        done = prepared.model_normal_bc1.get(layer_digest(layer)) if prepared.model_normal_bc1 else None
        block = done if done is not None else model_space_normal_bc1(compression.decode(layer, "bc5", texture.width, texture.height), layout)
        blocks.append(block if covered is None else blocks_covering(block, covered[k], BC1_BLOCK_BYTES))
    vk_format = ktx2.VK_FORMAT_BC1_RGB_UNORM_BLOCK
    return vk_format, ktx2.encode_ktx2_blocks(vk_format, texture.width, texture.height, blocks,
                                              zstd_level=IMPOSTOR_NORMAL_ZSTD_LEVEL)


BC1_BLOCK_BYTES = 8
# The impostor normal map's zstd level, above the export's ktx2.ZSTD_LEVEL (12): on the robot's 4.7 MB of
# BC1 blocks 19 takes 995 KB to 950 KB (its zip to under 10 MB) in 1.0 s, on the thread the export runs
# beside its meshes (bench_export_weight.py prints each file's bytes).
IMPOSTOR_NORMAL_ZSTD_LEVEL = 19


def covered_texels(uv: np.ndarray) -> np.ndarray:
    """(L, H, W) bool: the texels an exported UV map covers (uv_map_layers' uv32 words (L, H, W), bit 31, or
    rgba16 (L, H, W, 4), A over one half), after over_half_covered where the bundle has a surface map."""
    uv = np.asarray(uv)
    return (uv >> 31).astype(bool) if uv.ndim == 3 else uv[..., 3] > 32767


def blocks_covering(blocks: bytes, covered: np.ndarray, block_bytes: int) -> bytes:
    """One layer's 4x4 blocks (row-major, `block_bytes` each) with every block that holds no `covered` texel
    ((H, W) bool) set to 0: an all-zero BC1 block is black in either of BC1's modes."""
    height, width = np.shape(covered)
    live = np.asarray(covered).reshape(height // 4, 4, width // 4, 4).any(axis=(1, 3))
    out = np.frombuffer(blocks, dtype=np.uint8).reshape(height // 4, width // 4, block_bytes).copy()
    out[~live] = 0
    return out.tobytes()


def uv_map_layers(texture: TextureArray, prepared: PreparedLayers = NOTHING_PREPARED) -> tuple[int, np.ndarray]:
    """(vkFormat, texels) of an impostor UV map, bit for bit: uv32 words as R32_UINT (L, H, W),
    rgba16 as R16G16B16A16_UNORM (L, H, W, 4); uvblock (a block code no engine samples) decoded into
    uv32 words, which hold its 12-bit coordinates exactly enough (crowdbake.bake.map_codecs.uvblock_to_uv32;
    prepared.uv32 holds layers already decoded)."""
    if texture.pixel_format == "uvblock":
        from crowdbake.bake.map_codecs import uvblock_to_uv32

        words = []
        for layer in texture.layers:
            done = prepared.uv32.get(layer_digest(layer)) if prepared.uv32 else None
            words.append(done if done is not None else uvblock_to_uv32(layer, texture.width, texture.height))
        return ktx2.VK_FORMAT_R32_UINT, np.stack(words).astype(np.uint32, copy=False)
    if texture.pixel_format == "uv32":
        return ktx2.VK_FORMAT_R32_UINT, np.stack([texture.texels(k) for k in range(len(texture.layers))]).astype(np.uint32)
    if texture.pixel_format == "rgba16":
        return ktx2.VK_FORMAT_R16G16B16A16_UNORM, np.stack([texture.texels(k) for k in range(len(texture.layers))]).astype(np.uint16)
    raise ValueError(f"uv_map_layers: a UV map is uv32 or rgba16, got {texture.pixel_format}")


def over_half_covered(uv: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """An exported UV map (uv_map_layers: uv32 words (L, H, W) or rgba16 (L, H, W, 4)) with the texels the
    character covers half or less of, by the surface map's decoded alpha `coverage` (L, H, W) uint8 (SPEC.md
    "Impostor maps"), made background (0). The bundle's UV map covers every texel the character touches, for
    runtimes that weigh each by that alpha; an engine that draws a texel or not then draws the silhouette of
    the character's area, as crowdview's unmoved blends do, not one a texel fatter."""
    kept = np.asarray(coverage) > 127  # decoded 4-bit alpha: 7 · 17 = 119 is under one half, 8 · 17 = 136 over
    return np.where(kept[..., None] if uv.ndim == 4 else kept, uv, 0).astype(uv.dtype)


def region_codes_used(diffuse_layers: list[np.ndarray]) -> list[int]:
    """Region codes (SPEC.md: alpha = 17·r) that appear in any of the (L, H, W, 4) uint8 arrays."""
    codes: set[int] = set()
    for layers in diffuse_layers:
        codes.update(int(c) for c in np.unique(np.rint(layers[..., 3].astype(np.float32) / 17.0)))
    return sorted(codes)
