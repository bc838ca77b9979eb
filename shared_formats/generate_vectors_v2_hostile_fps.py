"""Writes shared_formats/vectors/v2-hostile-fps: v2's good bundle at other frame rates (SPEC.md
"manifest.json", `frames_per_second`).

Run once; the output is committed and never edited (SPEC.md, "Vectors"). A bundle whose manifest said
1e300 frames a second over pose caches at 24 verified in both readers, and every clip then lasted no
time at all: a crowd of 20,000 with `switch_after_s [0, 0]` drew 30 frames in 559 s. Cases:

* `good/`: every frame rate 1000, the largest allowed (the manifest and each CBPC header).
* `bad/fps_1e300`: the manifest says 1e300, the pose caches 24: `manifest_invalid`.
* `bad/fps_below_one`, `bad/fps_above_1000`: 0.5 and 1000.5, the pose caches alike: `manifest_invalid`.
* `bad/pose_cache_fps_differs`: the manifest says 30, the pose caches 24: `invalid_data`, the first mesh's CBPC.

Standard library only: the bytes are v2's good bundle with the frame rates patched and the manifest's
sizes and sha256 written again.

    python shared_formats/generate_vectors_v2_hostile_fps.py [OUT_DIR]   # default: shared_formats/vectors/v2-hostile-fps
"""
from __future__ import annotations

import hashlib
import json
import shutil
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
GOOD = HERE / "vectors" / "v2" / "good" / "bundle"
CBPC_FPS_OFFSET = 32  # SPEC.md "Pose cache": f32 frames_per_second

# case: (the manifest's frames_per_second, the pose caches' (None: as v2's good bundle), expected code, expected file)
BAD_CASES = {
    "fps_1e300": (1e300, None, "manifest_invalid", "manifest.json"),
    "fps_below_one": (0.5, 0.5, "manifest_invalid", "manifest.json"),
    "fps_above_1000": (1000.5, 1000.5, "manifest_invalid", "manifest.json"),
    "pose_cache_fps_differs": (30.0, None, "invalid_data", "poses/body_lod0.cbpc"),
}
GOOD_FPS = 1000.0


def write_bundle(out: Path, manifest_fps: float, cache_fps: float | None) -> None:
    """v2's good bundle into `out` with the manifest at `manifest_fps` and every CBPC at `cache_fps`."""
    manifest = json.loads((GOOD / "manifest.json").read_text())
    manifest["frames_per_second"] = manifest_fps
    shutil.copytree(GOOD, out)
    for entry in manifest["files"]:
        if entry["role"] != "pose-cache" or cache_fps is None:
            continue
        data = bytearray((GOOD / entry["path"]).read_bytes())
        struct.pack_into("<f", data, CBPC_FPS_OFFSET, cache_fps)
        (out / entry["path"]).write_bytes(bytes(data))
        entry["size"], entry["sha256"] = len(data), hashlib.sha256(data).hexdigest()
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")


def main(out: Path) -> None:
    shutil.rmtree(out / "good", ignore_errors=True)
    shutil.rmtree(out / "bad", ignore_errors=True)
    write_bundle(out / "good" / "bundle", GOOD_FPS, GOOD_FPS)
    (out / "good" / "expected.json").write_text(json.dumps({"frames_per_second": GOOD_FPS}) + "\n")
    for name, (manifest_fps, cache_fps, code, file) in BAD_CASES.items():
        write_bundle(out / "bad" / name / "bundle", manifest_fps, cache_fps)
        (out / "bad" / name / "expect.json").write_text(json.dumps({"error": code, "file": file}) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "vectors" / "v2-hostile-fps")
