#!/usr/bin/env python3
"""The paper's figure 3 for a mixed crowd: the largest crowd of a crowd description's archetypes (their
shares kept) that crowdview draws at 30 and at 60 fps, LOD by distance, headless.

    scripts/bench_mixed_crowd.py CROWD.json [--crowdview build/runtime/crowdview] [--out figure3.json]
        [--width 1280 --height 720] [--frames 8] [--max-seconds 600]

Each probe writes the description with `count` replaced, runs `crowdview --crowd ... --headless
--report`, and reads the median whole-frame time (cull to glFinish, after two warm-up frames).
N doubles from 8 until a target fails, then bisects to 10 %. Prints one line per probe and the
result, and writes every probe, the counts per archetype and LOD and the GPU memory per archetype
as JSON. Needs a description whose archetypes all give a share.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def probe(crowdview: str, description: dict, folder: Path, count: int, args: argparse.Namespace) -> dict:
    """One headless run of `count` characters; its report (frame_ms_median, archetypes, ...)."""
    crowd = dict(description, count=count)
    # Beside the description: its bundle folders are relative to its folder.
    path = args.crowd.parent / f".bench-crowd-{count}.json"
    path.write_text(json.dumps(crowd))
    report = folder / f"report-{count}.json"
    command = [crowdview, "--crowd", str(path), "--headless", "--frames", str(args.frames), "--width", str(args.width),
               "--height", str(args.height), "--report", str(report)] + (["--impostor-blend", args.blend] if args.blend else [])
    try:
        run = subprocess.run(command, capture_output=True, text=True)
    finally:
        path.unlink(missing_ok=True)
    if run.returncode != 0:
        raise SystemExit(f"bench_mixed_crowd: crowdview failed at N = {count}: {run.stderr.strip().splitlines()[-1:]}")
    return json.loads(report.read_text())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("crowd", type=Path)
    parser.add_argument("--crowdview", default="build/runtime/crowdview")
    parser.add_argument("--out", type=Path, default=Path("figure3_mixed.json"))
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--blend", choices=["off", "views", "frames", "full", "warp"], default=None)
    parser.add_argument("--max-seconds", type=float, default=600)
    args = parser.parse_args()
    description = json.loads(args.crowd.read_text())
    if any("share" not in a for a in description.get("archetypes", [])):
        print("bench_mixed_crowd: every archetype needs a share (the count is what the benchmark varies)", file=sys.stderr)
        return 2
    started = time.monotonic()
    probes: list[dict] = []
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench-mixed-") as tmp:
        folder = Path(tmp)
        for fps in (30, 60):
            budget_ms = 1000.0 / fps
            good, bad, n = 0, None, 8
            while time.monotonic() - started < args.max_seconds:
                report = probe(args.crowdview, description, folder, n, args)
                ms = report["frame_ms_median"]
                probes.append({"target_fps": fps, "count": n, "frame_ms_median": ms, "archetypes": report["archetypes"]})
                print(f"{fps} fps target: N = {n}: median frame {ms:.1f} ms ({1000 / max(ms, 1e-9):.1f} fps)", file=sys.stderr)
                if ms <= budget_ms:
                    good = n
                else:
                    bad = n
                if bad is None:
                    n *= 2
                elif bad - good <= max(1, good // 10):
                    break
                else:
                    n = (good + bad) // 2
            results[f"n_at_{fps}fps"] = good
        # Memory per archetype from the probe that loaded the most of them (a small N rounds some shares to none).
        last = max(probes, key=lambda p: len(p["archetypes"]), default={"archetypes": []})
    out = {"crowd": str(args.crowd), "width": args.width, "height": args.height, "frames": args.frames,
           "impostor_blend": args.blend or "warp (crowdview's default)", "seconds": round(time.monotonic() - started, 1),
           "results": results, "gpu_memory_bytes": {a["name"]: a["gpu_memory_bytes"] for a in last["archetypes"]},
           "probes": probes}
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps({"results": results, "gpu_memory_bytes": out["gpu_memory_bytes"]}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
