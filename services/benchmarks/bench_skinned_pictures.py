#!/usr/bin/env python3
"""crowdview's pictures of a skinned body against the same bake with vertex frames, side by side in one run.

    PYTHONPATH=services python services/benchmarks/bench_skinned_pictures.py \
        LABEL=SKINNED_BUNDLE:VERTEX_BUNDLE ... [--crowdview build/runtime/crowdview] [--count 60] [--frames 8]
        [--out out/bench/skinned_pictures.json]

Each pair is one character baked twice, with the defaults (the body skinned on the GPU, bundle format 4)
and with `--no-skinning` (the body as vertex frames). crowdview draws the same crowd (seed, count, street
camera, `--frames` frames) of each at `--lod high` and `--lod low`, headless; the two screenshots are
compared: mean absolute difference over every pixel (of 255) and SSIM (crowdbake.bake.fidelity.compare
over the pictures' box). Prints a table and writes JSON.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "services"))

from crowdbake.bake.fidelity import compare  # noqa: E402


def picture(crowdview: str, bundle: str, lod: str, count: int, frames: int, out: Path) -> np.ndarray:
    """crowdview's last frame of the crowd at `lod`: (H, W, 3) float64 in 0..1."""
    run = subprocess.run([crowdview, "--bundle", bundle, "--lod", lod, "--count", str(count), "--seed", "1", "--camera", "street",
                          "--headless", "--frames", str(frames), "--screenshot", str(out)], capture_output=True, text=True)
    if run.returncode != 0:
        raise SystemExit(f"bench_skinned_pictures: crowdview failed on {bundle}: {run.stderr.strip().splitlines()[-1:]}")
    return np.asarray(Image.open(out).convert("RGB"), dtype=np.float64) / 255.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="+", metavar="LABEL=SKINNED:VERTEX")
    parser.add_argument("--crowdview", default=str(REPO_ROOT / "build" / "runtime" / "crowdview"))
    parser.add_argument("--count", type=int, default=60)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--out", type=Path, default=Path("out/bench/skinned_pictures.json"))
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as scratch:
        for item in args.pairs:
            label, _, paths = item.partition("=")
            skinned, _, vertex = paths.partition(":")
            if not vertex:
                raise SystemExit(f"bench_skinned_pictures: {item!r} is not LABEL=SKINNED:VERTEX")
            for lod in ("high", "low"):
                a = picture(args.crowdview, skinned, lod, args.count, args.frames, Path(scratch) / "a.png")
                b = picture(args.crowdview, vertex, lod, args.count, args.frames, Path(scratch) / "b.png")
                scores = compare(b, a)
                results.append({"archetype": label, "lod": lod, "mean_abs_diff_255": float(np.abs(a - b).mean() * 255),
                                "ssim": scores["ssim"], "psnr_db": scores["psnr_db"]})
    print(f"{'archetype':<14}{'lod':<6}{'mean |diff| /255':>18}{'SSIM':>10}{'PSNR dB':>10}")
    for row in results:
        print(f"{row['archetype']:<14}{row['lod']:<6}{row['mean_abs_diff_255']:>18.4f}{row['ssim']:>10.5f}{row['psnr_db']:>10.1f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
