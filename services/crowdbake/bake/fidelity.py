"""Impostor fidelity: the impostor as a runtime would draw it against the mesh, at 1:1 pixel-to-texel.

The paper switches from mesh to impostor where one impostor texel covers one screen pixel, where impostors
are perceptually equivalent to the mesh (Dobbyn et al. 2006, section 6, after Hamill et al. 2005). At
that distance an orthographic view of the mesh at the tile's resolution *is* the screen image, so:

- the **mesh reference** (crowdbake.reference.mesh_reference; the bake draws it with a shader) is the
  mesh shaded per sample at `supersample`² samples per pixel (exact
  visibility, interpolated normals, the diffuse texture sampled at the interpolated UV) and box-filtered
  down to the tile: an anti-aliased rendering of the mesh;
- the **impostor image** is what the runtime reconstructs from the baked, compressed maps: the UV map's
  texture coordinates look up the same diffuse texture (paper section 5), the region code in its alpha
  picks the outfit colour, and the decoded normal map lights it.

Both use one light model, Lambert with an ambient term, one directional light fixed to the camera (above,
to the left, in front) so that every view is lit from the front, and no gamma. SSIM and PSNR compare them
per view over the character's bounding box; `nearest view` comparisons put the mesh at an angle between
two baked views and the impostor at the nearest baked view: the error of switching tiles, not blending.
Pure numpy (SSIM's window means with OpenCV's box filter).
"""
from __future__ import annotations

import numpy as np

from crowdbake.bake import map_codecs
from crowdbake.bake.shading import apply_outfit, lambert, texels_at

# Pixels added around the union of both images' coverage before measuring, so that the silhouette's
# outside is part of the comparison but an empty frame does not inflate SSIM.
MEASURE_MARGIN_PX = 4
# SSIM's window is 7 pixels; smaller boxes are grown to this.
MIN_MEASURE_SIZE = 7
# impostor_uv.frag.glsl: texture-coordinate gradients are clamped to this many tile texels' worth of
# tile UV, so neighbours across the silhouette or a UV seam do not pick a far too coarse mip level.
GRADIENT_LIMIT_TEXELS = 4.0


def impostor_image(
    uv_map: np.ndarray, normal_map: np.ndarray, diffuse: list[np.ndarray], outfit_row: np.ndarray, light: np.ndarray,
    coverage: np.ndarray | None = None,
) -> np.ndarray:
    """What the runtime draws from one tile: (S, S, 3) float64 0..1, black where the UV map has no coverage.

    uv_map: (S, S, 4) uint16 (rgba16) or (S, S) uint32 (uv32), as stored; normal_map: (S, S, 4) uint8
    as decoded from its (compressed) layer; coverage: the surface map's alpha (S, S) uint8, or None: a
    texel is drawn where the character covers over half of it (SPEC.md "Impostor maps"), as crowdview's
    unblended impostor draws it.
    """
    return impostor_images(uv_map, [normal_map], diffuse, outfit_row, light, coverage)[0]


def impostor_images(
    uv_map: np.ndarray, normal_maps: list[np.ndarray], diffuse: list[np.ndarray], outfit_row: np.ndarray, light: np.ndarray,
    coverage: np.ndarray | None = None,
) -> list[np.ndarray]:
    """impostor_image of one UV tile with each of several normal maps (the stored and the uncompressed
    normals of a view): the UV map is decoded and the diffuse sampled once, and only the covered texels'
    normals are decoded (a character covers a fraction of its tile). The same pictures, to the bit."""
    uv, material, covered = map_codecs.decode_uv_map(uv_map)
    if coverage is not None:
        covered = covered & (np.asarray(coverage) > 127)
    images = [np.zeros(uv.shape[:2] + (3,), dtype=np.float64) for _ in normal_maps]
    if covered.any():
        material = np.clip(material[covered], 0, len(diffuse) - 1)
        albedo = apply_outfit(texels_at(uv[covered], material, diffuse), outfit_row)
        for image, normal_map in zip(images, normal_maps):
            image[covered] = lambert(albedo, map_codecs.decode_normal_map(np.asarray(normal_map)[covered]), light)
    return images


def measure_box(*images: np.ndarray) -> tuple[slice, slice]:
    """(rows, columns) slices of the pixels any image lights, grown by MEASURE_MARGIN_PX (whole image if none)."""
    lit = np.zeros(images[0].shape[:2], dtype=bool)
    for image in images:
        image = np.asarray(image)
        for channel in range(image.shape[-1]):  # (a max over a 3-long last axis is several times slower)
            lit |= image[..., channel] > 0
    height, width = lit.shape
    if not lit.any():
        return slice(0, height), slice(0, width)
    rows, columns = np.nonzero(lit)

    def span(low: int, high: int, limit: int) -> slice:
        low, high = max(low - MEASURE_MARGIN_PX, 0), min(high + 1 + MEASURE_MARGIN_PX, limit)
        while high - low < MIN_MEASURE_SIZE and (low > 0 or high < limit):
            low, high = max(low - 1, 0), min(high + 1, limit)
        return slice(low, high)

    return span(int(rows.min()), int(rows.max()), height), span(int(columns.min()), int(columns.max()), width)


def ssim(a: np.ndarray, b: np.ndarray, window: int) -> float:
    """Mean SSIM of two (H, W, C) float64 images in 0..1, as scikit-image's structural_similarity computes it
    with its defaults (Wang et al. 2004: a uniform `window`² window, sample covariances, K1 = 0.01,
    K2 = 0.03, the map's border of (window - 1) / 2 left out, channels averaged), the window means taken
    with OpenCV's box filter: a few times faster than scipy's uniform filter on these small images, and
    equal to 1e-12 (services/tests/test_fidelity.py checks it against scikit-image)."""
    import cv2

    def mean(image: np.ndarray) -> np.ndarray:
        return cv2.blur(image, (window, window), borderType=cv2.BORDER_REFLECT)

    samples = window * window
    covariance = samples / (samples - 1.0)
    c1, c2 = 0.01**2, 0.03**2
    mean_a, mean_b = mean(a), mean(b)
    var_a = covariance * (mean(a * a) - mean_a * mean_a)
    var_b = covariance * (mean(b * b) - mean_b * mean_b)
    cov_ab = covariance * (mean(a * b) - mean_a * mean_b)
    index = ((2 * mean_a * mean_b + c1) * (2 * cov_ab + c2)) / ((mean_a**2 + mean_b**2 + c1) * (var_a + var_b + c2))
    pad = (window - 1) // 2
    index = index.reshape(a.shape)[pad : a.shape[0] - pad, pad : a.shape[1] - pad]
    return float(np.mean([index[..., c].mean(dtype=np.float64) for c in range(a.shape[2])]))


def compare(reference: np.ndarray, candidate: np.ndarray) -> dict[str, float]:
    """SSIM and PSNR (dB) of two (S, S, 3) images in 0..1 over measure_box; PSNR is inf for equal images."""
    reference = np.asarray(reference, dtype=np.float64)
    candidate = np.asarray(candidate, dtype=np.float64)
    if reference.shape != candidate.shape or reference.ndim != 3:
        raise ValueError(f"compare: images must be equal (H, W, 3), got {reference.shape} and {candidate.shape}")
    rows, columns = measure_box(reference, candidate)
    a, b = reference[rows, columns], candidate[rows, columns]
    window = min(7, *a.shape[:2])
    window -= 1 - window % 2  # odd
    score = ssim(np.ascontiguousarray(a), np.ascontiguousarray(b), window)
    error = float(np.mean((a - b) ** 2))
    psnr = float("inf") if error == 0 else float(10 * np.log10(1.0 / error))  # data range 1
    return {"ssim": score, "psnr_db": psnr}


def summarize(values: list[dict[str, float]]) -> dict[str, float]:
    """Mean and worst SSIM and PSNR over views (worst = lowest)."""
    if not values:
        raise ValueError("summarize: no measurements")
    ssim = np.array([v["ssim"] for v in values])
    psnr = np.array([v["psnr_db"] for v in values])
    finite = psnr[np.isfinite(psnr)]
    return {
        "views": len(values),
        "ssim_mean": float(ssim.mean()),
        "ssim_worst": float(ssim.min()),
        "psnr_db_mean": float(finite.mean()) if finite.size else float("inf"),
        "psnr_db_worst": float(psnr.min()),
    }


def uv_precision(uv_map: np.ndarray, texture_size: int, tile_size: int | None = None) -> dict[str, dict[str, float]]:
    """Texel error of storing a UV map's coordinates at lower precision, for a texture_size² texture.

    uv_map: (S, S, 4) uint16 (the baked, 16-bit map). Compares the 16-bit map with the same coordinates
    packed as uv32 (14 bits each), rounded to 8 bits (rgba8) and those 8-bit coordinates block-compressed
    as BC1 (DXT1), and as uvblock (H and W multiples of 4). Returns, per variant, the max and mean error in
    texels over covered texels (for rgba16 the rounding bound, `bound` True): why the bundle does not store
    8 bits. With tile_size: the diffuse footprint of the runtime's lookup at 1:1 (lookup_footprint_texels,
    diffuse texels per impostor texel) and uvblock's error in those footprints (what the lookup sees).
    """
    from crowdbake.bake import compression
    from crowdbake.formats.texel_codecs import unpack_uv32, unpack_uvblock

    uv, _, covered = map_codecs.decode_uv_map(uv_map)
    result: dict[str, dict[str, float]] = {}
    if not covered.any():
        return result
    exact = uv[covered]
    eight = np.zeros(uv_map.shape[:2] + (4,), dtype=np.uint8)
    eight[..., :2] = np.rint(uv * 255.0)
    eight[..., 3] = 255
    height, width = uv_map.shape[:2]
    padded_height, padded_width = height + (-height) % 4, width + (-width) % 4
    eight = np.pad(eight, ((0, padded_height - height), (0, padded_width - width), (0, 0)))
    bc1 = compression.decode_bc1(compression.encode_bc1(eight), padded_width, padded_height)[:height, :width]
    # The 16-bit map is the reference: its own rounding is at most half a step.
    half_step = 0.5 / 65535.0 * texture_size
    result["rgba16"] = {"max_texels": half_step, "mean_texels": half_step / 2.0, "bound": True}
    u32, v32, _, _ = unpack_uv32(map_codecs.uv_map_to_uv32(uv_map))
    variants = {
        "uv32": np.stack([u32, v32], axis=-1)[covered],
        "rgba8": eight[:height, :width, :2][covered].astype(np.float64) / 255.0,
        "bc1": bc1[..., :2][covered].astype(np.float64) / 255.0,
    }
    if height % 4 == 0 and width % 4 == 0:
        ub, vb, _, _ = unpack_uvblock(map_codecs.uv_map_to_uvblock(uv_map), width, height)
        variants["uvblock"] = np.stack([ub, vb], axis=-1)[covered]
    for name, stored in variants.items():
        error = np.abs(stored - exact).max(axis=1) * texture_size
        result[name] = {"max_texels": float(error.max()), "mean_texels": float(error.mean()), "bound": False}
    if tile_size:
        # What precision the lookup needs: at 1:1 an impostor texel is a pixel, and the runtime samples the
        # diffuse texture at the mip level its neighbours' coordinates span (lookup_lod).
        footprint = 2.0 ** np.clip(lookup_lod(np.where(covered[..., None], uv, 0.0), (texture_size, texture_size), tile_size), 0, None)[covered]
        result["lookup_footprint_texels"] = {"median": float(np.median(footprint)), "p10": float(np.percentile(footprint, 10))}
        if "uvblock" in variants:
            relative = np.abs(variants["uvblock"] - exact).max(axis=1) * texture_size / footprint
            result["uvblock_error_footprints"] = {"mean": float(relative.mean()), "p99": float(np.percentile(relative, 99)),
                                                 "over_one": float((relative > 1).mean())}
    return result


def quad_gradients(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dFdx, dFdy of a (S, S, 2) per-pixel value as a GPU takes them: within each 2×2 quad, the difference
    of the pair of pixels in that row (column); S even."""
    even_x = uv[:, 1::2] - uv[:, 0::2]
    dx = np.repeat(even_x, 2, axis=1)
    even_y = uv[1::2] - uv[0::2]
    dy = np.repeat(even_y, 2, axis=0)
    return dx, dy


def lookup_lod(uv: np.ndarray, texture_size: tuple[int, int], tile_size: int) -> np.ndarray:
    """(S, S) level of detail of crowdview's diffuse lookup (impostor_uv.frag.glsl's textureGrad, its
    gradients clamped to GRADIENT_LIMIT_TEXELS) at every texel of a (S, S, 2) uv tile at 1:1."""
    dx, dy = quad_gradients(uv)
    limit = GRADIENT_LIMIT_TEXELS / tile_size + 1e-6

    height, width = texture_size

    def texels_per_pixel(g: np.ndarray) -> np.ndarray:
        """|clamp(g) · (width, height)|: the gradient shortened to `limit`, in texels."""
        shorten = np.minimum(1.0, limit / np.maximum(np.hypot(g[..., 0], g[..., 1]), 1e-9))
        return np.hypot(g[..., 0] * (shorten * width), g[..., 1] * (shorten * height))

    rho = np.maximum(texels_per_pixel(dx), texels_per_pixel(dy))
    return np.log2(np.maximum(rho, 1e-12))
