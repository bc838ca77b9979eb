#!/usr/bin/env python3
"""The paper's figure 3 for a mixed crowd: the largest crowd of a crowd description's archetypes (their
shares kept) that crowdview draws at 30 and at 60 fps, LOD by distance, headless.

    scripts/bench_mixed_crowd.py CROWD.json [--crowdview build/runtime/crowdview] [--out figure3.json]
        [--width 1280 --height 720] [--frames 8] [--max-seconds 600] [--lod auto|high|low|impostor] [--gl-device D]

Each run writes the description with `count` replaced, runs `crowdview --crowd ... --headless
--report`, and reads the median whole-frame time (cull to glFinish, after two warm-up frames). A
crowd size whose median misses the frame budget, or meets it by less than CONFIRM_MARGIN, is run
again, up to PROBE_RUNS times, and the median of the runs' medians decides: one slow frame (other
work on the machine) must not end a search. N doubles from 8 until a target fails, then bisects to
10 %. --lod draws every character as one representation (figure 3 per representation), auto by
distance. No run starts that would end (as long as the last, in proportion to N above it) past
--max-seconds. Prints one line per run and the result, and writes every size's runs (the median and
its spread), the counts per archetype and LOD, the GPU memory per archetype, the impostor blend each
archetype drew with and the GL renderer as JSON. Needs a description whose archetypes all give a share.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

FIRST_COUNT = 8
MAX_COUNT = 1 << 20  # a million characters bounds the doubling
# Runs of one crowd size at most, and how far under the frame budget a median must be to count on
# one run (runtime/src/benchmark_search.h has the same rule for crowdview --benchmark).
PROBE_RUNS = 3
CONFIRM_MARGIN = 1.25
# Bisection stops within this fraction of the answer.
BISECT_TOLERANCE = 0.10
SOFTWARE_NOTE = ("a software rasteriser: it shades fragments on the CPU, where impostors cost as much as meshes or more, which "
                 "inverts the paper's ranking (impostors far cheaper than meshes on a GPU); compare with the paper on a GPU")


@dataclass
class Probe:
    """Every run of one crowd size: each run's median frame (ms) and its report."""

    count: int
    frame_ms: list[float] = field(default_factory=list)
    reports: list[dict] = field(default_factory=list)

    @property
    def median_ms(self) -> float:
        return statistics.median(self.frame_ms)

    def to_json(self) -> dict:
        return {"count": self.count, "frame_ms_median": round(self.median_ms, 2), "frame_ms_min": round(min(self.frame_ms), 2),
                "frame_ms_max": round(max(self.frame_ms), 2), "runs": len(self.frame_ms), "archetypes": self.reports[-1]["archetypes"]}


class MixedCrowdSearch:
    """The probes of one benchmark, shared by its 30 and 60 fps searches, and the clock they run against."""

    def __init__(self, run_crowdview, max_seconds: float):
        self.run_crowdview = run_crowdview  # count -> crowdview's --report document
        self.probes: dict[int, Probe] = {}
        self.started = time.monotonic()
        self.max_seconds = max_seconds
        self.last_run = (0.0, 1)  # (seconds, count) of the last run: the prediction of the next

    def fits(self, count: int) -> bool:
        seconds, last_count = self.last_run
        predicted = seconds * max(1.0, count / last_count)
        return time.monotonic() - self.started + predicted < self.max_seconds

    def run(self, probe: Probe) -> None:
        started = time.monotonic()
        report = self.run_crowdview(probe.count)
        self.last_run = (time.monotonic() - started, probe.count)
        probe.frame_ms.append(float(report["frame_ms_median"]))
        probe.reports.append(report)
        print(f"N = {probe.count}: median frame {probe.frame_ms[-1]:.1f} ms ({1000 / max(probe.frame_ms[-1], 1e-9):.1f} fps)"
              + (f", median of {len(probe.frame_ms)} runs {probe.median_ms:.1f} ms" if len(probe.frame_ms) > 1 else ""), file=sys.stderr)

    def holds(self, count: int, fps: float) -> bool | None:
        """Whether `count` characters hold `fps` (its runs' median frame within 1000 / fps ms), run again
        while near or over the budget; None where no run could start in time."""
        budget_ms = 1000.0 / fps
        probe = self.probes.get(count)
        if probe is None:
            if not self.fits(count):
                return None
            probe = self.probes[count] = Probe(count)
            self.run(probe)
        while len(probe.frame_ms) < PROBE_RUNS and probe.median_ms * CONFIRM_MARGIN > budget_ms and self.fits(count):
            self.run(probe)
        return probe.median_ms <= budget_ms

    def largest_holding(self, fps: float) -> tuple[int, bool]:
        """The largest crowd that holds `fps`, and whether the search converged (in time)."""
        good, bad = 0, None
        for count in sorted(self.probes):  # what the other target's search measured
            if self.holds(count, fps):
                good = max(good, count)
            elif bad is None:
                bad = count
        if bad is not None and good > bad:
            good = 0  # sizes that disagree even after their repeats: trust the failing one
        count = max(FIRST_COUNT, 2 * good)
        while bad is None:
            verdict = self.holds(count, fps) if count <= MAX_COUNT else None
            if verdict is None:
                return good, False
            good, bad, count = (count, None, 2 * count) if verdict else (good, count, count)
        while bad - good > max(1, int(good * BISECT_TOLERANCE)):
            middle = (good + bad) // 2
            verdict = self.holds(middle, fps)
            if verdict is None:
                return good, False
            good, bad = (middle, bad) if verdict else (good, middle)
        return good, True


def crowdview_runner(crowdview: str, crowd: Path, description: dict, folder: Path, args: argparse.Namespace):
    """count -> the report of one headless run of `count` characters."""

    def run(count: int) -> dict:
        # Beside the description: its bundle folders are relative to its folder.
        path = crowd.parent / f".bench-crowd-{count}.json"
        path.write_text(json.dumps(dict(description, count=count)))
        report = folder / f"report-{count}.json"
        command = [crowdview, "--crowd", str(path), "--headless", "--frames", str(args.frames), "--width", str(args.width),
                   "--height", str(args.height), "--report", str(report), "--lod", args.lod, "--gl-device", args.gl_device]
        command += ["--impostor-blend", args.blend] if args.blend else []
        try:
            done = subprocess.run(command, capture_output=True, text=True)
        finally:
            path.unlink(missing_ok=True)
        if done.returncode != 0:
            raise SystemExit(f"bench_mixed_crowd: crowdview failed at N = {count}: {done.stderr.strip().splitlines()[-1:]}")
        return json.loads(report.read_text())

    return run


def summary(search: MixedCrowdSearch, results: dict, args: argparse.Namespace) -> dict:
    """The JSON written to --out: results, the machine and the blend that drew them, every probe."""
    probes = [search.probes[count] for count in sorted(search.probes)]
    # Memory and blend per archetype from the probe that loaded the most of them (a small N rounds some shares to none).
    widest = max((p.reports[-1] for p in probes), key=lambda r: len(r["archetypes"]), default={"archetypes": []})
    gl = widest.get("gl") or {}
    out = {"crowd": str(args.crowd), "lod": args.lod, "width": args.width, "height": args.height, "frames": args.frames,
           "impostor_blend": {a["name"]: a.get("impostor_blend") for a in widest["archetypes"]}, "gl": gl,
           "seconds": round(time.monotonic() - search.started, 1), "probe_runs": PROBE_RUNS, "results": results,
           "gpu_memory_bytes": {a["name"]: a["gpu_memory_bytes"] for a in widest["archetypes"]},
           "probes": [p.to_json() for p in probes]}
    if gl.get("software_rasteriser"):
        out["software_rasteriser_note"] = f"GL_RENDERER {gl.get('renderer')} is {SOFTWARE_NOTE}"
    return out


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
    parser.add_argument("--lod", choices=["auto", "high", "low", "impostor"], default="auto")
    parser.add_argument("--gl-device", default="auto", help="crowdview's --gl-device: auto, software or N")
    args = parser.parse_args()
    description = json.loads(args.crowd.read_text())
    if any("share" not in a for a in description.get("archetypes", [])):
        print("bench_mixed_crowd: every archetype needs a share (the count is what the benchmark varies)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="bench-mixed-") as tmp:
        search = MixedCrowdSearch(crowdview_runner(args.crowdview, args.crowd, description, Path(tmp), args), args.max_seconds)
        results = {}
        for fps in (30, 60):
            results[f"n_at_{fps}fps"], results[f"converged_{fps}"] = search.largest_holding(fps)
        out = summary(search, results, args)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps({k: out[k] for k in ("results", "impostor_blend", "gpu_memory_bytes")}, indent=2))
    if "software_rasteriser_note" in out:
        print(f"bench_mixed_crowd: {out['software_rasteriser_note']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
