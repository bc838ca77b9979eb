"""Hostile uploads against a real API: status, seconds and peak memory of the API process per input.

    PYTHONPATH=services:services/tests:tests python services/benchmarks/bench_hostile.py [--out out/bench/hostile.json]

Starts the API (uvicorn, one process, the deploy manifests' options, default limits) on loopback with a
temporary data folder, then sends each input of tests/corpus.py's `hostile_inputs()` once (full size:
a 10^7-element zero-filled accessor, a 144 Mpx PNG in a .glb, 200 x 1 MiB OBJ frames in a zip, a 32 MiB
OBJ...), then the hostile requests of tests/test_hostile_requests.py: bodies without a valid key or over
their route's limit (sent over a raw socket until the server answers) and timelines claiming frames they
do not hold. For each it records the status, the seconds until the answer, the API's peak resident memory
above what it held before (Linux: /proc/PID/status VmHWM, reset before each request by writing 5 to
/proc/PID/clear_refs), and the median latency of /health polled meanwhile (the event loop stays free
while uploads are parsed in the thread pool). Prints one line per input and writes the JSON.

The target, for every input: an answer in seconds, within +300 MiB of the API's memory, and never a
5xx: a 4xx for all but the node chain, which is a valid character (201) that a quadratic check once
took 18.7 s to load, and the timeline of 10,000 clips (valid, 201). The exit status is 1 when an input misses the target.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[2]
for folder in (REPO / "services", REPO / "services" / "tests", REPO / "tests"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

MiB = 1 << 20


def _status_kib(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def reset_peak(pid: int) -> None:
    """Reset VmHWM to the current RSS (Linux >= 4.0, proc(5) clear_refs '5')."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def measure(client: httpx.Client, pid: int, route: str, files: dict) -> dict:
    baseline = _status_kib(pid, "VmRSS")
    reset_peak(pid)
    health: list[float] = []
    done = threading.Event()

    def poll_health() -> None:
        with httpx.Client(base_url=str(client.base_url), timeout=30) as poller:
            while not done.is_set():
                started = time.perf_counter()
                poller.get("/health")
                health.append(time.perf_counter() - started)
                done.wait(0.05)

    poller = threading.Thread(target=poll_health)
    poller.start()
    started = time.perf_counter()
    response = client.post(route, files=files)
    seconds = time.perf_counter() - started
    done.set()
    poller.join()
    peak = _status_kib(pid, "VmHWM")
    body = response.json() if response.headers.get("content-type", "").endswith("json") else {}
    return {
        "status": response.status_code, "problem": body.get("type"), "detail": (body.get("errors") or [{}])[0].get("message", body.get("detail")),
        "seconds": round(seconds, 3), "peak_mib_above_baseline": round((peak - baseline) / 1024, 1),
        "baseline_mib": round(baseline / 1024, 1), "health_median_ms": round(1000 * statistics.median(health), 1) if health else None,
        "bytes_sent": sum(len(entry[1]) for entry in files.values()),
    }


def measure_raw(port: int, pid: int, head: bytes, chunks) -> dict:
    """As `measure`, for a request sent byte for byte (headers that announce more than is sent)."""
    from test_hostile_requests import send_until_answered

    baseline = _status_kib(pid, "VmRSS")
    reset_peak(pid)
    answer, sent, seconds = send_until_answered(port, head, chunks)
    peak = _status_kib(pid, "VmHWM")
    head_part, _, body_part = answer.partition(b"\r\n\r\n")
    try:
        body = json.loads(body_part)
    except ValueError:
        body = {}
    return {"status": int(head_part.split(b" ", 2)[1]) if head_part else None, "problem": body.get("type"), "detail": body.get("detail"),
            "seconds": round(seconds, 3), "peak_mib_above_baseline": round((peak - baseline) / 1024, 1), "baseline_mib": round(baseline / 1024, 1),
            "health_median_ms": None, "bytes_sent": sent}


def body_inputs(keys: dict[str, str]) -> list[tuple[str, str, bytes, object]]:
    """(name, route, request head, body chunks) of the hostile bodies."""
    from test_hostile_requests import _chunked, _head, _zeros

    json_type = {"Content-Type": "application/json"}
    return [
        ("200 MiB chunked, no key", "/v1/bakes/check", _head("POST", "/v1/bakes/check", {**json_type, "Transfer-Encoding": "chunked"}), _chunked(200 * MiB)),
        ("200 MiB announced, no key", "/v1/bakes", _head("POST", "/v1/bakes", {**json_type, "Content-Length": str(200 * MiB)}), _zeros(200 * MiB)),
        ("6 GiB announced, bake key", "/v1/bakes", _head("POST", "/v1/bakes", {**json_type, "Content-Length": str(6 << 30),
                                                                                "Authorization": f"Bearer {keys['bake']}"}), []),
        ("200 MiB chunked, bake key", "/v1/bakes", _head("POST", "/v1/bakes", {**json_type, "Transfer-Encoding": "chunked",
                                                                                "Authorization": f"Bearer {keys['bake']}"}), _chunked(200 * MiB)),
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="out/bench/hostile.json", help="where to write the JSON")
    args = parser.parse_args()

    from corpus import hostile_inputs
    from service_fixtures import free_port, local_api_key, service_env, start_api
    from test_hostile_requests import TIMELINES

    print("building the inputs...", file=sys.stderr)
    inputs = hostile_inputs() + [(f"timeline: {name}", "/v1/assets/timelines", {"timeline": ("timeline.json", document)})
                                 for name, (document, _, _) in TIMELINES.items()]
    with tempfile.TemporaryDirectory(prefix="bench-hostile-") as folder:
        root = Path(folder)
        key = local_api_key(root / "data", "upload", "bench")
        keys = {"bake": local_api_key(root / "data", "bake", "bench bake")}
        port = free_port()
        api = start_api(service_env(root / "data", "filesystem://"), port, root / "api.log")
        results = []
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {key}"}, timeout=600) as client:
                for name, route, files in inputs:
                    row = {"input": name, "route": route, **measure(client, api.popen.pid, route, files)}
                    results.append(row)
                    print(f"{row['status']}  {row['seconds']:7.2f} s  +{row['peak_mib_above_baseline']:7.1f} MiB  "
                          f"health p50 {row['health_median_ms']} ms  {name}: {row['detail']}")
            for name, route, head, chunks in body_inputs(keys):
                row = {"input": f"body: {name}", "route": route, **measure_raw(port, api.popen.pid, head, chunks)}
                results.append(row)
                print(f"{row['status']}  {row['seconds']:7.2f} s  +{row['peak_mib_above_baseline']:7.1f} MiB  "
                      f"{row['bytes_sent'] / MiB:.1f} MiB sent  {row['input']}: {row['detail']}")
        finally:
            api.stop()
    report = {"machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg(), "platform": platform.platform()}, "results": results}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    ok = all(row["status"] is not None and row["status"] < 500 and row["seconds"] < 10 and row["peak_mib_above_baseline"] <= 300 for row in results)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
