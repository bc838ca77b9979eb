"""Writes shared_formats/vectors/v1-uv32: the v1 good bundle with its UV map in pixel format 5
(`uv32`), the decoded values of that map, and broken bundles for the new format.

v1's vectors are never edited (SPEC.md, "Vectors"), so the format added before the first release
gets this folder of its own. The bundle is v1's good bundle (the v1 generator's functions,
imported) with impostor/uv.cbtx replaced; like v1 it is deterministic, and a test regenerates
it into a temporary folder to prove the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v1_uv32.py [OUT_DIR]   # default: shared_formats/vectors/v1-uv32
"""
from __future__ import annotations

import importlib.util
import struct
import sys
from pathlib import Path

import numpy as np

from crowdbake.formats.binary import PIXEL_FORMAT_CODES, decode_texture_array, encode_texture_array
from crowdbake.formats.texel_codecs import pack_uv32, unpack_uv32
from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes

HERE = Path(__file__).resolve().parent
UV = "impostor/uv.cbtx"
WIDTH, HEIGHT, LAYERS = 8, 4, 2  # v1's atlas: tile 4, two azimuths, one elevation, two frames
# Texels whose decoded fields expected.json spells out: (layer, row, column).
SAMPLE_TEXELS = [(0, 0, 0), (0, 0, 4), (0, 1, 2), (0, 3, 7), (1, 0, 5), (1, 2, 3), (1, 3, 6), (1, 3, 7)]


def _v1_generator():
    """shared_formats/generate_vectors_v1.py as a module (shared_formats is not a package)."""
    spec = importlib.util.spec_from_file_location("generate_vectors_v1", HERE / "generate_vectors_v1.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def uv32_layers() -> np.ndarray:
    """(2, 4, 8) uint32: deterministic texels that set every field's bits somewhere: u and v over
    0..1 with both ends, all eight material indices, and uncovered texels (stored as 0)."""
    layer, row, column = np.meshgrid(np.arange(LAYERS), np.arange(HEIGHT), np.arange(WIDTH), indexing="ij")
    texel = (layer * HEIGHT + row) * WIDTH + column  # 0..63
    u = texel / (LAYERS * HEIGHT * WIDTH - 1)
    v = 1.0 - ((texel * 37) % 64) / 63.0
    material = texel % 8
    covered = (texel % 5) != 4
    return pack_uv32(u, v, material, covered)


def good_files() -> tuple[dict, list[BundleFile]]:
    v1 = _v1_generator()
    manifest, files = v1.good_files()
    uv_bytes = encode_texture_array(WIDTH, HEIGHT, "uv32", uv32_layers())
    files = [BundleFile(f.path, uv_bytes if f.path == UV else f.data, f.role) for f in files]
    sections = {key: manifest[key] for key in ("frames_per_second", "cycle", "materials", "outfits", "meshes", "impostor")}
    return build_manifest("vector-good-uv32", "1.0.0", sections, files, created=v1.CREATED, format_version=1), files


def expected_values(manifest: dict, files: list[BundleFile]) -> dict:
    """v1's expected values for every file, plus the uv32 map's decoded texels at SAMPLE_TEXELS."""
    out = _v1_generator().expected_values(manifest, files)
    texture = decode_texture_array(next(f.data for f in files if f.path == UV))
    texels = []
    for layer, row, column in SAMPLE_TEXELS:
        word = int(texture.texels(layer)[row, column])
        u, v, material, covered = unpack_uv32(np.uint32(word))
        texels.append({"layer": layer, "row": row, "column": column, "word": word,
                       "u14": word & 0x3FFF, "v14": (word >> 14) & 0x3FFF,  # the stored integers; u = u14 / 16383
                       "u": float(u), "v": float(v), "material": int(material), "coverage": bool(covered)})
    out["uv32_texels"] = {"file": UV, "texels": texels}
    return out


def bad_cases(manifest: dict, files: list[BundleFile]):
    """(name, manifest bytes, files, file to leave out, expected code, file named by the error)."""
    v1 = _v1_generator()
    data = {f.path: f.data for f in files}

    def edited(path, new_bytes):
        m, fs = v1._with_file(manifest, files, path, new_bytes)
        return manifest_bytes(m), fs

    # uv32 header over rgba16-sized layers: 8 bytes a texel where the format says 4.
    _, v1_files = v1.good_files()
    rgba16_as_uv32 = bytearray(next(f.data for f in v1_files if f.path == UV))
    struct.pack_into("<I", rgba16_as_uv32, 28, PIXEL_FORMAT_CODES["uv32"])
    # rgba16 header over uv32-sized layers: half the bytes the format needs.
    uv32_as_rgba16 = bytearray(data[UV])
    struct.pack_into("<I", uv32_as_rgba16, 28, PIXEL_FORMAT_CODES["rgba16"])
    # A valid CBTX of the right size, but rgba8: too few bits for texture coordinates.
    rgba8_uv = encode_texture_array(WIDTH, HEIGHT, "rgba8", [bytes(4 * WIDTH * HEIGHT)] * LAYERS)

    yield ("uv32_layer_size_disagrees", *edited(UV, bytes(rgba16_as_uv32)), None, "size_mismatch", UV)
    yield ("rgba16_header_on_uv32_layers", *edited(UV, bytes(uv32_as_rgba16)), None, "size_mismatch", UV)
    yield ("uv_map_rgba8", *edited(UV, rgba8_uv), None, "invalid_data", UV)
    yield ("truncated_uv32", *edited(UV, data[UV][:-3]), None, "truncated", UV)


def generate(out_dir: Path) -> None:
    manifest, files = good_files()
    _v1_generator().write_folder(out_dir, manifest, files, expected_values(manifest, files), bad_cases(manifest, files))


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "vectors" / "v1-uv32"
    generate(target)
    print(f"wrote {target}")
