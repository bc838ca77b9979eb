"""Wall time of a bake of several clips on the service: the clips sample (Idle, Walking, Running in one
simulation, with its timeline) baked over REST by one Celery worker of N prefork processes.

    PYTHONPATH=services python services/benchmarks/bench_service_clips.py [--workers 2] [--out out/bench/service_clips.json]

Starts a private redis-server on loopback (Celery's filesystem broker when none is installed), uvicorn and
the worker on a temporary data folder, generates the small clips sample (a walk of 16 frames, a coarse
8 x 36 cloth), uploads it, bakes it once untimed (each worker process imports the stages and makes its GL
context on its first task) and then again under another version, timed from the submission to the bake's
success. Prints and writes the wall time, each stage's recorded seconds (a fan-out stage's: summed over its
tasks) and the span each task kind covered in the worker's log.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import httpx

from service_bench import FINAL_STATES, free_port

REPO = Path(__file__).resolve().parents[2]
if str(REPO / "services" / "tests") not in sys.path:  # service_fixtures: the tests' way of starting the service
    sys.path.insert(0, str(REPO / "services" / "tests"))

SERVICES_DIR = Path(__file__).resolve().parents[1]
# As services/tests/clips_fixtures.py: seconds to simulate and to bake.
CLIPS_SAMPLE = dict(garment="tight", seed=1, cycle_frames=16, texture_size=64, cloth_rows=8, cloth_columns=36, build="heavy")
PARAMS = {"impostor_frames": 2, "azimuths": 8, "elevations_deg": [0, 30], "tile_size": 64, "lod_triangles": 1200,
          "cycle_views": 3, "candidates": 3, "export": False}
START_TIMEOUT_S = 120
BAKE_TIMEOUT_S = 900
# "[2026-01-01 10:00:00,123: INFO/ForkPoolWorker-1] Task crowdbake.stage.<name>[<id>] succeeded in 2.5s: None"
SUCCEEDED = re.compile(r"^\[(?P<at>[\d-]+ [\d:]+,\d+): INFO/[^\]]+\] Task crowdbake\.stage\.(?P<task>\w+)\[[^\]]+\] succeeded in (?P<s>[\d.]+)s")


def task_spans(log: str, since: float) -> dict[str, dict]:
    """Per task name, from the worker log's "succeeded" lines after `since` (epoch s): how many ran, their
    summed seconds, and the wall span from the first one's start to the last one's end."""
    found: dict[str, list[tuple[float, float]]] = {}
    for line in log.splitlines():
        match = SUCCEEDED.match(line)
        if match:
            end = dt.datetime.strptime(match["at"], "%Y-%m-%d %H:%M:%S,%f").timestamp()
            if end - float(match["s"]) >= since:
                found.setdefault(match["task"], []).append((end - float(match["s"]), end))
    return {task: {"tasks": len(spans), "summed_s": round(sum(b - a for a, b in spans), 2),
                   "span_s": round(max(b for _, b in spans) - min(a for a, _ in spans), 2)} for task, spans in found.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2, help="prefork processes of the one Celery worker")
    parser.add_argument("--out", type=Path, default=Path("out/bench/service_clips.json"))
    args = parser.parse_args()

    from crowdbake.sample.clips import DEFAULT_SEQUENCE
    from crowdbake.sample.generate import generate_sample
    from service_fixtures import local_api_key, service_env, start_api, start_process, start_worker

    root = Path(tempfile.mkdtemp(prefix="bench-service-clips-"))
    processes = []
    try:
        sample = root / "sample"
        generate_sample(sample, clips=DEFAULT_SEQUENCE, **CLIPS_SAMPLE)
        redis = shutil.which("redis-server")
        broker = "filesystem://"
        if redis:
            redis_port = free_port()
            processes.append(start_process([redis, "--port", str(redis_port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                                            "--dir", str(root)], os.environ.copy(), root / "redis.log"))
            broker = f"redis://127.0.0.1:{redis_port}/0"
        env = service_env(root / "data", broker)
        key = local_api_key(root / "data", "upload,bake,publish,read", "clips benchmark")
        port = free_port()
        processes.append(start_api(env, port, root / "api.log", timeout=START_TIMEOUT_S))
        processes.append(start_worker(env, root / "worker.log", concurrency=args.workers))
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
            deadline = time.monotonic() + START_TIMEOUT_S
            while client.get("/ready").status_code != 200:  # the worker answers the broker
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the service did not become ready; see {root}/api.log and worker.log")
                time.sleep(0.2)

            def upload(url: str, **files: Path) -> str:
                answer = client.post(url, files={field: (path.name, path.read_bytes()) for field, path in files.items()})
                answer.raise_for_status()
                return answer.json()["id"]

            body = {"name": "bench-clips", "params": PARAMS,
                    "character": upload("/v1/assets/characters", file=sample / "character.glb"),
                    "cloth": upload("/v1/assets/cloth", cache=sample / "cloth.pc2", mesh=sample / "cloth.obj"),
                    "timeline": upload("/v1/assets/timelines", timeline=sample / "timeline.json"),
                    "textures": {path.name: upload("/v1/assets/textures", file=path) for path in sorted((sample / "textures").glob("*.png"))}}

            def bake(version: str) -> tuple[dict, float, float]:
                began, wall = time.time(), time.perf_counter()
                created = client.post("/v1/bakes", json=dict(body, version=version))
                created.raise_for_status()
                deadline = time.monotonic() + BAKE_TIMEOUT_S
                while (state := client.get(f"/v1/bakes/{created.json()['id']}").json())["state"] not in FINAL_STATES:
                    if time.monotonic() > deadline:
                        raise RuntimeError(f"the bake did not finish; see {root}/worker.log")
                    time.sleep(0.1)
                if state["state"] != "succeeded":
                    raise RuntimeError(f"the bake {state['state']}: {state['error']}")
                return state, time.perf_counter() - wall, began

            bake("0.0.1-warm-up")
            state, wall, began = bake("1.0.0")
        stages = {stage["stage"]: {"state": stage["state"], "seconds": stage["seconds"]} for stage in state["stages"]}
        spans = task_spans((root / "worker.log").read_text(errors="replace"), began)
        result = {"workers": args.workers, "broker": broker.split(":")[0], "wall_s": round(wall, 2), "stages": stages, "tasks": spans,
                  "cpus": os.cpu_count(), "load_average": os.getloadavg(), "machine": platform.machine()}
        print(f"clips bake on the service, {args.workers} worker processes ({result['broker']} broker): {wall:.1f} s wall")
        for name, stage in stages.items():
            print(f"  {name:10s} {stage['state']:10s} {stage['seconds'] if stage['seconds'] is not None else '-'} s")
        for task, figures in spans.items():
            print(f"  task {task:15s} x{figures['tasks']}: {figures['summed_s']} s of work within {figures['span_s']} s")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.out}")
        return 0
    finally:
        for process in reversed(processes):
            process.stop(timeout=30)
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
