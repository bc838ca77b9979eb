"""Writes shared_formats/vectors/v1-uvblock: the v1 good bundle with its UV map in pixel format 6
(`uvblock`), the decoded values of every texel of that map, and broken bundles for the new format.

v1's vectors are never edited (SPEC.md, "Vectors"), so the format added before the first release
gets this folder of its own. The bundle is v1's good bundle (the v1 generator's functions,
imported) with impostor/uv.cbtx replaced; like v1 it is deterministic, and a test regenerates
it into a temporary folder to prove the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v1_uvblock.py [OUT_DIR]   # default: shared_formats/vectors/v1-uvblock
"""
from __future__ import annotations

import importlib.util
import struct
import sys
from pathlib import Path

import numpy as np

from crowdbake.formats.binary import PIXEL_FORMAT_CODES, decode_texture_array, encode_texture_array
from crowdbake.formats.texel_codecs import pack_uvblock, unpack_uvblock
from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes

HERE = Path(__file__).resolve().parent
UV = "impostor/uv.cbtx"
WIDTH, HEIGHT, LAYERS = 8, 4, 2  # v1's atlas: tile 4, two azimuths, one elevation, two frames: two blocks a layer


def _v1_generator():
    """shared_formats/generate_vectors_v1.py as a module (shared_formats is not a package)."""
    spec = importlib.util.spec_from_file_location("generate_vectors_v1", HERE / "generate_vectors_v1.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def uvblock_layers() -> list[bytes]:
    """Two layers whose four blocks use every part of the format: layer 0 block 0 one smooth UV chart
    (one subset, a small shift), block 1 a UV seam (two charts of one material) and outside texels;
    layer 1 block 0 three materials (three subsets), block 1 one texel at u = v = 1 and the rest outside."""
    row, column = np.meshgrid(np.arange(HEIGHT), np.arange(WIDTH), indexing="ij")
    layers = []
    # Layer 0.
    u = 0.25 + 0.004 * column + 0.001 * row
    v = 0.60 + 0.003 * row
    material = np.zeros((HEIGHT, WIDTH), np.int64)
    covered = np.ones((HEIGHT, WIDTH), bool)
    seam = (column >= 4) & (column >= 6)
    u = np.where(seam, 0.9 - 0.002 * row, u)
    v = np.where(seam, 0.1 + 0.002 * column, v)
    covered &= ~((column >= 4) & (row == 3))
    material = np.where(column >= 4, 1, material)
    layers.append(pack_uvblock(u, v, material, covered))
    # Layer 1.
    u = 0.5 + 0.01 * column
    v = 0.05 + 0.01 * row
    material = np.where(column < 4, np.array([0, 1, 3, 3])[column % 4], 2)
    covered = (column < 4) | ((row == 2) & (column == 5))
    u = np.where((row == 2) & (column == 5), 1.0, u)
    v = np.where((row == 2) & (column == 5), 1.0, v)
    layers.append(pack_uvblock(u, v, material, covered))
    return layers


def good_files() -> tuple[dict, list[BundleFile]]:
    v1 = _v1_generator()
    manifest, files = v1.good_files()
    uv_bytes = encode_texture_array(WIDTH, HEIGHT, "uvblock", uvblock_layers())
    files = [BundleFile(f.path, uv_bytes if f.path == UV else f.data, f.role) for f in files]
    sections = {key: manifest[key] for key in ("frames_per_second", "cycle", "materials", "outfits", "meshes", "impostor")}
    return build_manifest("vector-good-uvblock", "1.0.0", sections, files, created=v1.CREATED, format_version=1), files


def expected_values(manifest: dict, files: list[BundleFile]) -> dict:
    """v1's expected values for every file, plus every texel of the uvblock map: the stored integers
    qu, qv (u = qu / 4095), material and coverage."""
    out = _v1_generator().expected_values(manifest, files)
    texture = decode_texture_array(next(f.data for f in files if f.path == UV))
    texels = []
    for layer in range(LAYERS):
        u, v, material, covered = unpack_uvblock(texture.layers[layer], WIDTH, HEIGHT)
        for row in range(HEIGHT):
            for column in range(WIDTH):
                texels.append({"layer": layer, "row": row, "column": column, "qu": int(round(u[row, column] * 4095)),
                               "qv": int(round(v[row, column] * 4095)), "material": int(material[row, column]),
                               "coverage": bool(covered[row, column])})
    out["uvblock_texels"] = {"file": UV, "texels": texels}
    return out


def bad_cases(manifest: dict, files: list[BundleFile]):
    """(name, manifest bytes, files, file to leave out, expected code, file named by the error)."""
    v1 = _v1_generator()
    data = {f.path: f.data for f in files}

    def edited(path, new_bytes):
        m, fs = v1._with_file(manifest, files, path, new_bytes)
        return manifest_bytes(m), fs

    # Texel 0 of layer 0's first block in subset 0, whose header now says base 255, shift 7: 4080 + 7·128.
    above = bytearray(data[UV])
    block = 32  # the first block follows the 32-byte header
    words = list(struct.unpack_from("<6I", above, block))
    words[0] = (words[0] & ~3) | 1
    words[1] = (words[1] & ~0x1FFFFF) | 255 | 7 << 18
    words[3] = words[3] | 7  # off_u of texel 0
    struct.pack_into("<6I", above, block, *words)
    # uvblock header over uv32-sized layers: 4 bytes a texel where the format says 1.5.
    uv32_as_uvblock = bytearray(encode_texture_array(WIDTH, HEIGHT, "uv32", np.zeros((LAYERS, HEIGHT, WIDTH), np.uint32)))
    struct.pack_into("<I", uv32_as_uvblock, 28, PIXEL_FORMAT_CODES["uvblock"])

    yield ("uvblock_coordinate_above_4095", *edited(UV, bytes(above)), None, "invalid_data", UV)
    yield ("uvblock_layer_size_disagrees", *edited(UV, bytes(uv32_as_uvblock)), None, "size_mismatch", UV)
    yield ("truncated_uvblock", *edited(UV, data[UV][:-5]), None, "truncated", UV)


def generate(out_dir: Path) -> None:
    manifest, files = good_files()
    _v1_generator().write_folder(out_dir, manifest, files, expected_values(manifest, files), bad_cases(manifest, files))


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "vectors" / "v1-uvblock"
    generate(target)
    print(f"wrote {target}")
