"""The impostor maps as a bundle stores them and a reader decodes them: the bake's 16-bit UV map to and
from the uv32 and uvblock pixel formats (SPEC.md formats 5 and 6, byte layouts in crowdbake.formats.binary),
and the 8-bit normal map back to unit normals. numpy in, numpy out."""
from __future__ import annotations

import numpy as np

from crowdbake.formats.texel_codecs import (
    UVBLOCK_COORD_MAX, UVBLOCK_MAX_MATERIAL, pack_uv32, pack_uvblock_blocks, unblocks, unpack_uv32, uvblock_coordinates,
    uvblock_live_texels,
)


def decode_uv_map(uv_map: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A UV map as stored -> uv (S, S, 2) float64, material (S, S) int64, coverage (S, S) bool.

    uv_map: (S, S, 4) uint16 (rgba16, and the bake's own 16-bit maps) or (S, S) uint32 words (uv32).
    """
    uv_map = np.asarray(uv_map)
    if uv_map.ndim == 2 and uv_map.dtype == np.uint32:
        u, v, material, covered = unpack_uv32(uv_map)
        return np.stack([u, v], axis=-1), material, covered
    if uv_map.ndim != 3 or uv_map.shape[2] != 4:
        raise ValueError(f"decode_uv_map: expected (H, W, 4) uint16 or (H, W) uint32, got {uv_map.shape} {uv_map.dtype}")
    return uv_map[..., :2].astype(np.float64) / 65535.0, uv_map[..., 2].astype(np.int64), uv_map[..., 3] >= 32768


def uv_map_to_uv32(uv_map: np.ndarray) -> np.ndarray:
    """The bake's (H, W, 4) uint16 UV map as (H, W) uint32 uv32 words (SPEC.md pixel format 5).

    Coordinates are re-rounded from 16 to 14 bits (at most 0.5/16383 + 0.5/65535 off the exact
    value); material indices above 7 cannot be stored and raise ValueError.
    """
    uv, material, covered = decode_uv_map(uv_map)
    return pack_uv32(uv[..., 0], uv[..., 1], np.where(covered, material, 0), covered)


def uv_map_to_uvblock(uv_map: np.ndarray) -> bytes:
    """The bake's (H, W, 4) uint16 UV map as one uvblock layer (SPEC.md pixel format 6; H, W multiples of 4).

    The same bytes as pack_uvblock of decode_uv_map's planes, but only the blocks the character touches are
    gathered and decoded: an impostor atlas is mostly empty, and converting every texel to float64 took
    most of a frame's pack time."""
    uv_map = np.asarray(uv_map)
    height, width = uv_map.shape[:2]
    if uv_map.ndim != 3 or uv_map.shape[2] != 4 or height % 4 or width % 4:
        raise ValueError(f"uv_map_to_uvblock: expected (H, W, 4) uint16 with H and W multiples of 4, "
                         f"got {uv_map.shape} {uv_map.dtype}")
    blocks = uv_map.reshape(height // 4, 4, width // 4, 4, 4)
    live = (blocks[..., 3] >= 32768).any(axis=(1, 3))  # (rows, columns) of blocks
    rows, columns = np.nonzero(live)
    texels = blocks[rows, :, columns].reshape(-1, 16, 4)  # (N, 16, 4): the live blocks, texels row-major
    uv, material, covered = decode_uv_map(texels)
    if covered.any() and material[covered].max() > UVBLOCK_MAX_MATERIAL:
        raise ValueError(f"uvblock material indices must lie in 0..{UVBLOCK_MAX_MATERIAL}")
    return pack_uvblock_blocks(live.ravel(), uvblock_coordinates(uv), material, covered)


def uvblock_to_uv32(data: bytes, width: int, height: int) -> np.ndarray:
    """One uvblock layer as (H, W) uv32 words holding the same decoded texels (12-bit coordinates fit 14
    bits to within 1/32767), for code that reads uv32: the fidelity scoring, the export, the web preview."""
    live, (qu, qv, material, covered) = uvblock_live_texels(data, width, height)
    blocks = np.zeros((len(live), 16), np.uint32)  # a block the character does not touch: uv32 words 0
    blocks[live] = pack_uv32(qu / UVBLOCK_COORD_MAX, qv / UVBLOCK_COORD_MAX, material, covered)
    return unblocks(blocks, height, width)


def decode_normal_map(normal_map: np.ndarray) -> np.ndarray:
    """(..., 4) uint8 normal codes (a map, or chosen texels of one) -> (..., 3) float64 unit normals
    ((rgb / 255) · 2 - 1, renormalised)."""
    n = np.asarray(normal_map)[..., :3].astype(np.float64) / 255.0 * 2.0 - 1.0
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 1e-12)


def _tile_bases(layout) -> np.ndarray:
    """(E, A, 3, 3) float32 rows right, up, back of every tile's orthographic view (crowdbake.bake.impostor_views.ortho_view)."""
    from crowdbake.bake.impostor_views import ortho_view

    bases = np.empty((len(layout.elevations_deg), len(layout.azimuths_deg), 3, 3), dtype=np.float32)
    for e, elevation in enumerate(layout.elevations_deg):
        for a, azimuth in enumerate(layout.azimuths_deg):
            view = ortho_view(np.zeros(3), 1.0, azimuth, elevation, layout.tile_size)
            bases[e, a] = view.right, view.up, view.back
    return bases


def _tile_planes(atlas: np.ndarray, layout, channels: int) -> list[np.ndarray]:
    """The first `channels` channels of an (H, W, C) atlas as float32 planes viewed (E, h, A, w): the cell of
    view (a, e) is plane[e, :, a, :]."""
    rings, columns = len(layout.elevations_deg), len(layout.azimuths_deg)
    shape = (rings, layout.cell_height, columns, layout.cell_width)
    return [np.asarray(atlas)[..., c].astype(np.float32).reshape(shape) for c in range(channels)]


def _rotate_planes(planes: list[np.ndarray], matrices: np.ndarray, outputs: int = 3) -> list[np.ndarray]:
    """Vectors held as three (E, h, A, w) planes, each cell's times its (3, 3) matrix from `matrices`
    (E, A, 3, 3), as `outputs` planes: out_j = Σ_i plane_i · M[i, j], broadcast per tile. Working on planes
    (not (..., 3) vectors) keeps every product a plain contiguous array operation."""
    m = matrices.astype(np.float32)[:, None, :, None]  # (E, 1, A, 1, 3, 3)
    return [planes[0] * m[..., 0, j] + planes[1] * m[..., 1, j] + planes[2] * m[..., 2, j] for j in range(outputs)]


def _unit_code(component: np.ndarray) -> np.ndarray:
    """A normal component in [-1, 1] as its 8-bit code round((c + 1) · 127.5)."""
    return np.rint((np.clip(component, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)


def normal_atlas_to_view_xy(normal_atlas: np.ndarray, layout) -> np.ndarray:
    """The bake's (H, W, 4) uint8 model-space normal atlas (RGB = (n + 1) / 2) as the bc5 normal map stores
    it (SPEC.md "Impostor maps"): R, G = (n · right + 1) / 2, (n · up + 1) / 2 in each tile's own view, B = 0,
    A = 255. The third component, n · back, is left out: the reader takes it as sqrt(1 - x² - y²).
    The codes are decoded as decode_normal_map does ((rgb / 255) · 2 - 1, renormalised), in float32."""
    planes = [p * np.float32(2.0 / 255.0) - np.float32(1.0) for p in _tile_planes(normal_atlas, layout, 3)]
    length = np.sqrt(planes[0] ** 2 + planes[1] ** 2 + planes[2] ** 2)
    inverse = np.divide(1.0, length, out=np.zeros_like(length), where=length > 1e-12)
    right, up = _rotate_planes(planes, np.swapaxes(_tile_bases(layout), -1, -2), outputs=2)  # n · right, n · up
    out = np.zeros(normal_atlas.shape[:2] + (4,), dtype=np.uint8)
    out[..., 0] = _unit_code(right * inverse).reshape(out.shape[:2])
    out[..., 1] = _unit_code(up * inverse).reshape(out.shape[:2])
    out[..., 3] = 255
    return out


def view_xy_to_model_normals(texels: np.ndarray, layout) -> np.ndarray:
    """(H, W, 4) uint8 texels of a bc5 normal map, decoded -> (H, W, 3) float32 model-space unit normals:
    x, y = rg / 255 · 2 - 1 in the tile's view, z = sqrt(max(0, 1 - x² - y²)) towards the camera, rotated out
    of the view (the shader's sample_normal, shaders/impostor_warp.glsl)."""
    x, y = (p * np.float32(2.0 / 255.0) - np.float32(1.0) for p in _tile_planes(texels, layout, 2))
    z = np.sqrt(np.maximum(np.float32(0.0), 1.0 - x * x - y * y))
    # A texel past the unit circle (x² + y² > 1) has z = 0 and a length above 1: renormalised here.
    length = np.sqrt(x * x + y * y + z * z)
    inverse = np.divide(1.0, length, out=np.zeros_like(length), where=length > 1e-12)
    model = np.empty(np.shape(texels)[:2] + (3,), dtype=np.float32)
    for j, plane in enumerate(_rotate_planes([x * inverse, y * inverse, z * inverse], _tile_bases(layout))):
        model[..., j] = plane.reshape(model.shape[:2])
    return model


def model_normals_to_codes(normals: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> (H, W, 4) uint8 RGB = (n + 1) / 2, A = 255 (the bake's normal atlas)."""
    out = np.full(normals.shape[:2] + (4,), 255, dtype=np.uint8)
    out[..., :3] = np.rint((np.clip(normals, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    return out
