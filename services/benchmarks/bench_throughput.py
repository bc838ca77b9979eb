"""Bake throughput of the service: bakes per minute with 1 and with 2 workers, and their ratio.

    PYTHONPATH=services python services/benchmarks/bench_throughput.py [--workers 1,2] [--bakes 12]
        [--broker auto|redis|filesystem] [--out out/bench/throughput.json]

For each worker count N, starts a fresh local service with `crowdbake serve --workers N` (the API and
one Celery worker with N prefork processes) on a private data folder, with a private `redis-server` on
loopback as the broker when one is installed (else Celery's filesystem broker), uploads the small
procedural sample once, bakes N warm-up bakes (untimed: each worker process imports the stages and
makes its GL context on its first task), then submits K bakes at once (distinct versions, so nothing
is deduplicated) and times them from the first submission to the last one finishing.

Bakes are small (a 3-cycle sample with 64² textures, 2 impostor frames x 4 azimuths x 2 elevations of
32² tiles), so the figure is about the service and its queue as much as about the bake itself. The
ratio 2-to-1 can reach at most the cores free: the JSON records the CPU count and the load average
before and after, since on a machine shared with other work both limit it.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

from service_bench import FINAL_STATES, SMALL_BAKE_PARAMS, free_port

SERVICES_DIR = Path(__file__).resolve().parents[1]
SAMPLE = dict(garment="loose", cycles=3, seed=1, cycle_frames=24, texture_size=64)
POLL_S = 0.25
START_TIMEOUT_S = 120
BAKE_TIMEOUT_S = 1800


def wait_until(check, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.2)
    raise RuntimeError(f"timed out waiting for {what}")


class Redis:
    """A private redis-server on loopback (no persistence), stopped on exit."""

    def __init__(self, folder: Path):
        self.port = free_port()
        self.process = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no", "--dir", str(folder)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        wait_until(self._answers, 20, "redis-server")
        self.url = f"redis://127.0.0.1:{self.port}/0"

    def _answers(self) -> bool:
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=1) as sock:
                sock.sendall(b"PING\r\n")
                return sock.recv(16).startswith(b"+PONG")
        except OSError:
            return False

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=20)


def environment(data: Path, broker: str | None) -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if not key.startswith("CROWDBAKE_")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(SERVICES_DIR), env.get("PYTHONPATH", "")]))
    env.setdefault("PYOPENGL_PLATFORM", "osmesa")
    env["CROWDBAKE_DATA_DIR"] = str(data)
    if broker:
        env["CROWDBAKE_BROKER_URL"] = broker
    return env


def upload_sample(client: httpx.Client, sample: Path) -> dict:
    def post(path: str, files: dict) -> str:
        response = client.post(path, files=files)
        response.raise_for_status()
        return response.json()["id"]

    character = post("/v1/assets/characters", {"file": ("character.glb", (sample / "character.glb").read_bytes())})
    cloth = post("/v1/assets/cloth", {"cache": ("cloth.pc2", (sample / "cloth.pc2").read_bytes()), "mesh": ("cloth.obj", (sample / "cloth.obj").read_bytes())})
    textures = {path.name: post("/v1/assets/textures", {"file": (path.name, path.read_bytes())}) for path in sorted((sample / "textures").glob("*.png"))}
    return {"character": character, "cloth": cloth, "textures": textures}


def bake_all(client: httpx.Client, assets: dict, versions: list[str]) -> tuple[float, list[dict]]:
    """Start a bake per version at once; seconds until the last one ended, and the bakes' records."""
    started = time.perf_counter()
    ids = []
    for version in versions:
        response = client.post("/v1/bakes", json={"name": "throughput", "version": version, **assets, "params": SMALL_BAKE_PARAMS})
        if response.status_code != 202:
            raise RuntimeError(f"bake {version} was not started: {response.status_code} {response.text}")
        ids.append(response.json()["id"])
    deadline = time.monotonic() + BAKE_TIMEOUT_S
    pending = set(ids)
    while pending:
        if time.monotonic() > deadline:
            raise RuntimeError(f"bakes still running after {BAKE_TIMEOUT_S} s: {sorted(pending)}")
        for bake_id in list(pending):
            if client.get(f"/v1/bakes/{bake_id}").json()["state"] in FINAL_STATES:
                pending.discard(bake_id)
        if pending:
            time.sleep(POLL_S)
    elapsed = time.perf_counter() - started
    bakes = [client.get(f"/v1/bakes/{bake_id}").json() for bake_id in ids]
    failed = [bake for bake in bakes if bake["state"] != "succeeded"]
    if failed:
        raise RuntimeError(f"{len(failed)} bakes did not succeed, first: {failed[0]['error']}")
    return elapsed, bakes


def run(workers: int, bakes: int, sample: Path, broker_kind: str, scratch: Path) -> dict:
    data = scratch / f"data-{workers}"
    redis = Redis(scratch) if broker_kind == "redis" else None
    env = environment(data, redis.url if redis else None)
    crowdbake = [sys.executable, "-m", "crowdbake"]
    key = subprocess.run([*crowdbake, "keys", "create", "--data", str(data), "--scopes", "upload,bake,publish", "--label", "bench"],
                         env=env, capture_output=True, text=True, check=True).stdout.strip()
    port = free_port()
    log = open(scratch / f"serve-{workers}.log", "wb")
    serve = subprocess.Popen([*crowdbake, "serve", "--data", str(data), "--port", str(port), "--workers", str(workers)],
                             env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        def ready() -> bool:
            if serve.poll() is not None:
                raise RuntimeError(f"crowdbake serve exited: {(scratch / f'serve-{workers}.log').read_text()[-2000:]}")
            try:
                return httpx.get(f"{url}/ready", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(ready, START_TIMEOUT_S, "the service")
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
            assets = upload_sample(client, sample)
            warmup, _ = bake_all(client, assets, [f"0.0.{k}-warmup" for k in range(workers)])
            load_before = os.getloadavg()
            seconds, records = bake_all(client, assets, [f"1.0.{k}" for k in range(bakes)])
            load_after = os.getloadavg()
    finally:
        serve.terminate()
        try:
            serve.wait(timeout=60)
        except subprocess.TimeoutExpired:
            serve.kill()
        log.close()
        if redis:
            redis.stop()
    stage_seconds = {stage["stage"]: [] for stage in records[0]["stages"]}
    for record in records:
        for stage in record["stages"]:
            stage_seconds[stage["stage"]].append(stage["seconds"] or 0.0)
    latencies = [(_time(r["finished_at"]) - _time(r["created_at"])) for r in records]
    return {
        "workers": workers,
        "bakes": bakes,
        "seconds": seconds,
        "bakes_per_minute": 60.0 * bakes / seconds,
        "warmup_seconds": warmup,
        "bake_latency_seconds": latencies,
        "stage_seconds_mean": {stage: sum(values) / len(values) for stage, values in stage_seconds.items()},
        "work_seconds_per_bake": sum(sum(values) for values in stage_seconds.values()) / bakes,
        "load_average_before": load_before[0],
        "load_average_after": load_after[0],
    }


def _time(text: str) -> float:
    import datetime as dt

    return dt.datetime.fromisoformat(text).timestamp()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", default="1,2", help="worker counts to measure, comma separated (default 1,2)")
    parser.add_argument("--bakes", type=int, default=12, help="timed bakes per worker count (default 12)")
    parser.add_argument("--broker", choices=("auto", "redis", "filesystem"), default="auto",
                        help="auto: a private redis-server when installed, else the filesystem broker")
    parser.add_argument("--out", type=Path, default=Path("out/bench/throughput.json"))
    args = parser.parse_args()
    counts = [int(value) for value in args.workers.split(",")]
    broker = args.broker if args.broker != "auto" else ("redis" if shutil.which("redis-server") else "filesystem")

    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    sys.path.insert(0, str(SERVICES_DIR))
    from crowdbake.sample.generate import generate_sample

    scratch = Path(tempfile.mkdtemp(prefix="crowdbake-throughput-"))
    try:
        sample = scratch / "sample"
        generate_sample(sample, **SAMPLE)
        runs = []
        for workers in counts:
            print(f"{workers} worker{'s' if workers > 1 else ''}: {args.bakes} bakes ({broker} broker) ...", flush=True)
            result = run(workers, args.bakes, sample, broker, scratch)
            runs.append(result)
            print(f"  {result['seconds']:.1f} s, {result['bakes_per_minute']:.2f} bakes/min "
                  f"(work {result['work_seconds_per_bake']:.1f} s per bake, load {result['load_average_before']:.1f})", flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    by_workers = {run["workers"]: run for run in runs}
    report = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "gl_platform": os.environ.get("PYOPENGL_PLATFORM")},
        "broker": broker,
        "sample": SAMPLE,
        "params": SMALL_BAKE_PARAMS,
        "command": " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]),
        "runs": runs,
    }
    if 1 in by_workers and 2 in by_workers:
        report["ratio_2_to_1"] = by_workers[2]["bakes_per_minute"] / by_workers[1]["bakes_per_minute"]
        print(f"2 workers / 1 worker: {report['ratio_2_to_1']:.2f}x")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
