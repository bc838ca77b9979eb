"""Load on the service: concurrent uploads, queued bakes on two workers, API latency while they bake.

    PYTHONPATH=services python services/benchmarks/load_service.py [--uploads 50] [--duplicates 10]
        [--bakes 20] [--workers 2] [--clients 4] [--sample DIR] [--timeout 900] [--out out/bench/load.json]

Starts a private stack on loopback only: `redis-server` (no persistence), the API (uvicorn) and
`--workers` Celery workers (one prefork process each) on a temporary data folder, then

1. uploads `--uploads` distinct PNG textures and `--duplicates` copies of one more, all at once (one
   thread per request): every distinct upload must become its own asset and blob, and the copies one
   asset between them (deduplication under concurrency);
2. uploads the procedural sample and submits `--bakes` bakes at once (distinct versions of the same
   inputs, small parameters), and while they run, `--clients` threads read the API (a bake, the bake
   list, the asset list, /health) as fast as it answers, timing every request;
3. checks that every bake succeeded exactly once: one "bake succeeded" and one "publish finished" in
   each bake's log, one bundle record per version, none missing, none extra.

Prints the figures (upload rate and latency, bake throughput, API latency p50/p90/p99/max under load)
and writes them as JSON. The request count and the time are bounded (--timeout). Figures are for this
machine: the JSON records the CPU count and the load average, since other work on the machine slows
both the bakes and the API.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import platform
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from service_bench import FINAL_STATES, SMALL_BAKE_PARAMS, free_port

SERVICES_DIR = Path(__file__).resolve().parents[1]
REPO = SERVICES_DIR.parent
# Small bakes (3-cycle sample, 64² textures; 2 impostor frames x 4 azimuths x 2 rings of 32²): the
# figure is about the service and its queue, not the renderer.
START_TIMEOUT_S = 120
POLL_S = 0.5
# Pause between two reads of one latency client: a busy dashboard, not a denial of service.
CLIENT_PAUSE_S = 0.02
TEXTURE_SIZE = 64


def percentile(values: list[float], q: float) -> float | None:
    """The q-th percentile (0..100) by the nearest-rank method; None for no values."""
    if not values:
        return None
    ordered = sorted(values)
    rank = max(1, int(round(q / 100.0 * len(ordered) + 0.5 - 1e-9)))
    return ordered[min(rank, len(ordered)) - 1]


def latency_summary(seconds: list[float]) -> dict:
    milliseconds = [1000.0 * value for value in seconds]
    return {
        "count": len(milliseconds),
        "p50_ms": percentile(milliseconds, 50), "p90_ms": percentile(milliseconds, 90),
        "p99_ms": percentile(milliseconds, 99), "max_ms": max(milliseconds) if milliseconds else None,
    }


def texture_png(seed: int) -> bytes:
    """A distinct 64² RGBA PNG per seed (noise, so no two are alike)."""
    import numpy as np
    from PIL import Image

    pixels = np.random.default_rng(seed).integers(0, 256, (TEXTURE_SIZE, TEXTURE_SIZE, 4), dtype=np.uint8)
    pixels[..., 3] = 255
    buffer = io.BytesIO()
    Image.fromarray(pixels, "RGBA").save(buffer, format="PNG")
    return buffer.getvalue()


# ------------------------------------------------------------------------------------------ stack


@dataclass
class Stack:
    """redis-server, uvicorn and Celery workers on one temporary data folder (loopback only)."""

    root: Path
    workers: int
    processes: list[subprocess.Popen] = field(default_factory=list)
    port: int = 0
    key: str = ""
    settings: object = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _spawn(self, command: list[str], env: dict[str, str], log: str) -> subprocess.Popen:
        with open(self.root / log, "wb") as handle:
            process = subprocess.Popen(command, env=env, stdout=handle, stderr=subprocess.STDOUT, cwd=str(self.root))
        self.processes.append(process)
        return process

    def start(self) -> "Stack":
        from crowdbake.settings import Settings
        from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
        from crowdbake.storage.keys import create_api_key

        redis_port = free_port()
        self._spawn([shutil.which("redis-server") or "redis-server", "--port", str(redis_port), "--bind", "127.0.0.1", "--save", "",
                     "--appendonly", "no", "--dir", str(self.root)], dict(os.environ), "redis.log")
        data = self.root / "data"
        env = {key: value for key, value in os.environ.items() if not key.startswith("CROWDBAKE_")}
        env.update({
            "CROWDBAKE_DATA_DIR": str(data), "CROWDBAKE_BROKER_URL": f"redis://127.0.0.1:{redis_port}/0",
            "CROWDBAKE_QUEUE": f"load-{uuid.uuid4().hex[:8]}", "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "osmesa"),
            "PYTHONPATH": os.pathsep.join(filter(None, [str(SERVICES_DIR), os.environ.get("PYTHONPATH", "")])),
        })
        self.settings = Settings(data_dir=data)
        self.settings.ensure_dirs()
        engine = make_engine(self.settings.database_url)
        migrate(engine)
        with session_scope(make_sessionmaker(engine)) as session:
            self.key, _ = create_api_key(session, "upload,bake,publish,read", "load benchmark")
        engine.dispose()
        self.port = free_port()
        self._spawn([sys.executable, "-m", "uvicorn", "--factory", "crowdbake.api.app:create_app", "--host", "127.0.0.1",
                     "--port", str(self.port), "--log-level", "warning"], env, "api.log")
        for index in range(self.workers):
            self._spawn([sys.executable, "-m", "celery", "-A", "crowdbake.jobs.celery_app", "worker", "--pool", "prefork", "--concurrency", "1",
                         "--queues", env["CROWDBAKE_QUEUE"], "--hostname", f"load{index}-{uuid.uuid4().hex[:6]}@%h", "--loglevel", "INFO",
                         "--without-gossip", "--without-mingle"], env, f"worker-{index}.log")
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.url}/ready", timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"the API did not become ready within {START_TIMEOUT_S} s; see {self.root}/api.log")

    def stop(self) -> None:
        for process in reversed(self.processes):
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for process in self.processes:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


# -------------------------------------------------------------------------------------- phases


def concurrent_uploads(stack: Stack, uploads: int, duplicates: int) -> tuple[dict, list[str]]:
    """Phase 1: distinct textures and copies of one, all at once. Returns (figures, problems)."""
    bodies = [(f"diffuse_{index}.png", texture_png(index)) for index in range(uploads)]
    copy = texture_png(uploads)
    bodies += [("diffuse_copy.png", copy)] * duplicates
    headers = {"Authorization": f"Bearer {stack.key}"}
    limits = httpx.Limits(max_connections=len(bodies), max_keepalive_connections=len(bodies))
    barrier = threading.Barrier(len(bodies))

    with httpx.Client(base_url=stack.url, headers=headers, timeout=120, limits=limits) as client:
        def upload(item):
            name, data = item
            barrier.wait()  # every request leaves together
            started = time.perf_counter()
            response = client.post("/v1/assets/textures", files={"file": (name, data)})
            return name, response.status_code, response.json().get("id"), time.perf_counter() - started

        started = time.perf_counter()
        with ThreadPoolExecutor(max_workers=len(bodies)) as pool:
            results = list(pool.map(upload, bodies))
        wall = time.perf_counter() - started

    problems = []
    distinct = [result for result in results if result[0] != "diffuse_copy.png"]
    copies = [result for result in results if result[0] == "diffuse_copy.png"]
    if any(status != 201 for _, status, _, _ in distinct):
        problems.append(f"distinct uploads answered {sorted({status for _, status, _, _ in distinct})}, expected 201 each")
    if len({asset for _, _, asset, _ in distinct}) != uploads:
        problems.append("distinct uploads did not become distinct assets")
    if copies and (len({asset for _, _, asset, _ in copies}) != 1 or sorted(status for _, status, _, _ in copies) != [200] * (duplicates - 1) + [201]):
        problems.append(f"{duplicates} copies gave assets {sorted({asset for _, _, asset, _ in copies})} with statuses "
                        f"{sorted(status for _, status, _, _ in copies)}, expected one asset, one 201 and the rest 200")
    stored = sum(1 for _ in Path(stack.settings.blob_dir, "sha256").rglob("*") if _.is_file())
    expected_blobs = uploads + (1 if duplicates else 0)
    if stored != expected_blobs:
        problems.append(f"{stored} blobs stored, expected {expected_blobs}")
    figures = {"requests": len(bodies), "distinct": uploads, "copies": duplicates, "wall_s": round(wall, 3),
               "uploads_per_s": round(len(bodies) / wall, 1), "latency": latency_summary([seconds for *_, seconds in results])}
    return figures, problems


def upload_sample(client: httpx.Client, sample: Path) -> dict:
    character = client.post("/v1/assets/characters", files={"file": ("character.glb", (sample / "character.glb").read_bytes())})
    cloth = client.post("/v1/assets/cloth", files={"cache": ("cloth.pc2", (sample / "cloth.pc2").read_bytes()),
                                                   "mesh": ("cloth.obj", (sample / "cloth.obj").read_bytes())})
    for response in (character, cloth):
        if response.status_code not in (200, 201):
            raise RuntimeError(f"uploading the sample failed: {response.status_code} {response.text[:300]}")
    return {"character": character.json()["id"], "cloth": cloth.json()["id"]}


def queued_bakes(stack: Stack, sample: Path, bakes: int, clients: int, timeout: float) -> tuple[dict, list[str]]:
    """Phase 2: `bakes` bakes submitted at once, API latency measured while they run."""
    headers = {"Authorization": f"Bearer {stack.key}"}
    problems: list[str] = []
    with httpx.Client(base_url=stack.url, headers=headers, timeout=60) as client:
        ids = upload_sample(client, sample)
        run = uuid.uuid4().hex[:6]
        bodies = [{"name": "load-walker", "version": f"{run}.{index}", **ids, "params": SMALL_BAKE_PARAMS} for index in range(bakes)]
        started = time.perf_counter()
        with ThreadPoolExecutor(max_workers=min(bakes, 16)) as pool:
            created = list(pool.map(lambda body: client.post("/v1/bakes", json=body), bodies))
        if any(response.status_code != 202 for response in created):
            problems.append(f"bake submissions answered {sorted({response.status_code for response in created})}, expected 202 each")
        bake_ids = [response.json()["id"] for response in created if response.status_code == 202]
        if len(set(bake_ids)) != len(bake_ids):
            problems.append("two submissions returned the same bake")

        latencies: list[float] = []
        errors: list[str] = []
        done = threading.Event()

        def read_api(seed: int) -> None:
            chooser = random.Random(seed)
            with httpx.Client(base_url=stack.url, headers=headers, timeout=30) as reader:
                while not done.is_set():
                    path = chooser.choice([f"/v1/bakes/{chooser.choice(bake_ids)}", "/v1/bakes?limit=20", "/v1/assets?limit=10", "/health"])
                    clock = time.perf_counter()
                    try:
                        status = reader.get(path).status_code
                    except httpx.HTTPError as error:
                        errors.append(f"{path}: {type(error).__name__}")
                        continue
                    latencies.append(time.perf_counter() - clock)
                    if status != 200:
                        errors.append(f"{path}: {status}")
                    time.sleep(CLIENT_PAUSE_S)

        readers = [threading.Thread(target=read_api, args=(seed,), daemon=True) for seed in range(clients)]
        for thread in readers:
            thread.start()
        deadline = time.monotonic() + timeout
        states: dict[str, str] = {}
        try:
            while time.monotonic() < deadline:
                listing = client.get("/v1/bakes", params={"name": "load-walker", "limit": 500}).json()["data"]
                states = {bake["id"]: bake["state"] for bake in listing if bake["id"] in set(bake_ids)}
                if len(states) == len(bake_ids) and all(state in FINAL_STATES for state in states.values()):
                    break
                time.sleep(POLL_S)
        finally:
            wall = time.perf_counter() - started
            done.set()
            for thread in readers:
                thread.join(timeout=60)
        unfinished = [bake_id for bake_id in bake_ids if states.get(bake_id) not in FINAL_STATES]
        if unfinished:
            problems.append(f"{len(unfinished)} bakes not finished within {timeout} s")
        failed = {bake_id: state for bake_id, state in states.items() if state != "succeeded"}
        if failed:
            problems.append(f"bakes that did not succeed: {failed}")
        if errors:
            problems.append(f"{len(errors)} API reads failed during the bakes, first {errors[0]}")
        problems += exactly_once(stack, bake_ids, [body["version"] for body in bodies])

    figures = {"bakes": bakes, "workers": stack.workers, "wall_s": round(wall, 2), "bakes_per_minute": round(60.0 * bakes / wall, 2),
               "api_latency_during_bakes": latency_summary(latencies), "api_read_errors": len(errors), "params": SMALL_BAKE_PARAMS}
    return figures, problems


def exactly_once(stack: Stack, bake_ids: list[str], versions: list[str]) -> list[str]:
    """From the database: one success and one publish per bake, one bundle per version, nothing else."""
    from sqlalchemy import select

    from crowdbake.storage.db import make_engine, make_sessionmaker
    from crowdbake.storage.models import BakeLog, Bundle

    problems = []
    engine = make_engine(stack.settings.database_url)
    with make_sessionmaker(engine)() as session:
        for bake_id in bake_ids:
            lines = [row.message for row in session.scalars(select(BakeLog).where(BakeLog.bake_id == bake_id))]
            succeeded, published = lines.count("bake succeeded"), sum(line.startswith("publish finished") for line in lines)
            if (succeeded, published) != (1, 1):
                problems.append(f"bake {bake_id}: {succeeded} successes and {published} publishes, expected 1 and 1")
        bundles = sorted(bundle.version for bundle in session.scalars(select(Bundle).where(Bundle.name == "load-walker")))
    engine.dispose()
    if bundles != sorted(versions):
        problems.append(f"bundles {bundles} differ from the submitted versions {sorted(versions)}")
    return problems


def run_load(sample: Path, uploads: int = 50, duplicates: int = 10, bakes: int = 20, workers: int = 2, clients: int = 4,
             timeout: float = 900.0, root: Path | None = None) -> dict:
    """Start the stack, run both phases, stop it. Returns the figures with a list of `problems` (empty
    when nothing was lost, duplicated or failed)."""
    own_root = root is None
    root = Path(tempfile.mkdtemp(prefix="crowdbake-load-")) if own_root else Path(root)
    root.mkdir(parents=True, exist_ok=True)
    stack = Stack(root, workers).start()
    load_before = os.getloadavg()
    try:
        upload_figures, upload_problems = concurrent_uploads(stack, uploads, duplicates)
        bake_figures, bake_problems = queued_bakes(stack, sample, bakes, clients, timeout)
    finally:
        stack.stop()
        if own_root:
            shutil.rmtree(root, ignore_errors=True)
    return {
        "uploads": upload_figures, "bakes": bake_figures, "problems": upload_problems + bake_problems,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "load_average_before": load_before, "load_average_after": os.getloadavg()},
    }


def ensure_sample(folder: Path) -> Path:
    if not (folder / "sample.json").is_file():
        from crowdbake.sample.generate import generate_sample

        print(f"generating the sample into {folder} ...", flush=True)
        generate_sample(folder, garment="loose", cycles=3, seed=1, cycle_frames=24, texture_size=64)
    return folder


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--uploads", type=int, default=50, help="distinct concurrent uploads (default 50)")
    parser.add_argument("--duplicates", type=int, default=10, help="concurrent copies of one more upload (default 10)")
    parser.add_argument("--bakes", type=int, default=20, help="bakes queued at once (default 20)")
    parser.add_argument("--workers", type=int, default=2, help="Celery workers, one process each (default 2)")
    parser.add_argument("--clients", type=int, default=4, help="threads reading the API while the bakes run (default 4)")
    parser.add_argument("--sample", type=Path, help="a `crowdbake sample` folder (default: generate out/bench/load-sample)")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds the bakes may take (default 900)")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench" / "load.json")
    args = parser.parse_args()
    if shutil.which("redis-server") is None:
        print("load_service: redis-server is not installed", file=sys.stderr)
        return 2
    sample = ensure_sample(args.sample or REPO / "out" / "bench" / "load-sample")
    result = run_load(sample, args.uploads, args.duplicates, args.bakes, args.workers, args.clients, args.timeout)
    uploads, bakes = result["uploads"], result["bakes"]
    latency = bakes["api_latency_during_bakes"]
    print(f"uploads: {uploads['requests']} at once ({uploads['distinct']} distinct + {uploads['copies']} copies) in {uploads['wall_s']:.2f} s, "
          f"{uploads['uploads_per_s']:.1f}/s, latency p50 {uploads['latency']['p50_ms']:.0f} ms p99 {uploads['latency']['p99_ms']:.0f} ms")
    print(f"bakes:   {bakes['bakes']} queued on {bakes['workers']} workers in {bakes['wall_s']:.1f} s = {bakes['bakes_per_minute']:.1f} bakes/min")
    print(f"API while baking: {latency['count']} reads, p50 {latency['p50_ms']:.1f} ms, p90 {latency['p90_ms']:.1f} ms, "
          f"p99 {latency['p99_ms']:.1f} ms, max {latency['max_ms']:.1f} ms, {bakes['api_read_errors']} errors")
    print("lost or duplicated: none" if not result["problems"] else "PROBLEMS:\n  " + "\n  ".join(result["problems"]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0 if not result["problems"] else 1


if __name__ == "__main__":
    sys.exit(main())
