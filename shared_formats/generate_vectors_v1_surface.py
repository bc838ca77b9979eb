"""Writes shared_formats/vectors/v1-surface: the v1 good bundle with a `bc2` surface map (SPEC.md "Impostor
maps", role `impostor-surface`), the decoded value of every texel of that map, and broken bundles for it.

v1's vectors are never edited (SPEC.md, "Vectors"), so the surface map gets this folder of its own. The
good bundle is v1's, files unchanged, plus impostor/surface.cbtx: 8x4 texels and two layers like v1's other
impostor maps (tile 4, two azimuths, one elevation, two baked frames), so each layer is two BC2 blocks, one
a view. The blocks are written here byte by byte from the DXT3 layout, not by the bake's encoder, so the
texels are chosen ones: alpha 255 where the character covers a texel, 17, 68 or 136 where it covers a
share, 0 outside; R (depth code), G and B (motion codes) from all four palette entries of each block.
Every endpoint pair is congruent modulo 3 in each channel, so the 1/3 and 2/3 blends are whole numbers and
any conforming BC2 decoder (floor, round or exact) gives expected.json's values. Deterministic; a test
regenerates it into a temporary folder to prove the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v1_surface.py [OUT_DIR]   # default: shared_formats/vectors/v1-surface
"""
from __future__ import annotations

import importlib.util
import json
import struct
import sys
from pathlib import Path

import numpy as np

from crowdbake.bake.compression import decode
from crowdbake.formats.binary import encode_texture_array
from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes

HERE = Path(__file__).resolve().parent
SURFACE = "impostor/surface.cbtx"
WIDTH, HEIGHT, LAYERS = 8, 4, 2  # v1's atlas: tile 4, two azimuths, one elevation, two frames

# The azimuth-0 view of layer 0, row by row: alpha (multiples of 17: BC2 stores 4 bits) and palette index.
# The other views mirror it (_block_texels). The two texels of each alpha byte differ and no row of
# indices reads the same reversed, so a reader that swaps nibbles or index order decodes other values.
ALPHA = np.array([[0, 136, 68, 0],
                  [136, 255, 255, 136],
                  [68, 255, 255, 136],
                  [17, 255, 255, 0]], np.uint8)
INDEX = np.array([[1, 2, 3, 1],
                  [2, 0, 0, 3],
                  [3, 0, 0, 2],
                  [1, 0, 3, 1]], np.uint8)
# RGB565 endpoints (r5, g6, b5) of the blocks (layer, azimuth), colour0 > colour1 as the bake writes them.
ENDPOINTS = {
    (0, 0): ((24, 36, 15), (15, 33, 16)),
    (0, 1): ((27, 45, 12), (12, 39, 19)),
    (1, 0): ((28, 54, 4), (20, 12, 23)),
    (1, 1): ((31, 15, 11), (19, 60, 27)),
}


def _v1_generator():
    """shared_formats/generate_vectors_v1.py as a module (shared_formats is not a package)."""
    spec = importlib.util.spec_from_file_location("generate_vectors_v1", HERE / "generate_vectors_v1.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _rgb565(r5: int, g6: int, b5: int) -> int:
    return r5 << 11 | g6 << 5 | b5


def _expand(r5: int, g6: int, b5: int) -> np.ndarray:
    """(3,) int: the 8-bit channels a decoder expands RGB565 to (high bits replicated into the low ones)."""
    return np.array([r5 << 3 | r5 >> 2, g6 << 2 | g6 >> 4, b5 << 3 | b5 >> 2])


def _block_texels(layer: int, azimuth: int) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) alpha and (4, 4) palette index of one view: azimuth 1 mirrors left-right, layer 1 top-bottom."""
    alpha, index = ALPHA, INDEX
    if azimuth:
        alpha, index = alpha[:, ::-1], index[:, ::-1]
    if layer:
        alpha, index = alpha[::-1], index[::-1]
    return alpha, index


def _palette(layer: int, azimuth: int) -> np.ndarray:
    """(4, 3) int: the four-colour palette of a block, exact: the endpoints' blends divide by 3."""
    c0, c1 = (_expand(*e) for e in ENDPOINTS[layer, azimuth])
    assert not ((2 * c0 + c1) % 3).any(), "endpoints must be congruent mod 3 in every channel"
    return np.stack([c0, c1, (2 * c0 + c1) // 3, (c0 + 2 * c1) // 3])


def _bc2_block(layer: int, azimuth: int) -> bytes:
    """16 bytes of DXT3: 4-bit alphas, texel 2k in the low nibble of byte k; colour0, colour1 (RGB565, little-endian);
    2-bit indices, texel i at bits 2i; texels in row-major order inside the block."""
    alpha, index = _block_texels(layer, azimuth)
    nibbles = (alpha // 17).reshape(-1)
    assert (nibbles * 17 == alpha.reshape(-1)).all()
    alpha_bytes = bytes(int(nibbles[2 * k]) | int(nibbles[2 * k + 1]) << 4 for k in range(8))
    colour0, colour1 = (_rgb565(*e) for e in ENDPOINTS[layer, azimuth])
    assert colour0 > colour1
    bits = sum(int(i) << (2 * n) for n, i in enumerate(index.reshape(-1)))
    return alpha_bytes + struct.pack("<HHI", colour0, colour1, bits)


def surface_layers() -> list[bytes]:
    """Two layers of two blocks: block a (row-major block order) is the view of azimuth a."""
    return [_bc2_block(layer, 0) + _bc2_block(layer, 1) for layer in range(LAYERS)]


def surface_texels() -> np.ndarray:
    """(2, 4, 8, 4) uint8 RGBA: the decoded surface map, from the chosen values (not from a decoder)."""
    out = np.zeros((LAYERS, HEIGHT, WIDTH, 4), np.uint8)
    for layer in range(LAYERS):
        for azimuth in range(WIDTH // 4):
            alpha, index = _block_texels(layer, azimuth)
            out[layer, :, 4 * azimuth:4 * azimuth + 4, :3] = _palette(layer, azimuth)[index]
            out[layer, :, 4 * azimuth:4 * azimuth + 4, 3] = alpha
    return out


def good_files() -> tuple[dict, list[BundleFile]]:
    v1 = _v1_generator()
    manifest, files = v1.good_files()
    files = [*files, BundleFile(SURFACE, encode_texture_array(WIDTH, HEIGHT, "bc2", surface_layers()), "impostor-surface")]
    sections = {key: manifest[key] for key in ("frames_per_second", "cycle", "materials", "outfits", "meshes", "impostor")}
    sections["impostor"] = {**sections["impostor"], "maps": {**sections["impostor"]["maps"], "surface": SURFACE}}
    return build_manifest("vector-good-surface", "1.0.0", sections, files, created=v1.CREATED, format_version=1), files


def expected_values(manifest: dict, files: list[BundleFile]) -> dict:
    """v1's expected values for every file, plus every texel of the surface map after BC2 decoding."""
    out = _v1_generator().expected_values(manifest, files)
    texels = surface_texels()
    # The bake's own decoder must agree, or these vectors would disagree with the readers they test.
    for layer, data in enumerate(surface_layers()):
        assert (decode(data, "bc2", WIDTH, HEIGHT) == texels[layer]).all(), layer
    out["surface_texels"] = {"file": SURFACE, "pixel_format": "bc2", "texels": [
        {"layer": layer, "x": x, "y": y, **dict(zip("rgba", map(int, texels[layer, y, x])))}
        for layer in range(LAYERS) for y in range(HEIGHT) for x in range(WIDTH)]}
    return out


def bad_cases(manifest: dict, files: list[BundleFile]):
    """(name, manifest bytes, files, file to leave out, expected code, file named by the error)."""
    v1 = _v1_generator()
    data = {f.path: f.data for f in files}

    def edited(new_bytes):
        m, fs = v1._with_file(manifest, files, SURFACE, new_bytes)
        return manifest_bytes(m), fs

    bc2 = data[SURFACE][32:]  # the layers, after the 32-byte header
    layer = bc2[:len(bc2) // LAYERS]
    # Valid CBTX files of the maps' size in formats the spec refuses for the surface map: bc5 has two
    # channels, no depth-and-motion triple; uv32 has rgba8's layer size, so only the format code tells.
    bc5 = encode_texture_array(WIDTH, HEIGHT, "bc5", [v1._bc_blocks(2, 16, 7), v1._bc_blocks(2, 16, 8)])
    uv32 = encode_texture_array(WIDTH, HEIGHT, "uv32", np.zeros((LAYERS, HEIGHT, WIDTH), np.uint32))
    # bc2 of the right format but one view wide, or one baked frame short of frame_indices.
    one_view = encode_texture_array(4, HEIGHT, "bc2", [_bc2_block(k, 0) for k in range(LAYERS)])
    one_layer = encode_texture_array(WIDTH, HEIGHT, "bc2", [layer])
    # The manifest names the surface map, but the files list does not hold it.
    unlisted = json.loads(manifest_bytes(manifest))
    unlisted["files"] = [entry for entry in unlisted["files"] if entry["path"] != SURFACE]
    v1_files = [f for f in files if f.path != SURFACE]

    yield ("surface_map_bc5", *edited(bc5), None, "invalid_data", SURFACE)
    yield ("surface_map_uv32", *edited(uv32), None, "invalid_data", SURFACE)
    yield ("surface_width_disagrees", *edited(one_view), None, "invalid_data", SURFACE)
    yield ("surface_layer_count_disagrees", *edited(one_layer), None, "invalid_data", SURFACE)
    yield ("surface_not_listed", manifest_bytes(unlisted), v1_files, None, "invalid_data", SURFACE)
    yield ("truncated_surface", *edited(data[SURFACE][:-3]), None, "truncated", SURFACE)


def generate(out_dir: Path) -> None:
    manifest, files = good_files()
    _v1_generator().write_folder(out_dir, manifest, files, expected_values(manifest, files), bad_cases(manifest, files))


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "vectors" / "v1-surface"
    generate(target)
    print(f"wrote {target}")
