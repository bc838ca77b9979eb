"""Materials as the bake sees them: base colour factor and texture per material, and one texture for the mesh.

A material's base colour is its texture (sRGB) times its baseColorFactor (linear, glTF 2.0 section
3.9.2). When several materials cover the merged mesh they are packed side by side into one atlas
(a flat tile for an untextured one) and the UVs moved into each material's tile. KTX2 (basisu)
images are transcoded by Basis Universal's `basisu` tool, or refused by name where it is not installed
(see crowdbake.formats.basisu); a texture with both a plain source and a KTX2 one reads the plain one,
which is lossless.
"""
from __future__ import annotations

import logging

import numpy as np

from crowdbake.formats.gltf.document import BASISU, _Document, decode_uri, extension
from crowdbake.formats.gltf.model import Material
from crowdbake.formats.images import decode_rgba

logger = logging.getLogger(__name__)

# Pixels of empty border around each material's tile in a merged texture: bilinear and mipmapped
# sampling near a tile's edge then reads that tile's own (edge-replicated) colour.
ATLAS_GUTTER = 4
# Side of the flat tile that stands for an untextured material in a merged texture.
FLAT_TILE = 8


def _image_bytes(doc: _Document, image_index: int) -> bytes:
    image = doc.item("images", image_index)
    where = f"{doc.where}: images[{image_index}]"
    if image.bufferView is not None:
        data, _ = doc.view_bytes(image.bufferView)
        return bytes(data)
    if image.uri is not None:
        return decode_uri(image.uri, doc.base, where)
    raise ValueError(f"{where} has neither bufferView nor uri")


def _texture_image(doc: _Document, texture_index: int, cache: dict[int, np.ndarray]) -> np.ndarray:
    texture = doc.item("textures", texture_index)
    source = texture.source
    if source is None:
        for name in ("EXT_texture_webp", "MSFT_texture_dds", BASISU):
            source = (extension(texture, name) or {}).get("source", source)
        if source is None:
            raise ValueError(f"{doc.where}: textures[{texture_index}] has no source image crowdbake can read")
    if source not in cache:
        cache[source] = decode_rgba(_image_bytes(doc, source), f"{doc.where}: images[{source}]")
    return cache[source]


def read_material(doc: _Document, index: int | None, images: dict[int, np.ndarray]) -> tuple[Material, int]:
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
