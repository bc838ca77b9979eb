"""The impostor as crowdview's shader draws it, blended over views and frames, in numpy: the reference
crowdview's own shader, as the bake draws it (crowdbake.render.runtime_shader), is tested against.

crowdview (runtime/README.md, "Impostor blending"; shaders/impostor_uv.frag.glsl) mixes the samples
crowdbake.bake.view_blend chooses: each (view, frame) sample reads its own UV-map texel at the same offset
inside its tile, looks the diffuse texture up with that exact coordinate, and only colours, normals and
coverage are blended, each sample weighted by the part of the pixel its silhouette covers; the pixel's
opacity is a smooth step of the blended coverage (edge_alpha), drawn over black here, as crowdview
blends it over the scene.

The diffuse lookup is the shader's `textureGrad` with trilinear filtering over a box-filtered mip chain
(what glGenerateMipmap makes on common drivers), at the level crowdbake.bake.fidelity.lookup_lod takes
from the UV differences of neighbouring screen pixels within their 2×2 quad (1 pixel = 1 tile texel at
the switch distance). Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake import shading
from crowdbake.bake.fidelity import lookup_lod
from crowdbake.reference.coverage import wrap_uv
from crowdbake.bake.view_blend import FrameWeights, ViewWeights

# runtime/src/config.h CV_EDGE_LOW: blended coverage at or under this is transparent, at or over one minus
# it opaque (edge_alpha).
EDGE_LOW = 0.1
# config.h CV_MISS_LOW, CV_MISS_HIGH: target texels of a reprojection's last miss where trust starts and
# ends falling (trust); TRUSTED_SHARE: the part of the blended coverage trusted samples must hold for the
# colour to be theirs alone.
MISS_LOW, MISS_HIGH, TRUSTED_SHARE = 0.5, 2.0, 0.05


def edge_alpha(coverage: np.ndarray, reprojected: bool = True) -> np.ndarray:
    """Opacity (same shape, float64 0..1) of pixels whose blended samples cover `coverage` (0..1) of their
    weight, as impostor_uv_map.glsl edge_alpha. Reprojected samples' silhouettes disagree by a texel or
    two: GLSL's smoothstep(EDGE_LOW, 1 - EDGE_LOW, coverage), a half-transparent edge that stays nearer the
    mesh than cutting at one half, which keeps only where they agree. Unmoved samples disagree by a whole
    limb: 1 where coverage is over one half, else 0."""
    coverage = np.asarray(coverage, dtype=np.float64)
    if not reprojected:
        return (coverage > 0.5).astype(np.float64)
    t = np.clip((coverage - EDGE_LOW) / (1.0 - 2.0 * EDGE_LOW), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True)
class DecodedTile:
    """One (view, frame) tile as the runtime samples it.

    uv: (S, S, 2) float64 texture coordinates; material: (S, S) int64; covered: (S, S) bool;
    normal: (S, S, 3) float64 model-space unit normals (the decoded normal map); share: (S, S) float64
    0..1, the part of each pixel the sample's silhouette covers (the surface map's alpha, SPEC.md
    "Impostor maps"), or None: all of every covered pixel; miss: (S, S) target texels the reprojection
    still missed by at its last step (impostor_warp.reproject), or None: not reprojected; taps: the four
    texels round each reprojected point with their bilinear weights ((S, S) weight, tile) (impostor_warp.
    bilinear_taps), whose normals and colours crowdview blends for the sample's, or None: the texel's own.
    """

    uv: np.ndarray
    material: np.ndarray
    covered: np.ndarray
    normal: np.ndarray
    share: np.ndarray | None = None
    miss: np.ndarray | None = None
    taps: tuple | None = None


def trust(miss: np.ndarray | None) -> np.ndarray | float:
    """How far a reprojected sample's colour is trusted, 0..1, from its last step's miss in target texels
    (impostor_uv.frag.glsl, config.h CV_MISS_LOW and CV_MISS_HIGH): 1 where the fixed-point iteration
    converged, falling to 0 where it did not (the surface the pixel needs is hidden in that view)."""
    if miss is None:
        return 1.0
    t = np.clip((np.asarray(miss, np.float64) - MISS_LOW) / (MISS_HIGH - MISS_LOW), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def mip_chain(texture: np.ndarray) -> list[np.ndarray]:
    """(h, w, 4) uint8 -> [level 0, 1, ...] float64 RGB (h>>k, w>>k, 3), 2×2 box filter down to 1×1
    (glGenerateMipmap's usual filter; odd sizes drop their last row or column)."""
    level = np.asarray(texture)[..., :3].astype(np.float64)
    levels = [level]
    while level.shape[0] > 1 or level.shape[1] > 1:
        h, w = max(level.shape[0] // 2, 1), max(level.shape[1] // 2, 1)
        ys = np.minimum(np.arange(2 * h).reshape(h, 2), level.shape[0] - 1)
        xs = np.minimum(np.arange(2 * w).reshape(w, 2), level.shape[1] - 1)
        level = level[ys][:, :, xs].mean(axis=(1, 3))
        levels.append(level)
    return levels


def _bilinear(level: np.ndarray, uv: np.ndarray) -> np.ndarray:
    height, width = level.shape[:2]
    x = uv[:, 0] * width - 0.5
    y = uv[:, 1] * height - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    x1, y1 = (x0 + 1) % width, (y0 + 1) % height
    x0, y0 = x0 % width, y0 % height
    return (level[y0, x0] * (1 - fx) * (1 - fy) + level[y0, x1] * fx * (1 - fy) + level[y1, x0] * (1 - fx) * fy
            + level[y1, x1] * fx * fy)


def sample_trilinear(chain: list[np.ndarray], uv: np.ndarray, lod: np.ndarray) -> np.ndarray:
    """(N, 3) RGB 0..255 of a mip chain at (N, 2) uv (REPEAT) and (N,) level of detail (clamped to the chain)."""
    uv = wrap_uv(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    lod = np.clip(np.asarray(lod, dtype=np.float64).reshape(-1), 0.0, len(chain) - 1)
    low = np.floor(lod).astype(np.int64)
    fraction = (lod - low)[:, None]
    out = np.zeros((len(uv), 3))
    for level in np.unique(low):
        chosen = low == level
        colour = _bilinear(chain[level], uv[chosen])
        if level + 1 < len(chain):
            colour = colour * (1 - fraction[chosen]) + _bilinear(chain[level + 1], uv[chosen]) * fraction[chosen]
        out[chosen] = colour
    return out


def albedo(tile: DecodedTile, diffuse: list[np.ndarray], chains: list[list[np.ndarray]], outfit_row: np.ndarray,
           tile_size: int, lod_uv: np.ndarray | None = None) -> np.ndarray:
    """(S, S, 3) outfit-coloured diffuse 0..1 of one tile's covered texels (0 elsewhere), as the shader's
    albedo_at; lod_uv: the (S, S, 2) coordinates whose screen differences set the mip level (None: the
    tile's own; a bilinear tap looks up at its sample's level, as filtered_albedo)."""
    out = np.zeros(tile.uv.shape[:2] + (3,))
    covered = tile.covered
    if not covered.any():
        return out
    texels = np.zeros((int(covered.sum()), 4))
    material = np.clip(tile.material[covered], 0, len(diffuse) - 1)
    uv = tile.uv[covered]
    lods: dict[tuple[int, int], np.ndarray] = {}  # by texture size: materials often share one
    for index, texture in enumerate(diffuse):
        chosen = material == index
        if not chosen.any():
            continue
        if texture.shape[:2] not in lods:
            lods[texture.shape[:2]] = lookup_lod(tile.uv if lod_uv is None else lod_uv, texture.shape[:2], tile_size)[covered]
        lod = lods[texture.shape[:2]][chosen]
        texels[chosen, :3] = sample_trilinear(chains[index], uv[chosen], lod)
        height, width = texture.shape[:2]
        wrapped = wrap_uv(uv[chosen])
        x = np.clip((wrapped[:, 0] * width).astype(np.int64), 0, width - 1)
        y = np.clip((wrapped[:, 1] * height).astype(np.int64), 0, height - 1)
        texels[chosen, 3] = texture[y, x, 3]  # region codes: the texel's own, unfiltered
    out[covered] = shading.apply_outfit(texels, outfit_row)
    return out


def sample_albedo_and_normal(tile: DecodedTile, diffuse: list[np.ndarray], chains: list[list[np.ndarray]],
                              outfit_row: np.ndarray, tile_size: int) -> tuple[np.ndarray, np.ndarray]:
    """A sample's (S, S, 3) albedo and unnormalised normal where it is covered (0 elsewhere): its texel's
    own, or with `taps` the bilinear blend of the four round its point (impostor_uv.frag.glsl
    filtered_albedo: over the taps the character covers, its own texel among them; impostor_warp.glsl
    filtered_normal: over all four, the normal map being filled into the background)."""
    if tile.taps is None:
        return albedo(tile, diffuse, chains, outfit_row, tile_size), np.where(tile.covered[..., None], tile.normal, 0.0)
    shape = tile.uv.shape[:2] + (3,)
    colour, weights, normal = np.zeros(shape), np.zeros(shape[:2]), np.zeros(shape)
    for weight, tap in tile.taps:
        counted = weight * (tap.covered & (weight > 0))
        colour += counted[..., None] * albedo(tap, diffuse, chains, outfit_row, tile_size, lod_uv=tile.uv)
        weights += counted
        normal += weight[..., None] * tap.normal
    # A covered sample's own texel is one of the taps, of weight a quarter or more: where it is covered, weights > 0.
    colour = colour / np.maximum(weights, 1e-6)[..., None]
    covered = tile.covered[..., None]
    return np.where(covered, colour, 0.0), np.where(covered, normal, 0.0)


def blend_image(samples: list[tuple[float, DecodedTile]], diffuse: list[np.ndarray], outfit_row: np.ndarray,
                light: np.ndarray, tile_size: int, chains: list[list[np.ndarray]] | None = None, reprojected: bool = True) -> np.ndarray:
    """The runtime's blended impostor over black: (S, S, 3) float64 0..1, the lit colour times edge_alpha
    of the blended coverage (black where that is 0); `reprojected`: the samples were moved (CV_WARP).

    samples: (weight, tile) per (view, frame) pair with weight > 0 (weights sum to 1); diffuse: per material
    (h, w, 4) uint8 as decoded (variation 0); outfit_row: (16, 4) uint8; light: (3,) model-space unit
    direction towards the light (crowdbake.bake.fidelity's Lambert model).
    """
    if chains is None:
        chains = [mip_chain(texture) for texture in diffuse]
    shape = samples[0][1].uv.shape[:2]
    coverage, trusted = np.zeros(shape), np.zeros(shape)
    colour, normal = np.zeros(shape + (3,)), np.zeros(shape + (3,))
    trusted_colour, trusted_normal = np.zeros(shape + (3,)), np.zeros(shape + (3,))
    for weight, tile in samples:
        if weight <= 0:
            continue
        w = weight * tile.covered * (1.0 if tile.share is None else tile.share)
        sure = w * trust(tile.miss)
        coverage += w
        trusted += sure
        sample_colour, sample_normal = sample_albedo_and_normal(tile, diffuse, chains, outfit_row, tile_size)
        colour += w[..., None] * sample_colour
        normal += w[..., None] * sample_normal
        trusted_colour += sure[..., None] * sample_colour
        trusted_normal += sure[..., None] * sample_normal
    # Where the samples whose reprojection converged hold enough of the coverage, the colour is theirs.
    use_trusted = trusted > TRUSTED_SHARE * coverage
    colour = np.where(use_trusted[..., None], trusted_colour, colour)
    normal = np.where(use_trusted[..., None], trusted_normal, normal)
    coverage_of_colour = np.where(use_trusted, trusted, coverage)
    alpha = edge_alpha(coverage, reprojected)
    drawn = alpha > 0
    image = np.zeros(shape + (3,))
    if drawn.any():
        base = colour[drawn] / coverage_of_colour[drawn][:, None]
        length = np.linalg.norm(normal[drawn], axis=-1, keepdims=True)
        unit = np.divide(normal[drawn], length, out=np.zeros_like(normal[drawn]), where=length > 1e-12)
        image[drawn] = shading.lambert(base, unit, light) * alpha[drawn][:, None]
    return image


def samples_for(view: ViewWeights, frames: FrameWeights) -> list[tuple[float, int, int]]:
    """(weight, tile, layer) of every (view, frame) pair with weight > 0, pairs repeated merged."""
    merged: dict[tuple[int, int], float] = {}
    for layer, frame_weight in ((frames.layers[0], 1.0 - frames.weight), (frames.layers[1], frames.weight)):
        for tile, view_weight in zip(view.tiles, view.weights):
            w = view_weight * frame_weight
            if w > 0:
                merged[(tile, layer)] = merged.get((tile, layer), 0.0) + w
    return [(w, tile, layer) for (tile, layer), w in merged.items()]
