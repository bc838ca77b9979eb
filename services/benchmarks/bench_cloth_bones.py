"""Cloth as bones: RMS and maximum error against the loop, seconds and bytes, for a sweep of bone counts.

Decomposes each bundle's LOD 0 garment loop (crowdbake.export.cloth_bones, Dem Bones, 4 influences) with
each bone count, prints a row per case and count, writes them as JSON and, with --plot, the figure of
docs/export.md "Cloth as bones".

    PYTHONPATH=services python services/benchmarks/bench_cloth_bones.py \\
        sample=out/demo/bundles/sample-walker/1.0.0 long_skirt=out/demo/bundles/cesiumman/1.0.0 \\
        --bones 4 8 16 32 64 128 --out out/bench/cloth_bones.json --plot docs/img/cloth_bones.png

(The bundles are scripts/demo.sh's: the procedural sample, and CesiumMan in the shared long skirt.)
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from crowdbake.export.cloth_bones import DEFAULT_ITERATIONS, decompose_cloth
from crowdbake.export.writer import ClothBonesRequest, bones_entry
from crowdbake.formats.bundle import verify_bundle


def sweep(name: str, bundle_dir: Path, counts: list[int], iterations: int) -> list[dict]:
    bundle = verify_bundle(bundle_dir)
    mesh = next(m for m in bundle.manifest["meshes"] if m["kind"] == "garment" and m["lod"] == 0)
    cache = bundle.pose_caches[mesh["file"]]
    rows = []
    for count in counts:
        start = time.perf_counter()
        bones = decompose_cloth(cache.positions, cache.indices, count, iterations)
        seconds = time.perf_counter() - start
        entry = bones_entry(bones, ClothBonesRequest(count, iterations=iterations), cache.vertex_count, cache.frame_count)
        rows.append({"case": name, "garment": mesh["part"], "vertices": cache.vertex_count, "frames": cache.frame_count, "bones": count,
                     "rms_mm": entry["rms_mm"], "max_mm": entry["max_mm"], "bytes": entry["bytes"],
                     "morph_target_bytes": cache.vertex_count * (cache.frame_count - 1) * 12, "seconds": round(seconds, 2)})
        print(f"{name:12s} {count:4d} bones  RMS {entry['rms_mm']:7.2f} mm  max {entry['max_mm']:7.1f} mm  {entry['bytes']:9,d} bytes  {seconds:6.1f} s", flush=True)
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6.4, 4.0))
    for case in dict.fromkeys(row["case"] for row in rows):
        mine = [row for row in rows if row["case"] == case]
        label = f"{case} ({mine[0]['vertices']} vertices, {mine[0]['frames']} frames)"
        line, = axis.plot([r["bones"] for r in mine], [r["rms_mm"] for r in mine], "o-", label=f"{label}: RMS")
        axis.plot([r["bones"] for r in mine], [r["max_mm"] for r in mine], "s--", color=line.get_color(), alpha=0.6, label=f"{case}: max")
    axis.set_xscale("log", base=2)
    axis.set_yscale("log")
    axis.set_xlabel("bones")
    axis.set_ylabel("error against the loop (mm)")
    axis.set_title("Cloth as bones (Dem Bones, 4 influences)")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cases", nargs="+", metavar="NAME=BUNDLE")
    parser.add_argument("--bones", nargs="+", type=int, default=[4, 8, 16, 32, 64, 128])
    parser.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS)
    parser.add_argument("--out", type=Path, default=Path("out/bench/cloth_bones.json"))
    parser.add_argument("--plot", type=Path)
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in args.cases:
        name, _, folder = case.partition("=")
        rows += sweep(name, Path(folder), args.bones, args.iterations)
        args.out.write_text(json.dumps(rows, indent=2) + "\n")  # as it goes: the long skirt's sweep takes minutes
    if args.plot:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
