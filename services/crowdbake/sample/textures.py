"""Diffuse texture variations and the outfit colour map (the paper's figure 2).

All variations share one layout (crowdbake.sample.humanoid.BODY_UV_RECTS and GARMENT_UV_RECT) and
one alpha channel of colour-region codes (crowdbake.sample.regions): only the RGB differs. Each
variation prints its own pattern (stripes, checks, dots, tartan...) in its own colours on the top
and on the skirt; skin, hair, shoes and legwear are light, nearly neutral tones because at run time
the outfit map multiplies them (a dark base colour could not be tinted light).

Pure functions of (size, seed); the same arguments give the same pixels.
"""
from __future__ import annotations

import colorsys

import numpy as np

from crowdbake.sample import regions
from crowdbake.sample.humanoid import BODY_UV_RECTS, GARMENT_UV_RECT, part_height, rect_to_part

VARIATION_COUNT = 8
OUTFIT_COUNT = 8
PATTERNS = ("plain", "stripes", "pinstripes", "checks", "dots", "diagonal", "tartan", "chevron")

# Base colours (RGB 0..1) of the untinted regions.
SKIN_BASE = (0.96, 0.84, 0.74)
HAIR_BASE = (0.80, 0.74, 0.66)
SHOES_BASE = (0.78, 0.78, 0.80)
LEGWEAR_BASE = (0.93, 0.92, 0.92)
EYES_BASE = (0.20, 0.20, 0.26)
GUTTER = (0.5, 0.5, 0.5)

WAIST_HEIGHT = 1.00  # the top ends, the legwear starts (hidden under the skirt's waistband at 1.06 m)
NECKLINE_HEIGHT = 1.44
SLEEVE_END = 0.28  # fraction of the arm's axis covered by the short sleeve


def _pixel_grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    centres = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(centres, centres, indexing="xy")
    return u, v


def _rect_mask(u: np.ndarray, v: np.ndarray, rect) -> np.ndarray:
    u0, v0, u1, v1 = rect
    return (u >= u0) & (u < u1) & (v >= v0) & (v < v1)


def region_layout(size: int) -> np.ndarray:
    """Region code per texel (size, size) uint8, identical for every variation."""
    u, v = _pixel_grid(size)
    codes = np.full((size, size), regions.NONE, dtype=np.uint8)
    for name, rect in BODY_UV_RECTS.items():
        mask = _rect_mask(u, v, rect)
        around, axis_param = rect_to_part(rect, u[mask], v[mask])
        height = part_height(name, axis_param)
        front = np.abs(around - 0.5)  # 0 at the front, 0.5 at the back
        if name == "torso":
            part = np.where(height > WAIST_HEIGHT, regions.TOP, regions.LEGWEAR)
            # A scoop neckline: deeper at the front.
            neckline = NECKLINE_HEIGHT + 0.05 * np.clip(front / 0.2, 0.0, 1.0) - 0.04 * np.clip(1 - front / 0.2, 0.0, 1.0)
            part = np.where(height > neckline, regions.SKIN, part)
        elif name == "head":
            # Hairline: low at the back, high over the face.
            hairline = 1.585 + 0.11 * np.clip(1.0 - (front - 0.08) / 0.22, 0.0, 1.0)
            part = np.where(height > hairline, regions.HAIR, regions.SKIN)
            for side in (-1.0, 1.0):
                eye = ((around - (0.5 + side * 0.047)) / 0.018) ** 2 + ((height - 1.646) / 0.009) ** 2 < 1.0
                part = np.where(eye, regions.EYES, part)
        elif name.startswith("arm"):
            part = np.where(axis_param < SLEEVE_END, regions.TOP, regions.SKIN)
        elif name.startswith("leg"):
            part = np.full(axis_param.shape, regions.LEGWEAR)
        else:  # feet
            part = np.full(axis_param.shape, regions.SHOES)
        codes[mask] = part
    codes[_rect_mask(u, v, GARMENT_UV_RECT)] = regions.SKIRT
    return codes


def _pattern(kind: str, x: np.ndarray, y: np.ndarray, period: float, rng: np.random.Generator) -> np.ndarray:
    """Pattern intensity in [0, 1] (1 = accent colour) at texel coordinates x, y (pixels)."""
    if kind == "plain":
        return np.zeros_like(x)
    if kind == "stripes":
        return (np.mod(y / period, 1.0) < 0.45).astype(float)
    if kind == "pinstripes":
        return (np.mod(x / (0.5 * period), 1.0) < 0.18).astype(float)
    if kind == "checks":
        a = np.mod(x / period, 1.0) < 0.5
        b = np.mod(y / period, 1.0) < 0.5
        return 0.5 * a + 0.5 * b  # gingham: overlaps darker
    if kind == "dots":
        jitter = rng.uniform(0.35, 0.65, size=2)
        fx, fy = np.mod(x / period, 1.0) - jitter[0], np.mod(y / period + 0.5 * (np.floor(x / period) % 2), 1.0) - jitter[1]
        return (fx**2 + fy**2 < 0.22**2).astype(float)
    if kind == "diagonal":
        return (np.mod((x + y) / (0.8 * period), 1.0) < 0.4).astype(float)
    if kind == "tartan":
        wide = (np.mod(x / (1.6 * period), 1.0) < 0.3).astype(float) + (np.mod(y / (1.6 * period), 1.0) < 0.3)
        thin = (np.abs(np.mod(x / (1.6 * period), 1.0) - 0.65) < 0.04).astype(float) + (np.abs(np.mod(y / (1.6 * period), 1.0) - 0.65) < 0.04)
        return np.clip(0.35 * wide + 0.6 * thin, 0.0, 1.0)
    if kind == "chevron":
        zig = np.abs(np.mod(x / period, 1.0) - 0.5) * period
        return (np.mod((y + zig) / (0.6 * period), 1.0) < 0.4).astype(float)
    raise ValueError(f"unknown pattern {kind!r}")


def _variation_colours(index: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(top base, top accent, skirt base, skirt accent) RGB for one variation: light bases, saturated accents."""
    hue = (index / VARIATION_COUNT + rng.uniform(-0.04, 0.04)) % 1.0
    second = (hue + 0.5 + rng.uniform(-0.1, 0.1)) % 1.0
    top_base = np.array(colorsys.hsv_to_rgb(hue, 0.10, 0.98))
    top_accent = np.array(colorsys.hsv_to_rgb(hue, 0.55, 0.70))
    skirt_base = np.array(colorsys.hsv_to_rgb(second, 0.12, 0.97))
    skirt_accent = np.array(colorsys.hsv_to_rgb(second, 0.60, 0.62))
    return top_base, top_accent, skirt_base, skirt_accent


def diffuse_textures(size: int = 1024, seed: int = 0, count: int = VARIATION_COUNT) -> np.ndarray:
    """count diffuse variations -> (count, size, size, 4) uint8 RGBA; alpha = 17 * region code."""
    if size < 64 or size & (size - 1):
        raise ValueError(f"texture size must be a power of two >= 64, got {size}")
    codes = region_layout(size)
    alpha = regions.region_alpha(codes)
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    period = size / 28.0
    shading = 1.0 - 0.04 * np.sin(x * 0.9) * np.sin(y * 1.1)  # a faint weave so plain cloth is not flat
    rng = np.random.default_rng(seed)
    out = np.empty((count, size, size, 4), dtype=np.uint8)
    fixed = np.zeros((size, size, 3))
    for code, colour in ((regions.SKIN, SKIN_BASE), (regions.HAIR, HAIR_BASE), (regions.SHOES, SHOES_BASE),
                         (regions.LEGWEAR, LEGWEAR_BASE), (regions.EYES, EYES_BASE), (regions.NONE, GUTTER)):
        fixed[codes == code] = colour
    hair = codes == regions.HAIR
    fixed[hair] *= (0.85 + 0.15 * np.sin(x[hair] * 0.6 + 0.3 * y[hair]))[:, None]  # strands
    garment_v0, garment_v1 = GARMENT_UV_RECT[1] * size, GARMENT_UV_RECT[3] * size
    band = ((y < garment_v0 + 0.06 * (garment_v1 - garment_v0)) | (y > garment_v1 - 0.05 * (garment_v1 - garment_v0))) & (codes == regions.SKIRT)
    for index in range(count):
        kind = PATTERNS[index % len(PATTERNS)]
        top_base, top_accent, skirt_base, skirt_accent = _variation_colours(index, rng)
        rgb = fixed.copy()
        for code, base, accent, scale in ((regions.TOP, top_base, top_accent, 0.8), (regions.SKIRT, skirt_base, skirt_accent, 1.0)):
            mask = codes == code
            amount = _pattern(kind, x[mask], y[mask], period * scale, rng)[:, None]
            rgb[mask] = (base * (1 - amount) + accent * amount) * shading[mask][:, None]
        rgb[band] = skirt_accent * 0.9  # waistband and hem trim
        out[index, ..., :3] = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
        out[index, ..., 3] = alpha
    return out


def outfit_map(seed: int = 0, outfits: int = OUTFIT_COUNT) -> np.ndarray:
    """Outfit colour map (outfits, 16, 4) uint8: row k, column r = the multiplier for region r in outfit k.

    Row 0 is all white (the textures as painted). Columns of unused codes and of code 0 are white.
    """
    rng = np.random.default_rng([seed, 1])
    table = np.ones((outfits, regions.REGION_COUNT, 3))
    skin_tones = [(1.0, 1.0, 1.0), (0.93, 0.82, 0.70), (0.80, 0.62, 0.48), (0.58, 0.42, 0.32), (0.42, 0.30, 0.23)]
    hair_colours = [(0.35, 0.24, 0.16), (0.95, 0.82, 0.50), (0.15, 0.12, 0.10), (0.70, 0.32, 0.16), (0.60, 0.58, 0.56)]
    for row in range(1, outfits):
        table[row, regions.SKIN] = skin_tones[rng.integers(len(skin_tones))]
        table[row, regions.HAIR] = hair_colours[rng.integers(len(hair_colours))]
        for code, saturation, value in ((regions.TOP, (0.2, 0.6), (0.75, 1.0)), (regions.SKIRT, (0.25, 0.7), (0.6, 1.0)),
                                        (regions.SHOES, (0.0, 0.5), (0.2, 0.7)), (regions.LEGWEAR, (0.0, 0.3), (0.5, 1.0))):
            table[row, code] = colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(*saturation), rng.uniform(*value))
        table[row, regions.EYES] = colorsys.hsv_to_rgb(rng.uniform(0.5, 0.65), 0.4, 1.0)
    out = np.empty((outfits, regions.REGION_COUNT, 4), dtype=np.uint8)
    out[..., :3] = np.clip(np.rint(table * 255), 0, 255).astype(np.uint8)
    out[..., 3] = 255
    return out
