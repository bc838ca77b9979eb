"""Writes shared_formats/vectors/v3: v2's bundle of two clips and two transitions with quantized pose caches
(CBPC version 2), their stored codes and decoded values, and broken bundles (SPEC.md, "Version 3").

Run once; the output is committed and never edited. Deterministic (fixed creation time), and a test
regenerates into a temporary folder to prove the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v3.py [OUT_DIR]   # default: shared_formats/vectors/v3

The parts sway and tilt, so codes fall between grid points and normals leave the axes, and every frame
has bounds of its own.
"""
from __future__ import annotations

import importlib.util
import json
import struct
import sys
from pathlib import Path

import numpy as np

from crowdbake.formats.binary import decode_pose_cache, encode_pose_cache, encode_quantized_pose_cache
from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes

_V2_SPEC = importlib.util.spec_from_file_location("generate_vectors_v2", Path(__file__).resolve().parent / "generate_vectors_v2.py")
v2 = importlib.util.module_from_spec(_V2_SPEC)
_V2_SPEC.loader.exec_module(v2)

FORMAT_VERSION = 3
POSE_HEADER = 64


def _swaying(base: np.ndarray, frames: int, phase: float) -> tuple[np.ndarray, np.ndarray]:
    """`base` (n, 3) swaying and rising over `frames`: (frames, n, 3) positions and unit normals tilted per
    vertex and frame."""
    positions, normals = [], []
    for f in range(frames):
        angle = 0.3 * np.sin(0.7 * f + phase)
        offset = np.float32([0.1 * np.sin(0.5 * f + phase), 0.0625 * f + 0.013, 0.05 * np.cos(0.3 * f)])
        positions.append(base + offset + np.float32([0.0, 0.0, 0.02]) * np.arange(len(base))[:, None])
        tilt = np.stack([np.full(len(base), np.sin(angle)), 0.2 * np.arange(len(base)) - 0.3, np.full(len(base), np.cos(angle))], axis=1)
        if f % 3 == 2:
            tilt[:, 2] *= -1  # facing away: the octahedron's folded half
        normals.append(tilt / np.linalg.norm(tilt, axis=1, keepdims=True))
    return np.stack(positions).astype(np.float32), np.stack(normals).astype(np.float32)


QUAD = (np.array([[0, 1, 2], [0, 2, 3]], np.uint32), np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.5, 1.0, 0.0], [-0.5, 1.0, 0.0]], np.float32),
        np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]], np.float32))
TRIANGLE = (np.array([[0, 1, 2]], np.uint32), np.array([[-0.25, 0.25, 0.0], [0.25, 0.25, 0.0], [0.0, 0.75, 0.0]], np.float32),
            np.array([[0.25, 0.75], [0.75, 0.75], [0.5, 0.25]], np.float32))
PARTS = {"poses/body_lod0.cbpc": (QUAD, 0.0), "poses/body_lod1.cbpc": (TRIANGLE, 0.5), "poses/cape_lod0.cbpc": (TRIANGLE, 1.5)}


def _pose_cache(path: str, frames: int = v2.POSE_FRAMES, encode=encode_quantized_pose_cache) -> bytes:
    (faces, base, uvs), phase = PARTS[path]
    return encode(faces, uvs, *_swaying(base, frames, phase), v2.FPS)


def good_files() -> tuple[dict, list[BundleFile]]:
    v2_manifest, v2_files = v2.good_files()
    files = [BundleFile(f.path, _pose_cache(f.path), f.role) if f.path in PARTS else f for f in v2_files]
    sections = {key: v2_manifest[key] for key in ("frames_per_second", "pose_frames", "clips", "transitions", "materials", "outfits",
                                                  "meshes", "impostor")}
    return build_manifest("vector-quantized", "3.0.0", sections, files, created=v2.CREATED, format_version=FORMAT_VERSION), files


def _stored(data: bytes) -> dict:
    """A CBPC version 2 file's stored frame sections, read straight from its bytes (SPEC.md byte layout)."""
    vertex_count, index_count, frame_count = struct.unpack_from("<III", data, 16)
    offset = POSE_HEADER + 4 * index_count + 8 * vertex_count
    bounds = np.frombuffer(data, "<f4", 6 * frame_count, offset)
    offset += 24 * frame_count
    normal_codes = np.frombuffer(data, "<u2", 2 * vertex_count * frame_count, offset)
    offset += 4 * vertex_count * frame_count
    position_codes = np.frombuffer(data, "<u2", 3 * vertex_count * frame_count, offset)
    return {"frame_bounds": bounds.tolist(), "normal_codes": normal_codes.tolist(), "position_codes": position_codes.tolist()}


def expected_values(manifest: dict, files: list[BundleFile]) -> dict:
    """What a reader must decode: the ranges (as v2's), and per pose cache its codes and decoded frames."""
    caches = {}
    for bundle_file in files:
        if bundle_file.path in PARTS:
            cache = decode_pose_cache(bundle_file.data, bundle_file.path)
            caches[bundle_file.path] = {"version": 2, "vertex_count": cache.vertex_count, "frame_count": cache.frame_count,
                                        "positions": cache.positions.reshape(-1).tolist(), "normals": cache.normals.reshape(-1).tolist(),
                                        **_stored(bundle_file.data)}
    return {"name": manifest["name"], "version": manifest["version"], "format_version": FORMAT_VERSION,
            "pose_frames": v2.POSE_FRAMES, "clips": v2.CLIPS, "transitions": v2.TRANSITIONS, "pose_caches": caches}


def _with_file(manifest: dict, files: list[BundleFile], path: str, data: bytes) -> tuple[bytes, list[BundleFile]]:
    """The bundle with `path` replaced by `data`, listed with its true size and hash (so only its content is wrong)."""
    changed = [BundleFile(f.path, data if f.path == path else f.data, f.role) for f in files]
    return manifest_bytes(dict(manifest, files=[f.entry() for f in sorted(changed, key=lambda f: f.path)])), changed


def _patched(data: bytes, offset: int, fmt: str, *values) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, *values)
    return bytes(out)


def bad_cases(manifest: dict, files: list[BundleFile]):
    """(name, manifest bytes, files, expected code, file named by the error)."""
    body = "poses/body_lod0.cbpc"
    data = next(f.data for f in files if f.path == body)
    frame_bounds = POSE_HEADER + 4 * 6 + 8 * 4  # the quad: 6 indices, 4 vertices

    def broken(name: str, new_data: bytes, code: str):
        return (name, *_with_file(manifest, files, body, new_data), code, body)

    yield broken("truncated_pose_cache", data[:-2], "truncated")
    yield broken("future_pose_cache_version", _patched(data, 4, "<I", 3), "unsupported_version")
    yield broken("pose_cache_counts_disagree", _patched(data, 16, "<I", 5), "size_mismatch")
    yield broken("frame_bounds_inverted", _patched(data, frame_bounds, "<f", 0.75), "invalid_data")  # frame 0: min x above max x
    yield broken("frame_bounds_outside_header", _patched(data, frame_bounds + 12, "<f", 9.0), "invalid_data")
    yield broken("frame_bounds_nan", _patched(data, frame_bounds + 24 * 3 + 4, "<f", float("nan")), "invalid_data")
    yield broken("header_bounds_nan", _patched(data, 40, "<f", float("nan")), "invalid_data")
    yield broken("float_pose_cache_in_v3", _pose_cache(body, encode=encode_pose_cache), "invalid_data")
    as_v2 = json.loads(manifest_bytes(manifest))
    as_v2["format_version"] = 2
    yield ("quantized_pose_cache_in_v2", manifest_bytes(as_v2), files, "invalid_data", body)
    future = json.loads(manifest_bytes(manifest))
    future["format_version"] = 4
    yield ("future_format_version", manifest_bytes(future), files, "unsupported_format_version", "manifest.json")


def write_vectors(out_dir: Path, good, expected, cases) -> None:
    """A vectors folder: good/ (bundle and expected.json) and bad/<case>/ (bundle and expect.json), from a
    generator's good_files(), expected_values(manifest, files) and bad_cases(manifest, files)."""
    if out_dir.exists():
        raise SystemExit(f"{out_dir} exists: vectors are never edited; a new format version gets a new folder")
    manifest, files = good()
    v2._write_raw(out_dir / "good" / "bundle", manifest_bytes(manifest), files)
    (out_dir / "good" / "expected.json").write_text(json.dumps(expected(manifest, files), indent=1) + "\n")
    for name, manifest_data, case_files, code, file in cases(manifest, files):
        case = out_dir / "bad" / name
        v2._write_raw(case / "bundle", manifest_data, case_files)
        (case / "expect.json").write_text(json.dumps({"error": code, "file": file}) + "\n")


def generate(out_dir: Path) -> None:
    write_vectors(out_dir, good_files, expected_values, bad_cases)


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "vectors" / "v3"
    generate(target)
    print(f"wrote {target}")
