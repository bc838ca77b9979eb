"""Writes shared_formats/vectors/v1-crop: the v1 good bundle read as cropped tiles (SPEC.md "Impostor
maps", `impostor.crop`), and broken bundles for the crop.

v1's vectors are never edited (SPEC.md, "Vectors"), so the crop gets this folder of its own. The good
bundle is v1's, files unchanged, with tiles of 8 texels of which the maps store the 4x4 crop at (4, 0):
v1's 8x4 atlases are then two cells of 4x4, as before. Deterministic; a test regenerates it into a
temporary folder to prove the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v1_crop.py [OUT_DIR]   # default: shared_formats/vectors/v1-crop
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes

HERE = Path(__file__).resolve().parent
TILE, CROP = 8, {"x": 4, "y": 0, "width": 4, "height": 4}


def _v1_generator():
    """shared_formats/generate_vectors_v1.py as a module (shared_formats is not a package)."""
    spec = importlib.util.spec_from_file_location("generate_vectors_v1", HERE / "generate_vectors_v1.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _manifest(impostor_changes: dict, name: str = "vector-good-crop") -> tuple[dict, list[BundleFile]]:
    v1 = _v1_generator()
    manifest, files = v1.good_files()
    sections = {key: manifest[key] for key in ("frames_per_second", "cycle", "materials", "outfits", "meshes", "impostor")}
    sections["impostor"] = {**sections["impostor"], **impostor_changes}
    return build_manifest(name, "1.0.0", sections, files, created=v1.CREATED, format_version=1), files


def good_files() -> tuple[dict, list[BundleFile]]:
    return _manifest({"tile_size": TILE, "crop": CROP})


def bad_cases():
    """(name, manifest bytes, files, expected code, file named by the error)."""
    cases = {
        # The crop's far edge past the tile: x + width = 12 > 8.
        "crop_outside_tile": ({"tile_size": TILE, "crop": {**CROP, "x": 8}}, "invalid_data", "manifest.json"),
        # Not on 4-texel blocks: BC blocks would straddle cells.
        "crop_not_on_blocks": ({"tile_size": TILE, "crop": {**CROP, "x": 2}}, "manifest_invalid", "manifest.json"),
        # Cells of 8x4 need 16x4 atlases; the maps are 8x4.
        "crop_disagrees_with_maps": ({"tile_size": TILE, "crop": {"x": 0, "y": 0, "width": 8, "height": 4}}, "invalid_data",
                                     "impostor/detail.cbtx"),
    }
    for name, (changes, code, file) in cases.items():
        manifest, files = _manifest(changes)
        yield name, manifest_bytes(manifest), files, code, file


def generate(out_dir: Path) -> None:
    v1 = _v1_generator()
    manifest, files = good_files()
    expected = {**v1.expected_values(manifest, files), "crop": {"tile_size": TILE, **CROP}}
    v1.write_folder(out_dir, manifest, files, expected,
                    ((name, data, case_files, None, code, file) for name, data, case_files, code, file in bad_cases()))


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "vectors" / "v1-crop"
    generate(target)
    print(f"wrote {target}")
