"""Writes shared_formats/vectors/v4: v3's bundle of two clips and two transitions with its body meshes as
skinned pose caches (CBSK), their stored arrays and skinned frames, and broken bundles (SPEC.md,
"Skinned pose cache" and "Version 4").

Run once; the output is committed and never edited. Deterministic (fixed creation time), and a test
regenerates into a temporary folder to prove the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v4.py [OUT_DIR]   # default: shared_formats/vectors/v4

Three joints: a root that sways and rises, a child that bends and grows (a scale, so normals need the
inverse transpose), and one that twists; vertices with one to four influences, weights that round.
"""
from __future__ import annotations

import importlib.util
import json
import struct
import sys
from pathlib import Path

import numpy as np

from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes
from crowdbake.formats.skinned_cache import HEADER_SIZE, decode_skinned_pose_cache, encode_skinned_pose_cache

_HERE = Path(__file__).resolve().parent


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, _HERE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


v2 = _load("generate_vectors_v2")
v3 = _load("generate_vectors_v3")

FORMAT_VERSION = 4
JOINTS = 3
# The v3 bundle's body caches, stored skinned under these names.
SKINNED = {"poses/body_lod0.cbpc": "poses/body_lod0.cbsk", "poses/body_lod1.cbpc": "poses/body_lod1.cbsk"}
# Per rest vertex (up to four of each part): joints and raw weights (normalised and coded by the writer).
INFLUENCES = [([0, 0, 0, 0], [1.0, 0.0, 0.0, 0.0]), ([0, 1, 0, 0], [0.6, 0.4, 0.0, 0.0]),
              ([0, 1, 2, 0], [0.2, 0.3, 0.5, 0.0]), ([2, 1, 0, 1], [0.1, 0.2, 0.3, 0.4])]


def _rotation(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    rotation = np.eye(3)
    rotation[i, i], rotation[i, j], rotation[j, i], rotation[j, j] = c, -s, s, c
    return rotation


def joint_matrices(frames: int) -> np.ndarray:
    """(frames, 3, 3, 4) float32: each joint's skinning matrix's top rows per frame."""
    out = np.zeros((frames, JOINTS, 3, 4))
    for f in range(frames):
        root = np.eye(4)
        root[:3, :3] = _rotation(1, 0.4 * np.sin(0.6 * f))
        root[:3, 3] = [0.1 * np.sin(0.5 * f), 0.0625 * f + 0.013, 0.05 * np.cos(0.3 * f)]
        bend = np.eye(4)
        bend[:3, :3] = _rotation(0, 0.5 * np.sin(0.9 * f + 0.3)) @ np.diag([1.0, 1.0 + 0.1 * f, 1.0])
        bend[:3, 3] = [0.0, 0.5, 0.0]
        twist = np.eye(4)
        twist[:3, :3] = _rotation(2, 0.7 * np.cos(0.4 * f))
        twist[:3, 3] = [0.2, 0.1 * np.sin(f), -0.1]
        for joint, matrix in enumerate((root, root @ bend, root @ bend @ twist)):
            out[f, joint] = matrix[:3]
    return out.astype(np.float32)


def _skinned_cache(v3_path: str) -> bytes:
    (faces, base, uvs), _phase = v3.PARTS[v3_path]
    rest_normals = np.tile(np.float32([0.0, 0.0, 1.0]), (len(base), 1))
    rest_normals[1] = np.float32([0.6, 0.0, 0.8])
    joints = np.array([INFLUENCES[k][0] for k in range(len(base))])
    weights = np.array([INFLUENCES[k][1] for k in range(len(base))])
    return encode_skinned_pose_cache(faces, uvs, base, rest_normals, joints, weights, joint_matrices(v2.POSE_FRAMES), v2.FPS)


def good_files() -> tuple[dict, list[BundleFile]]:
    v3_manifest, v3_files = v3.good_files()
    files = [BundleFile(SKINNED[f.path], _skinned_cache(f.path), f.role) if f.path in SKINNED else f for f in v3_files]
    sections = {key: v3_manifest[key] for key in ("frames_per_second", "pose_frames", "clips", "transitions", "materials", "outfits", "impostor")}
    sections["meshes"] = [dict(mesh, file=SKINNED.get(mesh["file"], mesh["file"])) for mesh in v3_manifest["meshes"]]
    return build_manifest("vector-skinned", "4.0.0", sections, files, created=v2.CREATED, format_version=FORMAT_VERSION), files


def expected_values(manifest: dict, files: list[BundleFile]) -> dict:
    """What a reader must decode: per CBSK its header counts, stored arrays and skinned frames."""
    skinned = {}
    for bundle_file in files:
        if bundle_file.path in SKINNED.values():
            cache = decode_skinned_pose_cache(bundle_file.data, bundle_file.path)
            bounds = struct.unpack_from("<3f3f", bundle_file.data, 36)
            skinned[bundle_file.path] = {
                "vertex_count": cache.vertex_count, "index_count": 3 * cache.triangle_count, "frame_count": cache.frame_count,
                "joint_count": cache.joint_count, "frames_per_second": cache.frames_per_second,
                "bounds_min": list(bounds[:3]), "bounds_max": list(bounds[3:]),
                "joints": cache.joints.tolist(), "weight_codes": cache.weight_codes.tolist(),
                "matrices": cache.matrices.reshape(cache.frame_count, cache.joint_count, 12).tolist(),
                "positions": cache.positions.tolist(), "normals": cache.normals.tolist()}
    return {"name": manifest["name"], "version": manifest["version"], "format_version": FORMAT_VERSION, "skinned": skinned}


def bad_cases(manifest: dict, files: list[BundleFile]):
    """(name, manifest bytes, files, expected code, file named by the error)."""
    body = "poses/body_lod0.cbsk"
    data = next(f.data for f in files if f.path == body)
    vertex_count, index_count, frame_count, joint_count = struct.unpack_from("<4I", data, 16)
    joints_at = HEADER_SIZE + 4 * index_count + 32 * vertex_count
    weights_at = joints_at + 8 * vertex_count
    matrices_at = weights_at + 8 * vertex_count

    def broken(name: str, new_data: bytes, code: str):
        return (name, *v3._with_file(manifest, files, body, new_data), code, body)

    yield broken("truncated_skinned_cache", data[:-4], "truncated")
    yield broken("future_skinned_cache_version", v3._patched(data, 4, "<I", 2), "unsupported_version")
    yield broken("joint_count_zero", v3._patched(data, 28, "<I", 0), "invalid_header")
    yield broken("skinned_counts_disagree", v3._patched(data, 16, "<I", vertex_count + 1), "size_mismatch")
    yield broken("joint_out_of_range", v3._patched(data, joints_at + 8 * 2 + 2, "<H", joint_count), "invalid_data")
    yield broken("weights_do_not_sum", v3._patched(data, weights_at + 8 * 1, "<H", 40000), "invalid_data")
    yield broken("matrix_nan", v3._patched(data, matrices_at + 4 * (12 * (joint_count + 1) + 5), "<f", float("nan")), "invalid_data")
    # Joint 1 (weighted by vertices 1 to 3) collapsed at frame 2: its 3 x 3 block all zeros.
    yield broken("matrix_singular", v3._patched(data, matrices_at + 4 * 12 * (2 * joint_count + 1), "<3f4x3f4x3f", *([0.0] * 9)), "invalid_data")
    yield broken("bounds_miss_a_position", v3._patched(data, 48, "<f", struct.unpack_from("<f", data, 48)[0] - 0.05), "invalid_data")
    garment = json.loads(manifest_bytes(manifest))
    garment["meshes"] = [dict(mesh, kind="garment") if mesh["file"] == body else mesh for mesh in garment["meshes"]]
    yield ("skinned_garment", manifest_bytes(garment), files, "invalid_data", body)
    as_v3 = json.loads(manifest_bytes(manifest))
    as_v3["format_version"] = 3
    yield ("skinned_cache_in_v3", manifest_bytes(as_v3), files, "invalid_data", body)
    future = json.loads(manifest_bytes(manifest))
    future["format_version"] = 5
    yield ("future_format_version", manifest_bytes(future), files, "unsupported_format_version", "manifest.json")


def generate(out_dir: Path) -> None:
    v3.write_vectors(out_dir, good_files, expected_values, bad_cases)


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else _HERE / "vectors" / "v4"
    generate(target)
    print(f"wrote {target}")
