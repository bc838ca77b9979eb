"""Writes shared_formats/vectors/v2: a tiny bundle of two clips and two transitions, its decoded ranges,
and broken bundles (SPEC.md, "Version 2: clips and transitions").

Run once; the output is committed and never edited. Deterministic (fixed creation time), and a test
regenerates into a temporary folder to prove the Python writer still produces these exact bytes.

    python shared_formats/generate_vectors_v2.py [OUT_DIR]   # default: shared_formats/vectors/v2

The good bundle's 11 pose frames, clips then transitions:

    clip a [0, 4)  baked 0, 2     clip b [4, 6)  baked 4
    a -> b [6, 8)  baked 6, 7     b -> a [8, 11) baked 8, 10 (its ends; no frame between is needed)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from crowdbake.formats.binary import encode_pose_cache, encode_texture_array
from crowdbake.formats.bundle import BundleFile, build_manifest, manifest_bytes, write_bundle

CREATED = "2026-01-01T00:00:00Z"
POSE_FRAMES = 11
FPS = 24.0
FRAME_INDICES = [0, 2, 4, 6, 7, 8, 10]
CLIPS = [
    {"name": "a", "first_frame": 0, "frames": 4, "source_start_frame": 10, "source_end_frame": 14, "closing": "crossfade",
     "position_jump_ratio": 0.5, "velocity_jump_ratio": 0.25},
    {"name": "b", "first_frame": 4, "frames": 2, "source_start_frame": 30, "source_end_frame": 32, "closing": "none",
     "position_jump_ratio": 0.75, "velocity_jump_ratio": 1.25},
]
TRANSITIONS = [
    {"from_clip": 0, "to_clip": 1, "leave_frame": 3, "arrive_frame": 1, "first_frame": 6, "frames": 2,
     "source_start_frame": 20, "source_end_frame": 22, "position_jump_ratio": 1.0, "velocity_jump_ratio": 0.5},
    {"from_clip": 1, "to_clip": 0, "leave_frame": 0, "arrive_frame": 2, "first_frame": 8, "frames": 3,
     "source_start_frame": 40, "source_end_frame": 43, "position_jump_ratio": 0.25, "velocity_jump_ratio": 1.5},
]


def _part_frames(base: np.ndarray, frames: int, step: float) -> tuple[np.ndarray, np.ndarray]:
    """`base` (n, 3) rising `step` metres per pose frame: (frames, n, 3) positions and +Z normals."""
    positions = np.stack([base + np.float32([0.0, step * f, 0.0]) for f in range(frames)]).astype(np.float32)
    return positions, np.tile(np.float32([0.0, 0.0, 1.0]), (frames, len(base), 1))


def _quad(frames: int) -> bytes:
    base = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.5, 1.0, 0.0], [-0.5, 1.0, 0.0]], np.float32)
    uvs = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]], np.float32)
    return encode_pose_cache(np.array([[0, 1, 2], [0, 2, 3]], np.uint32), uvs, *_part_frames(base, frames, 0.125), FPS)


def _triangle(frames: int, z: float) -> bytes:
    base = np.array([[-0.25, 0.25, z], [0.25, 0.25, z], [0.0, 0.75, z]], np.float32)
    uvs = np.array([[0.25, 0.75], [0.75, 0.75], [0.5, 0.25]], np.float32)
    return encode_pose_cache(np.array([[0, 1, 2]], np.uint32), uvs, *_part_frames(base, frames, 0.0625), FPS)


def _bc_blocks(count: int, block_size: int, seed: int) -> bytes:
    """Deterministic BC blocks: the format only fixes their size, so any bytes are valid blocks."""
    return bytes((seed * 31 + i * 7) % 256 for i in range(count * block_size))


def good_files() -> tuple[dict, list[BundleFile]]:
    layers = len(FRAME_INDICES)
    files = [
        BundleFile("poses/body_lod0.cbpc", _quad(POSE_FRAMES), "pose-cache"),
        BundleFile("poses/body_lod1.cbpc", _triangle(POSE_FRAMES, 0.0), "pose-cache"),
        BundleFile("poses/cape_lod0.cbpc", _triangle(POSE_FRAMES, 0.1), "pose-cache"),
        BundleFile("textures/diffuse.cbtx", encode_texture_array(4, 4, "bc2", [_bc_blocks(1, 16, 1)]), "diffuse"),
        BundleFile("textures/outfits.cbtx", encode_texture_array(16, 1, "rgba8", np.arange(16 * 4, dtype=np.uint8).reshape(1, 1, 16, 4) * 3), "outfit-colours"),
        # Impostor atlases: tile 4, two azimuths, one elevation -> 8x4, one layer per baked pose frame.
        BundleFile("impostor/normal.cbtx", encode_texture_array(8, 4, "bc1", [_bc_blocks(2, 8, 3 + k) for k in range(layers)]), "impostor-normal"),
        BundleFile("impostor/uv.cbtx", encode_texture_array(8, 4, "uv32", ((np.arange(layers * 4 * 8, dtype=np.uint64).reshape(layers, 4, 8) * 2654435761) % 2**32).astype(np.uint32)), "impostor-uv"),
        BundleFile("cycle/cycle.json", b'{"clips": 2, "transitions": 2}\n', "cycle"),
    ]
    sections = {
        "frames_per_second": FPS,
        "pose_frames": POSE_FRAMES,
        "clips": CLIPS,
        "transitions": TRANSITIONS,
        "materials": [{"name": "outfit", "diffuse": "textures/diffuse.cbtx", "variations": 1}],
        "outfits": {"file": "textures/outfits.cbtx", "count": 1, "regions": 16},
        "meshes": [
            {"part": "body", "kind": "body", "lod": 0, "file": "poses/body_lod0.cbpc", "material": 0, "vertex_count": 4, "triangle_count": 2},
            {"part": "body", "kind": "body", "lod": 1, "file": "poses/body_lod1.cbpc", "material": 0, "vertex_count": 3, "triangle_count": 1},
            {"part": "cape", "kind": "garment", "lod": 0, "file": "poses/cape_lod0.cbpc", "material": 0, "vertex_count": 3, "triangle_count": 1},
        ],
        "impostor": {"tile_size": 4, "azimuths_deg": [0.0, 180.0], "elevations_deg": [0.0], "frame_indices": FRAME_INDICES,
                     "bounds": {"center": [0.0, 0.5, 0.0], "radius": 1.0},
                     "maps": {"normal": "impostor/normal.cbtx", "uv": "impostor/uv.cbtx"}},
    }
    manifest = build_manifest("vector-clips", "2.0.0", sections, files, created=CREATED, format_version=2)
    return manifest, files


def expected_values(manifest: dict) -> dict:
    """What a reader must decode from the good bundle's manifest: its ranges and baked frames."""
    return {"name": manifest["name"], "version": manifest["version"], "format_version": 2, "frames_per_second": FPS,
            "pose_frames": POSE_FRAMES, "clips": CLIPS, "transitions": TRANSITIONS, "frame_indices": FRAME_INDICES,
            "pose_cache_frame_count": {path: POSE_FRAMES for path in ("poses/body_lod0.cbpc", "poses/body_lod1.cbpc", "poses/cape_lod0.cbpc")}}


def _write_raw(folder: Path, manifest_data: bytes, files: list[BundleFile]) -> None:
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_bytes(manifest_data)
    for bundle_file in files:
        (folder / bundle_file.path).parent.mkdir(parents=True, exist_ok=True)
        (folder / bundle_file.path).write_bytes(bundle_file.data)


def bad_cases(manifest: dict, files: list[BundleFile]):
    """(name, manifest bytes, files, expected code, file named by the error)."""

    def edited(change) -> bytes:
        copy = json.loads(manifest_bytes(manifest))
        change(copy)
        return manifest_bytes(copy)

    def set_in(*path_and_value):
        *path, key, value = path_and_value

        def change(m):
            target = m
            for step in path:
                target = target[step]
            target[key] = value
        return change

    def add_cycle(m):
        m["cycle"] = {"source_start_frame": 10, "source_end_frame": 21, "frames": POSE_FRAMES, "closing": "none",
                      "position_jump_ratio": 0.5, "velocity_jump_ratio": 0.25}

    # A CBPC of 12 frames where the manifest says 11 pose frames: listed with its true size and hash.
    long_cape = _triangle(POSE_FRAMES + 1, 0.1)
    cape = "poses/cape_lod0.cbpc"
    long_files = [BundleFile(f.path, long_cape if f.path == cape else f.data, f.role) for f in files]
    long_manifest = dict(manifest, files=[f.entry() for f in sorted(long_files, key=lambda f: f.path)])

    m = "manifest.json"
    yield ("ranges_do_not_tile", edited(set_in("transitions", 0, "first_frame", 7)), files, "manifest_invalid", m)
    yield ("ranges_end_before_pose_frames", edited(set_in("pose_frames", 12)), files, "manifest_invalid", m)
    yield ("transition_clip_out_of_range", edited(set_in("transitions", 1, "to_clip", 2)), files, "manifest_invalid", m)
    yield ("transition_to_its_own_clip", edited(set_in("transitions", 0, "to_clip", 0)), files, "manifest_invalid", m)
    yield ("leave_frame_past_clip", edited(set_in("transitions", 0, "leave_frame", 4)), files, "manifest_invalid", m)
    yield ("arrive_frame_past_clip", edited(set_in("transitions", 0, "arrive_frame", 2)), files, "manifest_invalid", m)
    yield ("duplicate_clip_names", edited(set_in("clips", 1, "name", "a")), files, "manifest_invalid", m)
    yield ("cycle_key_in_v2", edited(add_cycle), files, "manifest_invalid", m)
    yield ("clips_missing", edited(lambda c: c.pop("clips")), files, "manifest_invalid", m)
    yield ("pose_cache_frames_differ", manifest_bytes(long_manifest), long_files, "invalid_data", cape)
    # Same layer count as the atlases, so only the range rule breaks: 10 (the last of b -> a) becomes 9.
    yield ("transition_end_not_baked", edited(set_in("impostor", "frame_indices", [0, 2, 4, 6, 7, 8, 9])), files, "invalid_data", m)
    yield ("transition_start_not_baked", edited(set_in("impostor", "frame_indices", [0, 2, 4, 5, 7, 8, 10])), files, "invalid_data", m)
    yield ("clip_without_baked_frame", edited(set_in("impostor", "frame_indices", [0, 2, 3, 6, 7, 8, 10])), files, "invalid_data", m)
    yield ("future_format_version", edited(set_in("format_version", 3)), files, "unsupported_format_version", m)


def generate(out_dir: Path) -> None:
    if out_dir.exists():
        raise SystemExit(f"{out_dir} exists: vectors are never edited; a new format version gets a new folder")
    manifest, files = good_files()
    write_bundle(out_dir / "good" / "bundle", manifest, files)
    (out_dir / "good" / "expected.json").write_text(json.dumps(expected_values(manifest), indent=1) + "\n")
    for name, manifest_data, case_files, code, file in bad_cases(manifest, files):
        case = out_dir / "bad" / name
        _write_raw(case / "bundle", manifest_data, case_files)
        (case / "expect.json").write_text(json.dumps({"error": code, "file": file}) + "\n")


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "vectors" / "v2"
    generate(target)
    print(f"wrote {target}")
