"""Do switches of clip pop? crowdview's switch figure for a bundle of several clips, per representation.

    PYTHONPATH=services python services/benchmarks/bench_clip_switches.py [--bundle DIR | --bake-robot ARGS...]
        [--count 21] [--frames 900] [--switch-after 0.5,1.5] [--blends frames,warp]

Runs crowdview headless on a format-2 bundle once per representation (`--lod high`, `low`, `impostor`)
and impostor blend, every character switching clip every 0.5-1.5 s, and reads `--report`'s
`switch_jumps`: the largest screen-space jump of a character at a switch against the median per-frame
motion inside the clips it joins (runtime/README.md "Clips and switches"; the target is <= 1.5), and the
same against what the clip itself moves at that phase ("same phase"), and where the worst switch was.
Without --bundle it bakes ../shared/assets/robot_clips first (the bake's defaults, or the bake options
after --bake-robot). Prints a table and writes out/bench/clip_switches.json.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CROWDVIEW = Path(os.environ.get("CROWDVIEW", REPO / "build" / "runtime" / "crowdview"))
REPRESENTATIONS = ("high", "low", "impostor")
TARGET = 1.5


def bake_robot(assets: Path, out: Path, options: list[str]) -> Path:
    """The robot_clips bundle baked with `options` (bake CLI flags) into out/robot/1; its folder."""
    robot = assets / "robot_clips"
    command = [sys.executable, "-m", "crowdbake", "bake", str(robot / "robot.glb"), "--cloth", str(robot / "garment.pc2"),
               "--cloth-mesh", str(robot / "garment.obj"), "--timeline", str(robot / "timeline.json"), "--name", "robot",
               "--version", "1", "--no-export", "--out", str(out), *options]
    subprocess.run(command, check=True, env={**os.environ, "PYTHONPATH": str(REPO / "services")}, stdout=subprocess.DEVNULL)
    return out / "robot" / "1"


def switch_figures(bundle: Path, lod: str, blend: str, args) -> dict:
    """One headless crowdview run at `lod` and `blend`: its report's switch figures for that representation."""
    with tempfile.TemporaryDirectory() as scratch:
        report = Path(scratch) / "report.json"
        subprocess.run([str(CROWDVIEW), "--bundle", str(bundle), "--headless", "--lod", lod, "--impostor-blend", blend,
                        "--count", str(args.count), "--frames", str(args.frames), "--switch-after", args.switch_after,
                        "--width", "320", "--height", "240", "--report", str(report)],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        archetype = json.loads(report.read_text())["archetypes"][0]
    figures = archetype["switch_jumps"][lod]
    return {**figures, "characters_switched": archetype["clips"]["characters_switched"], "characters": archetype["characters"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bundle", type=Path, help="a format-2 bundle folder (default: bake robot_clips)")
    parser.add_argument("--assets", type=Path, default=REPO.parent / "shared" / "assets")
    parser.add_argument("--count", type=int, default=21)
    parser.add_argument("--frames", type=int, default=900)
    parser.add_argument("--switch-after", default="0.5,1.5")
    parser.add_argument("--blends", default="frames,warp", help="impostor blends to measure (crowdview --impostor-blend)")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench" / "clip_switches.json")
    parser.add_argument("--bake-robot", nargs=argparse.REMAINDER, default=[], help="bake options for the robot (the rest of the line)")
    args = parser.parse_args()
    if not CROWDVIEW.is_file():
        print(f"bench_clip_switches: {CROWDVIEW} not found: build crowdview first (scripts/setup.sh)", file=sys.stderr)
        return 2
    started = time.perf_counter()
    bundle = args.bundle
    if bundle is None:
        if not (args.assets / "robot_clips" / "timeline.json").is_file():
            print(f"bench_clip_switches: {args.assets}/robot_clips not found: give --bundle or --assets", file=sys.stderr)
            return 2
        bundle = bake_robot(args.assets, REPO / "out" / "bench" / "clip_switches_bundle", args.bake_robot)
    manifest = json.loads((bundle / "manifest.json").read_text())
    rows = []
    for blend in args.blends.split(","):
        for lod in REPRESENTATIONS:
            if lod != "impostor" and blend != args.blends.split(",")[0]:
                continue  # meshes do not blend impostors: one run each
            figures = switch_figures(bundle, lod, blend, args)
            rows.append({"representation": lod, "impostor_blend": blend if lod == "impostor" else None, **figures})
    print(f"{bundle}: {len(manifest.get('clips', []))} clips, {len(manifest.get('transitions', []))} transitions, "
          f"{len(manifest['impostor']['frame_indices'])} impostor frames; {args.count} characters, {args.frames} frames, "
          f"switching every {args.switch_after} s")
    print(f"{'representation':<24}{'largest ratio':>14}{'jump px':>10}{'ref px':>9}{'median':>8}{'same phase':>11}{'switches':>10}  "
          f"<= {TARGET}  worst switch (range frame -> range frame)")
    for row in rows:
        name = row["representation"] + (f" ({row['impostor_blend']})" if row["impostor_blend"] else "")
        ratio = row["largest_ratio"]
        worst = row.get("worst") or {}
        where = f"{worst['from']} {worst['from_frame']} -> {worst['to']} {worst['to_frame']}" if worst else "-"
        print(f"{name:<24}{ratio if ratio is None else round(ratio, 2)!s:>14}{row['jump_px'] or 0:>10.2f}{row['reference_px'] or 0:>9.2f}"
              f"{row['median_ratio'] or 0:>8.2f}{row.get('largest_ratio_same_phase') or 0:>11.2f}{row['switches_measured']:>10}  "
              f"{'ok' if ratio is not None and ratio <= TARGET else 'OVER':<6}{where}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"bundle": str(bundle), "count": args.count, "frames": args.frames, "switch_after_s": args.switch_after,
                                    "target": TARGET, "rows": rows, "seconds": time.perf_counter() - started}, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
