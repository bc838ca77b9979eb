"""What each file of an export costs: bytes unpacked and inside the published export.zip.

Exports a bundle the way publishing does (crowdbake.storage.exports.build_export: export/, export.zip,
index.json) and prints, then writes as JSON, per file its bytes and its compressed bytes in the zip,
largest first, with the totals.

    PYTHONPATH=services python services/benchmarks/bench_export_weight.py BUNDLE [--out weight.json]

BUNDLE: a bundle folder, e.g. the demo's sample (`scripts/demo.sh`: out/demo/bundles/sample-walker/1.0.0,
the procedural sample baked with the default parameters).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
import zipfile
from pathlib import Path

from crowdbake.storage.exports import FILES_FOLDER, ZIP_NAME, build_export


def export_weight(bundle: Path) -> dict:
    """{"files": [{path, bytes, zipped}], "total_bytes", "zip_bytes", "seconds"} of the bundle's export."""
    with tempfile.TemporaryDirectory() as tmp:
        staging = Path(tmp)
        start = time.perf_counter()
        build_export(bundle, staging)
        seconds = time.perf_counter() - start
        with zipfile.ZipFile(staging / ZIP_NAME) as archive:
            zipped = {info.filename.split("/", 1)[1]: info.compress_size for info in archive.infolist()}
        files = [{"path": path, "bytes": (staging / FILES_FOLDER / path).stat().st_size, "zipped": zipped[path]} for path in zipped]
        files.sort(key=lambda row: -row["zipped"])
        return {"bundle": str(bundle), "files": files, "total_bytes": sum(r["bytes"] for r in files),
                "zip_bytes": (staging / ZIP_NAME).stat().st_size, "seconds": round(seconds, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bundle", type=Path)
    parser.add_argument("--out", type=Path, default=Path("export_weight.json"))
    args = parser.parse_args()
    result = export_weight(args.bundle)
    print(f"{'file':48s} {'bytes':>12s} {'in zip':>12s}")
    for row in result["files"]:
        print(f"{row['path']:48s} {row['bytes']:12,d} {row['zipped']:12,d}")
    print(f"{'total':48s} {result['total_bytes']:12,d} {result['zip_bytes']:12,d}  (export.zip; {result['seconds']} s)")
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
