"""Where a bake's time goes, stage by stage: wall, CPU, seconds inside the renderer, peak memory.

    PYTHONPATH=services python services/benchmarks/bench_bake.py [--cases sample cesium robot]
        [--sample DIR] [--out out/bench/bake.json] [--against-rule RUNS]

Bakes, each case in a fresh process (so that imports and peak memory are its own), with the bake's
defaults (tiles of 88², up to 32 azimuths x 3 elevations, frames and views chosen by measuring within
the impostor budget):

- sample: the procedural sample (`crowdbake sample`: a walking character in a loose skirt, 8 diffuse
  variations of 1024²), generated into out/bench/sample unless --sample names one;
- cesium: CesiumMan with the shared long skirt (../shared/assets, skipped when absent);
- robot: the shared robot_clips (Idle, Walking, Running and their transitions, with its timeline).

--against-rule RUNS: each case baked RUNS times at the defaults and RUNS times as the impostor plan
was before it measured (`--impostor-choice rule`, no archetype budget: a budget per clip), in turn
(measured, rule, measured, rule ...), each in a fresh process after one warm-up bake of each; prints
the wall and CPU seconds of every run and the median of the pairs' ratios (measured / rule), and adds
them to the JSON as the case's "against_rule". Pairing in turn keeps the ratio when the machine's
speed drifts.

The bake runs through crowdbake.stages.runner.run_bake, as `crowdbake bake` does (--workers as its
option: default two worker processes for the poses stage beside the impostor tasks where two cores are
usable). Per stage, from run_bake's own figures (BakeSummary.timings, measured around each stage in this
process and around each item in the workers):

- wall and CPU seconds (CPU of every thread; in workers, summed over the stage's items; a stage's wall is
  the time during which at least one of its plan nodes ran, so stages that overlap add up to more than
  the bake);
- render: seconds inside pyrender/OpenGL (draw and read-back), summed by crowdbake.render.offscreen over
  every render of the bake (cycle views, impostor views, fidelity references), workers included;
- wall / render: 1.0 would be a bake bound by its renderer;
- for the case's whole process tree (its imports, the fork server and every worker; the kernel's
  accounting of the processes it waited for): user and system CPU seconds and minor page faults;
- peak RSS of this process while the stage's progress reports came (sampled every 10 ms from
  /proc/self/statm); the process's and the largest worker's high-water marks are in the totals.

Prints a table per case and writes everything as JSON, with run_bake's timeline (timings.timeline: every
worker item and stage, its process, start, end and CPU seconds). The figures are for this machine's cores under
OSMesa (llvmpipe) unless PYOPENGL_PLATFORM=egl.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

# The shared third-party assets sit beside the repository (../shared/assets); --assets names another place.
ASSETS = Path(__file__).resolve().parents[2].parent / "shared" / "assets"
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")
SAMPLE_EVERY_S = 0.01


def current_rss() -> int:
    """Resident bytes of this process now."""
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * PAGE_BYTES


def render_totals() -> dict[str, float]:
    """The renderer's running totals (crowdbake.render.offscreen), zero before anything rendered.

    Read without importing the module, so that measuring never moves pyrender's import cost."""
    module = sys.modules.get("crowdbake.render.offscreen")
    if module is None or not hasattr(module, "render_timings"):
        return {"seconds": 0.0, "renders": 0, "setup_seconds": 0.0}
    totals = module.render_timings()
    return {"seconds": totals.seconds, "renders": totals.renders, "setup_seconds": totals.setup_seconds}


class StageMeter:
    """A run_bake progress callback that cuts the bake into stages and measures each one."""

    def __init__(self) -> None:
        self.stages: dict[str, dict] = {}
        self._lock = threading.Lock()
        self._current = "validate"
        self._start = self._snapshot()
        self._peak = current_rss()
        self._stop = threading.Event()
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()

    @staticmethod
    def _snapshot() -> dict:
        return {"wall": time.perf_counter(), "cpu": time.process_time(), "render": render_totals()}

    def _sample(self) -> None:
        while not self._stop.wait(SAMPLE_EVERY_S):
            rss = current_rss()
            with self._lock:
                self._peak = max(self._peak, rss)

    def _close(self) -> None:
        now = self._snapshot()
        with self._lock:
            peak, self._peak = max(self._peak, current_rss()), current_rss()
        render = {key: now["render"][key] - self._start["render"][key] for key in now["render"]}
        wall = now["wall"] - self._start["wall"]
        figures = self.stages.setdefault(self._current, {"wall_s": 0.0, "cpu_s": 0.0, "render_s": 0.0, "renders": 0, "render_setup_s": 0.0, "peak_rss_mib": 0.0})
        figures["wall_s"] += wall
        figures["cpu_s"] += now["cpu"] - self._start["cpu"]
        figures["render_s"] += render["seconds"]
        figures["renders"] += render["renders"]
        figures["render_setup_s"] += render["setup_seconds"]
        figures["peak_rss_mib"] = max(figures["peak_rss_mib"], peak / 2**20)
        self._start = now

    def __call__(self, stage: str, done: int, total: int) -> None:
        name = stage.split(":")[0]
        if name != self._current:
            self._close()
            self._current = name

    def finish(self) -> dict[str, dict]:
        self._close()
        self._stop.set()
        self._sampler.join()
        for figures in self.stages.values():
            figures["wall_over_render"] = figures["wall_s"] / figures["render_s"] if figures["render_s"] > 0 else None
        return self.stages


def ensure_sample(folder: Path) -> Path:
    if (folder / "sample.json").is_file():
        return folder
    from crowdbake.sample.generate import generate_sample

    print(f"generating the sample into {folder} ...", flush=True)
    generate_sample(folder)
    return folder


# What --against-rule compares the defaults with: the impostor plan before it measured (BakeParams values).
RULE = {"impostor_choice": "rule", "impostor_archetype_mib": None}


def case_inputs(case: str, sample: Path, assets: Path, config: str = "defaults"):
    """BakeInputs of a case, or None when its assets are missing; config "rule": with RULE's parameters."""
    from dataclasses import replace

    from crowdbake.params import BakeParams
    from crowdbake.stages.validate import BakeInputs

    params = BakeParams() if config == "defaults" else replace(BakeParams(), **RULE)
    timeline = None
    if case == "sample":
        folder = ensure_sample(sample)
        files = (folder / "character.glb", folder / "cloth.pc2", folder / "cloth.obj", folder / "textures")
    elif case == "cesium":
        skirt = assets / "long_skirt"
        if not (assets / "CesiumMan.glb").is_file() or not (skirt / "long_skirt.pc2").is_file():
            return None
        files = (assets / "CesiumMan.glb", skirt / "long_skirt.pc2", skirt / "long_skirt.obj", None)
    elif case == "robot":
        robot = assets / "robot_clips"
        if not all((robot / name).is_file() for name in ("robot.glb", "garment.pc2", "garment.obj", "timeline.json")):
            return None
        files, timeline = (robot / "robot.glb", robot / "garment.pc2", robot / "garment.obj", None), robot / "timeline.json"
    else:
        raise ValueError(f"unknown case {case!r}")
    return BakeInputs(*files, None, "bench", "1", params, created="2006-09-04T12:00:00Z", timeline=timeline)


def run_case(case: str, sample: Path, assets: Path, workers: int | None = None, config: str = "defaults") -> dict | None:
    """Bake one case in this process and measure it (call in a fresh process)."""
    started = time.perf_counter()
    from crowdbake.stages import runner

    import_s = time.perf_counter() - started
    inputs = case_inputs(case, sample, assets, config)
    if inputs is None:
        return None
    with tempfile.TemporaryDirectory(prefix="crowdbake-bench-") as scratch:
        meter = StageMeter()
        wall, cpu = time.perf_counter(), time.process_time()
        summary = runner.run_bake(inputs, Path(scratch) / "bundles", Path(scratch) / "work", progress=meter, workers=workers)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        sampled = meter.finish()
        stages = {}
        for name, figures in summary.timings["stages"].items():
            stages[name] = dict(figures, peak_rss_mib=sampled.get(name, {}).get("peak_rss_mib"),
                                wall_over_render=figures["wall_s"] / figures["render_s"] if figures["render_s"] > 0 else None)
        bundle_bytes = sum(p.stat().st_size for p in summary.bundle.rglob("*") if p.is_file())
    timings = summary.timings
    return {
        "case": case,
        "config": config,
        "params": inputs.params.to_dict(),
        "import_runner_s": import_s,
        "stages": stages,
        "run_bake_stage_wall_s": summary.timings_s,
        "timings": {"wall_s": wall, "cpu_s": timings["cpu_s"], "cpu_this_process_s": cpu, "render_s": timings["render_s"],
                    "renders": timings["renders"], "workers": timings["workers"], "poses_with_impostors_s": timings["poses_with_impostors_s"],
                    "timeline": timings["timeline"]},
        "wall_over_render": wall / timings["render_s"] if timings["render_s"] > 0 else None,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "peak_rss_largest_worker_mib": timings["peak_rss_mib"]["largest_worker"],
        "impostor": summary.impostor,
        "compression": summary.compression,
        "fidelity": {k: summary.fidelity[k] for k in ("impostor", "nearest_view") if k in summary.fidelity},
        "bundle_bytes": bundle_bytes,
    }


def process_tree(before: resource.struct_rusage, after: resource.struct_rusage) -> dict[str, float]:
    """The case's process and every process it waited for (the fork server, which waited for the workers),
    from the kernel's accounting: user and system CPU seconds and minor page faults (a page touched for the
    first time: the kernel zeroes it)."""
    return {"user_s": after.ru_utime - before.ru_utime, "sys_s": after.ru_stime - before.ru_stime,
            "minor_page_faults": after.ru_minflt - before.ru_minflt}


def print_case(report: dict) -> None:
    timings = report["timings"]
    worker_peak = report["peak_rss_largest_worker_mib"]
    print(f"\n{report['case']}: wall {timings['wall_s']:.2f} s, CPU {timings['cpu_s']:.2f} s (workers included), render {timings['render_s']:.2f} s "
          f"({timings['renders']} renders), wall/render {report['wall_over_render'] or float('nan'):.2f}, {timings['workers']} worker(s), "
          f"peak RSS {report['peak_rss_mib']:.0f} MiB" + (f", largest worker {worker_peak:.0f} MiB" if worker_peak else ""))
    tree = report.get("process_tree")
    if tree:
        print(f"  whole process tree (imports included): user {tree['user_s']:.2f} s, system {tree['sys_s']:.2f} s, "
              f"{tree['minor_page_faults'] / 1e6:.2f} million minor page faults")
    print(f"  {'stage':10s} {'wall s':>8s} {'CPU s':>8s} {'render s':>9s} {'wall/render':>11s} {'peak MiB':>9s}")
    for name, figures in report["stages"].items():
        ratio, peak = figures["wall_over_render"], figures["peak_rss_mib"]
        print(
            f"  {name:10s} {figures['wall_s']:8.2f} {figures['cpu_s']:8.2f} {figures['render_s']:9.2f} "
            f"{'-' if ratio is None else f'{ratio:.1f}':>11s} {'-' if peak is None else f'{peak:.0f}':>9s}"
        )
    for kind, figures in report["compression"].items():
        print(f"  compression {kind}: {figures['pixel_format']} mean |error| {figures['rgb_mean_abs']:.3f}, worst PSNR {figures['rgb_psnr_db_worst']:.2f} dB")


def bake_in_process(case: str, sample: Path, args, config: str = "defaults") -> dict | None:
    """run_case in a fresh process, with its process tree's CPU (process_tree)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(
        [sys.executable, __file__, "--one-case", case, "--config", config, "--sample", str(sample), "--assets", str(args.assets),
         "--out", str(args.out)] + ([] if args.workers is None else ["--workers", str(args.workers)]),
        stdout=subprocess.PIPE, text=True, check=True,
    )
    report = json.loads(done.stdout.strip().splitlines()[-1])
    if report is not None:
        report["process_tree"] = process_tree(before, resource.getrusage(resource.RUSAGE_CHILDREN))
    return report


def against_rule(case: str, sample: Path, args) -> dict:
    """The case at the defaults and at RULE, args.against_rule runs each in turn after a warm-up of each
    (module docstring): every run's wall and CPU seconds and the median ratios of the pairs."""
    runs: dict[str, list[dict]] = {"defaults": [], "rule": []}
    for k in range(args.against_rule + 1):
        for config in ("defaults", "rule"):
            report = bake_in_process(case, sample, args, config)
            tree = report["process_tree"]
            figures = {"wall_s": report["timings"]["wall_s"], "cpu_s": tree["user_s"] + tree["sys_s"]}
            print(f"  {case} {config:8s} {'warm-up' if k == 0 else f'run {k}':7s} wall {figures['wall_s']:6.2f} s, CPU {figures['cpu_s']:6.2f} s", flush=True)
            if k > 0:
                runs[config].append(figures)
    ratios = {key: float(np.median([a[key] / b[key] for a, b in zip(runs["defaults"], runs["rule"])])) for key in ("wall_s", "cpu_s")}
    print(f"  {case}: measured / rule, median of {args.against_rule} pairs: wall {ratios['wall_s']:.3f}, CPU {ratios['cpu_s']:.3f}")
    return {"rule": RULE, "runs": runs, "median_ratio": ratios}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", default=["sample", "cesium"], choices=["sample", "cesium", "robot"])
    parser.add_argument("--sample", type=Path, help="a `crowdbake sample` folder (default: generate out/bench/sample)")
    parser.add_argument("--out", type=Path, default=Path("out/bench/bake.json"), help="JSON report (default out/bench/bake.json)")
    parser.add_argument("--assets", type=Path, default=ASSETS, help=f"the shared assets folder (default {ASSETS})")
    parser.add_argument("--workers", type=int, help="run_bake's worker processes (default: its own choice, 2 on two cores)")
    parser.add_argument("--against-rule", type=int, metavar="RUNS", default=0,
                        help="also bake each case RUNS times as the impostor plan's rule, in turn with the defaults (module docstring)")
    parser.add_argument("--one-case", help=argparse.SUPPRESS)  # internal: bake this case here, print its JSON
    parser.add_argument("--config", default="defaults", choices=["defaults", "rule"], help=argparse.SUPPRESS)  # with --one-case
    args = parser.parse_args()
    sample = args.sample or args.out.parent / "sample"

    if args.one_case:
        print(json.dumps(run_case(args.one_case, sample, args.assets, args.workers, args.config)))
        return 0
    reports = []
    for case in args.cases:
        report = bake_in_process(case, sample, args)
        if report is None:
            print(f"\n{case}: skipped (assets missing under {args.assets})")
            continue
        reports.append(report)
        print_case(report)
        if args.against_rule > 0:
            report["against_rule"] = against_rule(case, sample, args)
    document = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "gl_platform": os.environ.get("PYOPENGL_PLATFORM")},
        "cases": reports,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
