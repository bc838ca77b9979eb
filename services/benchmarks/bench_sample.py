"""Seconds to generate the procedural sample, per garment, at the default settings.

    PYTHONPATH=services python services/benchmarks/bench_sample.py [--out out/bench/sample.json]
        [--cycles 20] [--repeat 1] [--garments loose tight]

Times `generate_sample` end to end (skeleton, walk, cloth simulation, textures, every file written)
and, separately, the simulation alone, then prints a table and writes JSON with the figures, the
settling curves and the machine it ran on. Target: well under a minute per garment on 2 cores.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from crowdbake.sample.generate import DEFAULT_CYCLES, generate_sample, settled_cycle, simulate_sample


def measure(garment: str, cycles: int, repeat: int) -> dict:
    simulate_seconds, generate_seconds = [], []
    for _ in range(repeat):
        started = time.perf_counter()
        simulation = simulate_sample(garment, cycles=cycles)
        simulate_seconds.append(time.perf_counter() - started)
        with tempfile.TemporaryDirectory() as folder:
            started = time.perf_counter()
            result = generate_sample(folder, garment=garment, cycles=cycles)
            generate_seconds.append(time.perf_counter() - started)
    frames = cycles * simulation.cycle_frames
    return {
        "garment": garment,
        "cycles": cycles,
        "frames": frames,
        "cloth_vertices": int(simulation.points.shape[1]),
        "simulate_seconds": round(min(simulate_seconds), 3),
        "generate_seconds": round(min(generate_seconds), 3),
        "simulated_frames_per_second": round(frames / min(simulate_seconds), 2),
        "settling_rms_mm": [round(float(value) * 1000, 2) for value in simulation.settling],
        "settled_cycle": settled_cycle(simulation.settling),
        "quality": result.quality,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench/sample.json"))
    parser.add_argument("--cycles", type=int, default=DEFAULT_CYCLES)
    parser.add_argument("--repeat", type=int, default=1, help="runs per garment; the fastest counts")
    parser.add_argument("--garments", nargs="+", default=["loose", "tight"])
    args = parser.parse_args(argv)

    rows = [measure(garment, args.cycles, args.repeat) for garment in args.garments]
    print(f"{'garment':<8} {'vertices':>8} {'frames':>7} {'simulate s':>11} {'generate s':>11} {'settled at':>11}")
    for row in rows:
        settled = row["settled_cycle"] if row["settled_cycle"] is not None else "-"
        print(f"{row['garment']:<8} {row['cloth_vertices']:>8} {row['frames']:>7} {row['simulate_seconds']:>11.2f} "
              f"{row['generate_seconds']:>11.2f} {settled!s:>11}")
        print(f"  settling RMS mm per cycle: {row['settling_rms_mm']}")
    report = {
        "benchmark": "sample",
        "machine": {
            "python": sys.version.split()[0],
            "numpy": np.__version__,
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        },
        "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
