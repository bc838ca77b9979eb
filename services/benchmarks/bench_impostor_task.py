"""CPU seconds of one impostor task, piece by piece, and where they go (cProfile).

    PYTHONPATH=services python services/benchmarks/bench_impostor_task.py --work WORK [--task f0000-e0 ...]
        [--repeat 3] [--top 25] [--out out/bench/impostor_task.json]

WORK is a bake's work folder (`crowdbake bake ... --work WORK`; only its impostor plan is read). Each
task (default: the first fidelity task, which also renders the mesh references, and the first plain
one) runs in this process as the bake's workers run it (stages.impostors.render_task, then the part's
npz bytes), once to warm up (GL context, imports) and then --repeat times: the best CPU seconds per
piece (scene load, GL render calls, map resolution, references, npz packing; `render_task`'s own
timings are wall seconds, the rest process CPU). One more run under cProfile lists the functions with
the most own time. Nothing is written into WORK.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.render.offscreen import render_timings  # noqa: E402
from crowdbake.stages.impostors import impostor_tasks, load_plan, load_scene, render_task  # noqa: E402
from crowdbake.stages.workdir import npz_bytes  # noqa: E402


def run_once(work: Path, plan, task) -> dict[str, float]:
    """One task, timed by piece: CPU seconds of the whole and of each piece, wall seconds inside GL."""
    pieces: dict[str, float] = {}
    started = time.process_time()
    scene = load_scene(work, plan, task.frame, runtime_textures=task.references)
    pieces["load_cpu_s"] = time.process_time() - started
    timings = {"render": 0.0, "maps": 0.0, "references": 0.0}
    gl_before = render_timings().seconds
    clock = time.process_time()
    arrays = render_task(scene, plan, task, timings)
    pieces["render_task_cpu_s"] = time.process_time() - clock
    clock = time.process_time()
    npz_bytes(arrays)
    pieces["npz_cpu_s"] = time.process_time() - clock
    pieces["total_cpu_s"] = time.process_time() - started
    pieces["gl_wall_s"] = render_timings().seconds - gl_before
    pieces["maps_wall_s"] = timings["maps"]
    pieces["references_wall_s"] = timings["references"]
    pieces["render_loop_wall_s"] = timings["render"]
    return pieces


def profile_once(work: Path, plan, task, top: int) -> list[dict]:
    """The `top` functions by own time in one run of the task."""
    profiler = cProfile.Profile(time.process_time)
    profiler.enable()
    scene = load_scene(work, plan, task.frame, runtime_textures=task.references)
    arrays = render_task(scene, plan, task, {"render": 0.0, "maps": 0.0, "references": 0.0})
    npz_bytes(arrays)
    profiler.disable()
    stats = pstats.Stats(profiler)
    rows = []
    for (filename, line, name), (_, calls, own, cumulative, _) in stats.stats.items():  # type: ignore[attr-defined]
        rows.append({"function": f"{Path(filename).name}:{line}({name})", "calls": calls, "own_s": own, "cumulative_s": cumulative})
    rows.sort(key=lambda row: -row["own_s"])
    return rows[:top]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--task", nargs="*", help="task ids (default: the first fidelity task and the first plain one)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--out", type=Path, default=Path("out/bench/impostor_task.json"))
    args = parser.parse_args()

    plan = load_plan(args.work)
    tasks = impostor_tasks(args.work)
    if args.task:
        by_id = {task.id: task for task in tasks}
        missing = [name for name in args.task if name not in by_id]
        if missing:
            parser.error(f"no impostor task {missing[0]!r} in {args.work} (tasks: {', '.join(by_id)})")
        chosen = [by_id[name] for name in args.task]
    else:
        chosen = [next(task for task in tasks if task.references), next(task for task in tasks if not task.references)]

    report = {"work": str(args.work), "repeat": args.repeat, "tasks": {}}
    for task in chosen:
        run_once(args.work, plan, task)  # warm-up: GL context, shaders, imports
        runs = [run_once(args.work, plan, task) for _ in range(args.repeat)]
        best = {key: min(run[key] for run in runs) for key in runs[0]}
        profile = profile_once(args.work, plan, task, args.top)
        report["tasks"][task.id] = {"views": len(task.views), "references": task.references, "best": best, "profile": profile}
        print(f"task {task.id}: {len(task.views)} views{' + references' if task.references else ''}, best of {args.repeat}")
        for key, value in best.items():
            print(f"  {key:<20} {value:8.3f}")
        print(f"  {'own s':>8} {'cum s':>8} {'calls':>7}  function (one profiled run)")
        for row in profile:
            print(f"  {row['own_s']:8.3f} {row['cumulative_s']:8.3f} {row['calls']:7d}  {row['function']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
