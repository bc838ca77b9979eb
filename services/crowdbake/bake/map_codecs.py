"""The impostor maps as a bundle stores them and a reader decodes them: the bake's 16-bit UV map to and
from the uv32 and uvblock pixel formats (SPEC.md formats 5 and 6, byte layouts in crowdbake.formats.binary),
and the 8-bit normal map back to unit normals. numpy in, numpy out."""
from __future__ import annotations

import numpy as np

from crowdbake.formats.binary import pack_uv32, pack_uvblock, unpack_uv32, unpack_uvblock


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
    """The bake's (H, W, 4) uint16 UV map as one uvblock layer (SPEC.md pixel format 6; H, W multiples of 4)."""
    uv, material, covered = decode_uv_map(uv_map)
    return pack_uvblock(uv[..., 0], uv[..., 1], np.where(covered, material, 0), covered)


def uvblock_to_uv32(data: bytes, width: int, height: int) -> np.ndarray:
    """One uvblock layer as (H, W) uv32 words holding the same decoded texels (12-bit coordinates fit 14
    bits to within 1/32767), for code that reads uv32: the fidelity scoring, the export, the web preview."""
    u, v, material, covered = unpack_uvblock(data, width, height)
    return pack_uv32(u, v, material, covered)


def decode_normal_map(normal_map: np.ndarray) -> np.ndarray:
    """(S, S, 4) uint8 normal map -> (S, S, 3) float64 unit normals ((rgb / 255) · 2 - 1, renormalised)."""
    n = np.asarray(normal_map)[..., :3].astype(np.float64) / 255.0 * 2.0 - 1.0
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 1e-12)


def _tile_bases(layout) -> np.ndarray:
    """(E, A, 3, 3) float32 rows right, up, back of every tile's orthographic view (crowdbake.bake.impostor_maps.ortho_view)."""
    from crowdbake.bake.impostor_maps import ortho_view

    bases = np.empty((len(layout.elevations_deg), len(layout.azimuths_deg), 3, 3), dtype=np.float32)
    for e, elevation in enumerate(layout.elevations_deg):
        for a, azimuth in enumerate(layout.azimuths_deg):
            view = ortho_view(np.zeros(3), 1.0, azimuth, elevation, layout.tile_size)
            bases[e, a] = view.right, view.up, view.back
    return bases


def _by_tile(atlas: np.ndarray, layout) -> np.ndarray:
    """(H, W, C) atlas as (E, A, S, S, C) tiles (a view, no copy)."""
    size, rings, columns = layout.tile_size, len(layout.elevations_deg), len(layout.azimuths_deg)
    return atlas.reshape(rings, size, columns, size, -1).transpose(0, 2, 1, 3, 4)


def _rotate_tiles(vectors: np.ndarray, matrices: np.ndarray, layout) -> np.ndarray:
    """(H, W, 3) float32 atlas of vectors, each tile's times its (3, 3) matrix from `matrices` (E, A, 3, 3):
    one batched matmul over (E, A, S·S, 3)."""
    size, rings, columns = layout.tile_size, len(layout.elevations_deg), len(layout.azimuths_deg)
    tiles = np.ascontiguousarray(_by_tile(vectors, layout)).reshape(rings, columns, size * size, 3)
    rotated = np.matmul(tiles, matrices).reshape(rings, columns, size, size, 3)
    return np.ascontiguousarray(rotated.transpose(0, 2, 1, 3, 4)).reshape(vectors.shape)


def normal_atlas_to_view_xy(normal_atlas: np.ndarray, layout) -> np.ndarray:
    """The bake's (H, W, 4) uint8 model-space normal atlas (RGB = (n + 1) / 2) as the bc5 normal map stores
    it (SPEC.md "Impostor maps"): R, G = (n · right + 1) / 2, (n · up + 1) / 2 in each tile's own view, B = 0,
    A = 255. The third component, n · back, is left out: the reader takes it as sqrt(1 - x² - y²)."""
    normals = decode_normal_map(normal_atlas).astype(np.float32)
    in_view = _rotate_tiles(normals, np.swapaxes(_tile_bases(layout), -1, -2), layout)  # n · (right, up, back)
    out = np.zeros(normal_atlas.shape[:2] + (4,), dtype=np.uint8)
    out[..., :2] = np.rint((np.clip(in_view[..., :2], -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    out[..., 3] = 255
    return out


def view_xy_to_model_normals(texels: np.ndarray, layout) -> np.ndarray:
    """(H, W, 4) uint8 texels of a bc5 normal map, decoded -> (H, W, 3) float32 model-space unit normals:
    x, y = rg / 255 · 2 - 1 in the tile's view, z = sqrt(max(0, 1 - x² - y²)) towards the camera, rotated out
    of the view (the shader's sample_normal, shaders/impostor_warp.glsl)."""
    in_view = np.empty(np.shape(texels)[:2] + (3,), dtype=np.float32)
    in_view[..., :2] = np.asarray(texels)[..., :2].astype(np.float32) * np.float32(2.0 / 255.0) - np.float32(1.0)
    in_view[..., 2] = np.sqrt(np.maximum(0.0, 1.0 - in_view[..., 0] ** 2 - in_view[..., 1] ** 2))
    model = _rotate_tiles(in_view, _tile_bases(layout), layout)
    length = np.linalg.norm(model, axis=-1, keepdims=True)
    return np.divide(model, length, out=np.zeros_like(model), where=length > 1e-12)


def model_normals_to_codes(normals: np.ndarray) -> np.ndarray:
    """(H, W, 3) unit normals -> (H, W, 4) uint8 RGB = (n + 1) / 2, A = 255 (the bake's normal atlas)."""
    out = np.full(normals.shape[:2] + (4,), 255, dtype=np.uint8)
    out[..., :3] = np.rint((np.clip(normals, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    return out
