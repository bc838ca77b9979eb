"""Writes shared_formats/vectors/v1: a tiny good bundle, its decoded values, and broken bundles.

Run once; the output is committed and never edited (SPEC.md, "Vectors"). The generator is
deterministic (fixed creation time), and a test regenerates into a temporary folder to prove
the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v1.py [OUT_DIR]   # default: shared_formats/vectors/v1
"""
from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

import numpy as np

from crowdbake.formats.binary import encode_pose_cache, encode_texture_array
from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes, sha256_hex, write_bundle

CREATED = "2026-01-01T00:00:00Z"


def _quad_frames(frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A unit quad in the XY plane facing +Z, rising 0.125 m per frame."""
    base = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.5, 1.0, 0.0], [-0.5, 1.0, 0.0]], np.float32)
    positions = np.stack([base + np.float32([0.0, 0.125 * f, 0.0]) for f in range(frames)])
    normals = np.tile(np.float32([0.0, 0.0, 1.0]), (frames, 4, 1))
    uvs = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]], np.float32)
    indices = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    return indices, uvs, positions, normals


def _triangle_frames(frames: int, z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    base = np.array([[-0.25, 0.25, z], [0.25, 0.25, z], [0.0, 0.75, z]], np.float32)
    positions = np.stack([base + np.float32([0.0, 0.0625 * f, 0.0]) for f in range(frames)])
    normals = np.tile(np.float32([0.0, 0.0, 1.0]), (frames, 3, 1))
    uvs = np.array([[0.25, 0.75], [0.75, 0.75], [0.5, 0.25]], np.float32)
    return np.array([[0, 1, 2]], np.uint32), uvs, positions, normals


def _bc_blocks(count: int, block_size: int, seed: int) -> bytes:
    """Deterministic BC blocks: the format only fixes their size, so any bytes are valid blocks."""
    return bytes((seed * 31 + i * 7) % 256 for i in range(count * block_size))


def good_files() -> tuple[dict, list[BundleFile]]:
    frames = 2
    files = [
        BundleFile("poses/body_lod0.cbpc", encode_pose_cache(*_quad_frames(frames), 24.0), "pose-cache"),
        BundleFile("poses/body_lod1.cbpc", encode_pose_cache(*_triangle_frames(frames, 0.0), 24.0), "pose-cache"),
        BundleFile("poses/skirt_lod0.cbpc", encode_pose_cache(*_triangle_frames(frames, 0.1), 24.0), "pose-cache"),
        # 4x4 diffuse, two variations, DXT3: one 16-byte block per layer.
        BundleFile("textures/diffuse.cbtx", encode_texture_array(4, 4, "bc2", [_bc_blocks(1, 16, 1), _bc_blocks(1, 16, 2)]), "diffuse"),
        BundleFile("textures/outfits.cbtx", encode_texture_array(16, 2, "rgba8", np.arange(16 * 2 * 4, dtype=np.uint8).reshape(1, 2, 16, 4) * 2), "outfit-colours"),
        # Impostor atlases: tile 4, two azimuths, one elevation -> 8x4, two baked frames.
        BundleFile("impostor/normal.cbtx", encode_texture_array(8, 4, "bc1", [_bc_blocks(2, 8, 3), _bc_blocks(2, 8, 4)]), "impostor-normal"),
        BundleFile(
            "impostor/uv.cbtx",
            encode_texture_array(8, 4, "rgba16", (np.arange(2 * 4 * 8 * 4, dtype=np.uint32).reshape(2, 4, 8, 4) * 257 % 65536).astype(np.uint16)),
            "impostor-uv",
        ),
        BundleFile("impostor/detail.cbtx", encode_texture_array(8, 4, "bc2", [_bc_blocks(2, 16, 5), _bc_blocks(2, 16, 6)]), "impostor-detail"),
        BundleFile("cycle/cycle.json", b'{"cycle_frames": 2}\n', "cycle"),
    ]
    sections = {
        "frames_per_second": 24.0,
        "cycle": {"source_start_frame": 10, "source_end_frame": 12, "frames": frames, "closing": "none",
                  "position_jump_ratio": 0.5, "velocity_jump_ratio": 0.25},
        "materials": [{"name": "outfit", "diffuse": "textures/diffuse.cbtx", "variations": 2}],
        "outfits": {"file": "textures/outfits.cbtx", "count": 2, "regions": 16},
        "meshes": [
            {"part": "body", "kind": "body", "lod": 0, "file": "poses/body_lod0.cbpc", "material": 0, "vertex_count": 4, "triangle_count": 2},
            {"part": "body", "kind": "body", "lod": 1, "file": "poses/body_lod1.cbpc", "material": 0, "vertex_count": 3, "triangle_count": 1},
            {"part": "skirt", "kind": "garment", "lod": 0, "file": "poses/skirt_lod0.cbpc", "material": 0, "vertex_count": 3, "triangle_count": 1},
        ],
        "impostor": {"tile_size": 4, "azimuths_deg": [0.0, 180.0], "elevations_deg": [0.0], "frame_indices": [0, 1],
                     "bounds": {"center": [0.0, 0.5, 0.0], "radius": 1.0},
                     "maps": {"normal": "impostor/normal.cbtx", "uv": "impostor/uv.cbtx", "detail": "impostor/detail.cbtx"}},
    }
    return build_manifest("vector-good", "1.0.0", sections, files, created=CREATED, format_version=1), files


def expected_values(manifest: dict, files: list[BundleFile]) -> dict:
    """What a reader must decode from the good bundle: every number, as plain JSON."""
    from crowdbake.formats.binary import decode_pose_cache, decode_texture_array

    out = {"name": manifest["name"], "version": manifest["version"], "format_version": 1, "pose_caches": {}, "textures": {}}
    for bundle_file in files:
        if bundle_file.role == "pose-cache":
            cache = decode_pose_cache(bundle_file.data)
            out["pose_caches"][bundle_file.path] = {
                "vertex_count": cache.vertex_count, "triangle_count": cache.triangle_count, "frame_count": cache.frame_count,
                "frames_per_second": cache.frames_per_second, "indices": cache.indices.reshape(-1).tolist(),
                "uvs": cache.uvs.reshape(-1).tolist(), "positions": cache.positions.reshape(-1).tolist(),
                "normals": cache.normals.reshape(-1).tolist(),
            }
        elif bundle_file.path.endswith(".cbtx"):
            texture = decode_texture_array(bundle_file.data)
            out["textures"][bundle_file.path] = {
                "width": texture.width, "height": texture.height, "pixel_format": texture.pixel_format,
                "layer_count": len(texture.layers), "layers_sha256": [sha256_hex(layer) for layer in texture.layers],
                "first_bytes_hex": texture.layers[0][:8].hex(),
            }
    return out


def _with_file(manifest: dict, files: list[BundleFile], path: str, data: bytes) -> tuple[dict, list[BundleFile]]:
    """The good bundle with one file's bytes replaced and the manifest updated to match them."""
    new_files = [BundleFile(f.path, data if f.path == path else f.data, f.role) for f in files]
    new_manifest = dict(manifest)
    new_manifest["files"] = [BundleFile(f.path, f.data, f.role).entry() for f in sorted(new_files, key=lambda f: f.path)]
    return new_manifest, new_files


def _write_raw(folder: Path, manifest_data: bytes, files: list[BundleFile], skip: str | None = None) -> None:
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_bytes(manifest_data)
    for bundle_file in files:
        if bundle_file.path == skip:
            continue
        (folder / bundle_file.path).parent.mkdir(parents=True, exist_ok=True)
        (folder / bundle_file.path).write_bytes(bundle_file.data)


def bad_cases(manifest: dict, files: list[BundleFile]):
    """(name, manifest bytes, files, file to leave out, expected code, file named by the error)."""
    data = {f.path: f.data for f in files}
    body = "poses/body_lod0.cbpc"
    uv = "impostor/uv.cbtx"

    def edited(path, new_bytes):
        m, fs = _with_file(manifest, files, path, new_bytes)
        return manifest_bytes(m), fs

    flipped = bytearray(data[body])
    flipped[100] ^= 0xFF
    nan_body = bytearray(data[body])
    struct.pack_into("<f", nan_body, 64 + 4 * 6 + 8 * 4, float("nan"))  # first position's x
    bad_index = bytearray(data[body])
    struct.pack_into("<I", bad_index, 64, 99)
    future_texture = bytearray(data[uv])
    struct.pack_into("<I", future_texture, 4, 2)
    odd_bc = bytearray(data["impostor/normal.cbtx"])
    struct.pack_into("<I", odd_bc, 16, 6)  # width 6 is not a multiple of 4 for bc1

    def manifest_with(**changes):
        m = json.loads(manifest_bytes(manifest))
        for key, value in changes.items():
            m[key] = value
        return manifest_bytes(m)

    escape = json.loads(manifest_bytes(manifest))
    escape["files"][0] = dict(escape["files"][0], path="../x")
    absolute = json.loads(manifest_bytes(manifest))
    absolute["files"][0] = dict(absolute["files"][0], path="/etc/passwd")
    lying_count = json.loads(manifest_bytes(manifest))
    lying_count["meshes"][0]["vertex_count"] = 5

    yield ("truncated_pose_cache", *edited(body, data[body][:-10]), None, "truncated", body)
    yield ("bad_magic", *edited(body, b"XXXX" + data[body][4:]), None, "bad_magic", body)
    yield ("future_binary_version", *edited(uv, bytes(future_texture)), None, "unsupported_version", uv)
    yield ("trailing_bytes", *edited(body, data[body] + b"\0\0\0\0"), None, "size_mismatch", body)
    yield ("index_out_of_range", *edited(body, bytes(bad_index)), None, "invalid_data", body)
    yield ("nan_position", *edited(body, bytes(nan_body)), None, "invalid_data", body)
    yield ("bc_size_not_multiple_of_4", *edited("impostor/normal.cbtx", bytes(odd_bc)), None, "invalid_header", "impostor/normal.cbtx")
    yield ("sha256_mismatch", manifest_bytes(manifest), _with_file(manifest, files, body, bytes(flipped))[1], None, "sha256_mismatch", body)
    yield ("size_mismatch", manifest_bytes(manifest), _with_file(manifest, files, body, data[body] + b"\0")[1], None, "size_mismatch", body)
    yield ("missing_file", manifest_bytes(manifest), files, uv, "missing_file", uv)
    yield ("path_escapes_bundle", manifest_bytes(escape), files, None, "unsafe_path", "../x")
    yield ("absolute_path", manifest_bytes(absolute), files, None, "unsafe_path", "/etc/passwd")
    yield ("future_format_version", manifest_with(format_version=2), files, None, "unsupported_format_version", "manifest.json")
    yield ("manifest_not_json", b'{"format": "crowdbake-bundle",', files, None, "manifest_invalid", "manifest.json")
    yield ("manifest_missing_field", manifest_with(meshes=None), files, None, "manifest_invalid", "manifest.json")
    yield ("vertex_count_disagrees", manifest_bytes(lying_count), files, None, "invalid_data", body)


def write_folder(out_dir: Path, manifest: dict, files: list[BundleFile], expected: dict, bad) -> None:
    """One vectors folder, as every v1 generator writes it: good/bundle and good/expected.json, then per
    bad case (name, manifest bytes, files, file to leave out or None, expected code, file named by the
    error) bad/NAME/bundle and bad/NAME/expect.json. Refuses a folder that exists."""
    if out_dir.exists():
        raise SystemExit(f"{out_dir} exists: vectors are never edited; a new format gets a new folder")
    write_bundle(out_dir / "good" / "bundle", manifest, files)
    (out_dir / "good" / "expected.json").write_text(json.dumps(expected, indent=1) + "\n")
    for name, manifest_data, case_files, skip, code, file in bad:
        case = out_dir / "bad" / name
        _write_raw(case / "bundle", manifest_data, case_files, skip)
        (case / "expect.json").write_text(json.dumps({"error": code, "file": file}) + "\n")


def generate(out_dir: Path) -> None:
    manifest, files = good_files()
    write_folder(out_dir, manifest, files, expected_values(manifest, files), bad_cases(manifest, files))


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "vectors" / "v1"
    generate(target)
    print(f"wrote {target}")
