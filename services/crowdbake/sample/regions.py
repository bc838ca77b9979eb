"""Colour-region codes carried in the alpha channel of the diffuse textures.

The paper (section 5, after Tecchia et al. 2002 and Dobbyn et al. 2005) encodes colouring regions
in the alpha channel of the diffuse texture; at run time the region picks a colour from an outfit
map, and the shader multiplies the texture colour by ``outfits[outfit, region]``.

Region r (0..15) is stored as alpha = 17 * r. DXT3/BC2 keeps 4 bits of alpha, and
17 * r == (r << 4) | r, so the code survives that quantisation exactly; decode with
``round(alpha / 17)``. Code 0 means "no recolouring: keep the texture colour".

The outfit colour map (textures/outfits.png) is REGION_COUNT texels wide (one column per code)
and one row per outfit.
"""
from __future__ import annotations

import numpy as np

REGION_COUNT = 16  # 4 bits of alpha
ALPHA_STEP = 17  # 255 / 15: alpha = ALPHA_STEP * code

NONE = 0  # keep the texture colour (gutters, details that must not be tinted)
SKIN = 1
HAIR = 2
TOP = 3
SKIRT = 4  # the simulated garment
SHOES = 5
LEGWEAR = 6  # tights / leggings / anything worn on the legs under the garment
EYES = 7  # eyes and other small facial detail

REGION_NAMES: dict[int, str] = {
    NONE: "none",
    SKIN: "skin",
    HAIR: "hair",
    TOP: "top",
    SKIRT: "skirt",
    SHOES: "shoes",
    LEGWEAR: "legwear",
    EYES: "eyes",
}


def region_alpha(codes: np.ndarray) -> np.ndarray:
    """Alpha values (uint8) for region codes 0..15, any shape."""
    codes = np.asarray(codes)
    if codes.size and (codes.min() < 0 or codes.max() >= REGION_COUNT):
        raise ValueError(f"region codes must lie in 0..{REGION_COUNT - 1}")
    return (codes.astype(np.uint16) * ALPHA_STEP).astype(np.uint8)


def region_codes(alpha: np.ndarray) -> np.ndarray:
    """Region codes (uint8) from alpha values, any shape: round(alpha / 17), exact after BC2's 4-bit alpha."""
    return np.rint(np.asarray(alpha, dtype=np.float32) / ALPHA_STEP).astype(np.uint8)
