"""Writes shared_formats/vectors/v1-hostile: manifests a hostile server could send, each a broken bundle
(only its manifest.json: each case fails before any listed file is read) with expect.json.

Run once; the output is committed and never edited (SPEC.md, "Vectors"). Each case is v1's good
manifest with one field changed:

* `size_2_64_minus_1`, `size_2_53`: a file size past 2^53 - 1, the largest integer every JSON reader
  holds exactly (manifest.schema.json's maximum): `manifest_invalid`. crowdview read 2^64 - 1 as 0
  (an out-of-range double-to-integer conversion), so an empty file would have matched it.
* `path_with_nul`, `path_with_terminal_escape`: a listed path holding a control character:
  `unsafe_path`, the path written with the character escaped (crowdview's message stopped at the NUL).

    python shared_formats/generate_vectors_v1_hostile.py [OUT_DIR]   # default: shared_formats/vectors/v1-hostile
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
GOOD_MANIFEST = HERE / "vectors" / "v1" / "good" / "bundle" / "manifest.json"

# case: (field of files[0] changed, its new value, expected error code, expected file)
CASES = {
    "size_2_64_minus_1": ("size", 2**64 - 1, "manifest_invalid", "manifest.json"),
    "size_2_53": ("size", 2**53, "manifest_invalid", "manifest.json"),
    "path_with_nul": ("path", "poses/body\x00.cbpc", "unsafe_path", "poses/body\\x00.cbpc"),
    "path_with_terminal_escape": ("path", "poses/\x1b[2J.cbpc", "unsafe_path", "poses/\\x1b[2J.cbpc"),
}


def main(out: Path) -> None:
    good = json.loads(GOOD_MANIFEST.read_text())
    shutil.rmtree(out / "bad", ignore_errors=True)
    for name, (key, value, code, file) in CASES.items():
        manifest = json.loads(json.dumps(good))
        manifest["files"][0][key] = value
        case = out / "bad" / name
        (case / "bundle").mkdir(parents=True)
        (case / "bundle" / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
        (case / "expect.json").write_text(json.dumps({"error": code, "file": file}) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "vectors" / "v1-hostile")
