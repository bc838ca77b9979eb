"""The picture crowdview's impostor shader draws (crowdbake.render.runtime_shader), drawn in float64 numpy
from the bundle's own maps: the reference that shader is tested against, not what a bake ships.

A bundle's UV, normal and surface maps are decoded as crowdview samples them (AtlasTiles), each
(view, frame) sample is reprojected by the surface map (sample_tile, crowdbake.reference.impostor_warp)
and the samples crowdbake.bake.view_blend chooses are blended (numpy_picture,
crowdbake.reference.impostor_blend).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from crowdbake.bake import compression, impostor_views, map_codecs, shading, surface_maps
from crowdbake.bake.atlas import AtlasLayout, view_tile
from crowdbake.reference import impostor_blend, impostor_warp
from crowdbake.reference.impostor_blend import DecodedTile
from crowdbake.bake.view_blend import FrameWeights, ViewWeights
from crowdbake.formats.binary import TextureArray
from crowdbake.formats.texel_codecs import unpack_uv32, unpack_uvblock
from crowdbake.render.runtime_shader import RuntimeAtlas, RuntimePicture
from crowdbake.stages.runtime_fidelity import parsed_map


def decode_atlas_layer(uv_map: TextureArray, normal_map: TextureArray, layer: int, layout: AtlasLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(uv (H, W, 2), material (H, W), covered (H, W), normal (H, W, 3) model space) of one layer of the
    bundle's UV and normal maps (parsed CBTX), decoded as crowdview samples them."""
    if uv_map.pixel_format == "uvblock":
        u, v, material, covered = unpack_uvblock(uv_map.layers[layer], uv_map.width, uv_map.height)
        uv = np.stack([u, v], axis=-1)
    elif uv_map.pixel_format == "uv32":
        u, v, material, covered = unpack_uv32(uv_map.texels(layer))
        uv = np.stack([u, v], axis=-1)
    else:
        uv, material, covered = map_codecs.decode_uv_map(uv_map.texels(layer))
    # Outside the character the shader's decode gives coordinate 0, which its gradients then see.
    uv = np.where(covered[..., None], uv, 0.0)
    if normal_map.pixel_format == "bc5":
        normals = compression.decode(normal_map.layers[layer], "bc5", normal_map.width, normal_map.height)
        return uv, material, covered, map_codecs.view_xy_to_model_normals(normals, layout)
    if normal_map.pixel_format in ("bc1", "bc2"):
        normals = compression.decode(normal_map.layers[layer], normal_map.pixel_format, normal_map.width, normal_map.height)
    else:
        normals = normal_map.texels(layer)
    return uv, material, covered, map_codecs.decode_normal_map(normals)


def decode_surface_layer(surface_map: TextureArray, layer: int) -> np.ndarray:
    """(H, W, 4) uint8 texels of one layer of the bundle's surface map, decoded as crowdview samples it."""
    if surface_map.pixel_format in ("bc1", "bc2"):
        return compression.decode(surface_map.layers[layer], surface_map.pixel_format, surface_map.width, surface_map.height)
    return surface_map.texels(layer)


class AtlasTiles:
    """Tiles of decoded atlas layers, decoded once per layer; the surface map's too when given (warp False:
    its alpha only, crowdview's `full` blend).

    uv_file, normal_file, surface_file: the bundle's CBTX files (bytes) or already parsed TextureArrays."""

    def __init__(self, layout: AtlasLayout, uv_file: bytes | TextureArray, normal_file: bytes | TextureArray,
                 surface_file: bytes | TextureArray | None = None, radius: float = 1.0, warp: bool = True):
        self.layout, self.radius, self.warp = layout, radius, warp
        self.uv_map, self.normal_map = parsed_map(uv_file, "uv map"), parsed_map(normal_file, "normal map")
        self.surface_map = parsed_map(surface_file, "surface map")
        self._layers: dict[int, tuple] = {}
        self._surfaces: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _view(self, plane: np.ndarray, tile: int, edge: bool = False) -> np.ndarray:
        """The whole tile `tile` of a decoded layer (crowdbake.bake.atlas.view_tile): outside the crop not
        covered, or with `edge` clamped to the crop as crowdview's surface reads are."""
        columns = len(self.layout.azimuths_deg)
        return view_tile(self.layout, plane, tile % columns, tile // columns, edge)

    def surface(self, tile: int, layer: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(depth (S, S), motion (S, S, 2)) metres of a tile (crowdbake.bake.surface_maps) and its coverage
        (S, S) 0..1 (the alpha; 1 in a bc1 map); None without a surface map."""
        if self.surface_map is None:
            return None
        if layer not in self._surfaces:
            texels = decode_surface_layer(self.surface_map, layer)
            self._surfaces[layer] = (*surface_maps.decode_surface(texels, self.radius), texels[..., 3] / 255.0)
        return tuple(self._view(plane, tile, edge=True) for plane in self._surfaces[layer])

    def tile(self, tile: int, layer: int) -> DecodedTile:
        if layer not in self._layers:
            self._layers[layer] = decode_atlas_layer(self.uv_map, self.normal_map, layer, self.layout)
        return DecodedTile(*(self._view(plane, tile) for plane in self._layers[layer]))


def sample_tile(tiles: AtlasTiles, tile: int, layer: int, target: impostor_views.OrthoView,
                frames: FrameWeights) -> DecodedTile:
    """One (view, frame) sample as crowdview draws it for a camera at `target` and cycle position `frames`:
    reprojected (crowdbake.reference.impostor_warp.warp_tile) when the bundle has a surface map."""
    decoded = tiles.tile(tile, layer)
    surface = tiles.surface(tile, layer)
    if surface is None:
        return decoded
    if not tiles.warp:  # unmoved: each texel weighs its own coverage
        return replace(decoded, share=surface[-1])
    columns = len(tiles.layout.azimuths_deg)
    source = impostor_views.ortho_view(target.center, target.radius, tiles.layout.azimuths_deg[tile % columns],
                                      tiles.layout.elevations_deg[tile // columns], target.size)
    *fields, coverage = surface
    return impostor_warp.warp_tile(decoded, source, tuple(fields), target, impostor_warp.motion_fraction(layer, frames), coverage=coverage,
                                   crop=tiles.layout.crop_box)


def numpy_picture(atlas: RuntimeAtlas, tiles: AtlasTiles, picture: RuntimePicture, chains: list[list[np.ndarray]] | None = None) -> np.ndarray:
    """The picture crowdbake.render.runtime_shader draws, drawn by the numpy copy of crowdview's shader
    (crowdbake.reference.impostor_blend, impostor_warp) in float64: (S, S, 3), the reference the shader is
    tested against. tiles: AtlasTiles of the same maps; chains: the diffuse textures' mip chains."""
    # A material without region codes (bc1) is drawn with none, as crowdview's u_has_regions.
    diffuse = [texture if regions else np.concatenate([texture[..., :3], np.zeros_like(texture[..., :1])], axis=-1)
               for texture, regions in zip(atlas.diffuse, atlas.has_regions)]
    chains = chains if chains is not None else [impostor_blend.mip_chain(texture) for texture in diffuse]
    view = impostor_views.ortho_view(atlas.center, atlas.radius, picture.azimuth_deg, picture.elevation_deg, atlas.tile_size)
    frames = FrameWeights(picture.layers, picture.frame_weight)
    weights = ViewWeights(picture.tiles, picture.view_weights)
    samples = [(w, sample_tile(tiles, tile, k, view, frames)) for w, tile, k in impostor_blend.samples_for(weights, frames)]
    return impostor_blend.blend_image(samples, diffuse, atlas.outfit_row, shading.camera_light(view), atlas.tile_size, chains,
                                      reprojected=tiles.surface_map is not None and tiles.warp)
