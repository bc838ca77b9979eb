#!/usr/bin/env python3
"""GPU memory per archetype and per part (body meshes, garment meshes, impostor maps, textures) as crowdview
uploads it: `crowdview --report`'s `gpu_memory_bytes`, beside each bundle's pose-cache bytes on disk.

    python services/benchmarks/bench_gpu_memory.py [--bake sample] [--bake robot] [--work DIR]
        [--bundle LABEL PATH] [--case LABEL PATH CROWDVIEW] [--crowdview build/runtime/crowdview]
        [--out out/bench/gpu_memory.json]

--bake bakes with this checkout, as scripts/demo.sh does: `sample` generates the sample clothed character
(loose garment) and bakes it; `robot` bakes ../shared/assets/robot_clips with its timeline (slow: every
clip and transition). --bundle measures a bundle already baked with --crowdview; --case names the crowdview
too, so a build of another revision can measure the bundle its bake wrote (e.g. before and after a format
change). Prints a table and writes every figure as JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_ASSETS = Path(os.environ.get("CROWDBAKE_SHARED_ASSETS", REPO_ROOT.parent / "shared" / "assets"))
MIB = 1024 * 1024
# crowdview's report: meshes = bodies + garments (builds before the split report meshes only).
PARTS = ("meshes", "bodies", "garments", "impostors", "textures", "total")


def crowdbake(*args: str) -> None:
    """Runs this checkout's crowdbake command line; stops with its last lines on failure."""
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT / "services"), PYOPENGL_PLATFORM=os.environ.get("PYOPENGL_PLATFORM", "osmesa"))
    run = subprocess.run([sys.executable, "-m", "crowdbake", *args], capture_output=True, text=True, env=env)
    if run.returncode != 0:
        raise SystemExit(f"bench_gpu_memory: crowdbake {args[0]} failed: {run.stderr.strip().splitlines()[-3:]}")


def bake(which: str, work: Path) -> Path:
    """The bundle folder of `which` (sample or robot), baked into `work` unless already there."""
    bundle = work / "bundles" / which / "1.0.0"
    if (bundle / "manifest.json").is_file():
        return bundle
    if which == "sample":
        sample = work / "sample"
        crowdbake("sample", str(sample), "--garment", "loose")
        crowdbake("bake", str(sample / "character.glb"), "--cloth", str(sample / "cloth.pc2"), "--cloth-mesh", str(sample / "cloth.obj"),
                  "--textures", str(sample / "textures"), "--name", which, "--version", "1.0.0", "--out", str(work / "bundles"))
    else:
        robot = SHARED_ASSETS / "robot_clips"
        crowdbake("bake", str(robot / "robot.glb"), "--cloth", str(robot / "garment.pc2"), "--cloth-mesh", str(robot / "garment.obj"),
                  "--timeline", str(robot / "timeline.json"), "--name", which, "--version", "1.0.0", "--out", str(work / "bundles"))
    return bundle


def measure(crowdview: str, bundle: Path) -> dict:
    """crowdview's gpu_memory_bytes for one character of `bundle` (one headless frame); parts its build does
    not split are absent."""
    with tempfile.TemporaryDirectory(prefix="bench-gpu-memory-") as tmp:
        report = Path(tmp) / "report.json"
        run = subprocess.run([crowdview, "--bundle", str(bundle), "--count", "1", "--headless", "--frames", "1", "--width", "64",
                              "--height", "64", "--report", str(report)], capture_output=True, text=True)
        if run.returncode != 0:
            raise SystemExit(f"bench_gpu_memory: crowdview failed on {bundle}: {run.stderr.strip().splitlines()[-2:]}")
        (archetype,) = json.loads(report.read_text())["archetypes"]
    return archetype["gpu_memory_bytes"]


def pose_cache_files(bundle: Path) -> dict:
    """Bytes on disk of each pose cache the runtime draws (mesh LODs 0 and 1), by kind of part."""
    manifest = json.loads((bundle / "manifest.json").read_text())
    sizes = {entry["path"]: entry["size"] for entry in manifest["files"]}
    out: dict[str, int] = {"body": 0, "garment": 0}
    for mesh in manifest["meshes"]:
        if mesh["lod"] <= 1:
            out[mesh["kind"]] += sizes[mesh["file"]]
    return {"format_version": manifest["format_version"], "pose_cache_bytes": out}


def row(label: str, memory: dict) -> str:
    cells = [f"{memory[part] / MIB:11.2f}" if part in memory else f"{'-':>11}" for part in PARTS]
    return f"{label:<34}" + "".join(cells)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bake", action="append", choices=["sample", "robot"], default=[])
    parser.add_argument("--work", type=Path, default=REPO_ROOT / "out" / "bench_gpu_memory")
    parser.add_argument("--bundle", nargs=2, action="append", default=[], metavar=("LABEL", "PATH"))
    parser.add_argument("--case", nargs=3, action="append", default=[], metavar=("LABEL", "PATH", "CROWDVIEW"))
    parser.add_argument("--crowdview", default=str(REPO_ROOT / "build" / "runtime" / "crowdview"))
    parser.add_argument("--out", type=Path, default=Path("out/bench/gpu_memory.json"))
    args = parser.parse_args()
    cases = [(which, bake(which, args.work), args.crowdview) for which in args.bake]
    cases += [(label, Path(path), args.crowdview) for label, path in args.bundle]
    cases += [(label, Path(path), crowdview) for label, path, crowdview in args.case]
    if not cases:
        parser.error("nothing to measure: give --bake, --bundle or --case")
    results = []
    print(f"{'MiB':<34}" + "".join(f"{part:>11}" for part in PARTS))
    for label, bundle, crowdview in cases:
        memory = measure(crowdview, bundle)
        results.append({"label": label, "bundle": str(bundle), "crowdview": crowdview, "gpu_memory_bytes": memory, **pose_cache_files(bundle)})
        print(row(label, memory))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"results": results}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
