"""A broker that stops answering, and processes that die: the API stays up, nothing is orphaned.

A stopped Redis (SIGSTOP, as a partition or a stalled fsync looks from outside) still accepts TCP
connections but never answers. Before readiness bounded its own wait, 45 keyless `/ready` calls held
every thread of the request pool and `/health` stopped answering; a killed `crowdbake serve` left its
Celery worker running and taking jobs.
"""
from __future__ import annotations

import concurrent.futures
import os
import signal
import subprocess
import sys
import time

import httpx
import pytest

from crowdbake.api.readiness import READY_FRESH_S
from reliability_fixtures import RedisServer, child_pids, make_service
from service_fixtures import free_port

# slow: real Redis, API and serve processes for tens of seconds; runs in CI (CROWDBAKE_SLOW_TESTS=1)
pytestmark = pytest.mark.slow

# Readiness callers fired at once: more than the request pool's 40 threads (anyio's default).
STORM = 45


@pytest.fixture
def frozen_redis_service(tmp_path):
    redis = RedisServer(tmp_path / "redis").start()
    service = make_service(tmp_path / "service", redis.url)
    service.start_api()
    yield service, redis
    os.kill(redis.popen.pid, signal.SIGCONT)
    service.stop()
    redis.stop()


def test_health_answers_within_a_second_while_the_broker_is_frozen(frozen_redis_service):
    service, redis = frozen_redis_service
    assert httpx.get(f"{service.url}/ready", timeout=10).status_code == 200
    os.kill(redis.popen.pid, signal.SIGSTOP)
    time.sleep(READY_FRESH_S + 0.2)  # past the shared answer of the probe above
    with concurrent.futures.ThreadPoolExecutor(STORM) as pool:
        started = time.monotonic()
        storm = [pool.submit(httpx.get, f"{service.url}/ready", timeout=30) for _ in range(STORM)]
        time.sleep(0.5)  # let the storm arrive first
        health_started = time.monotonic()
        health = httpx.get(f"{service.url}/health", timeout=10)
        health_s = time.monotonic() - health_started
        answers = [future.result() for future in storm]
        storm_s = time.monotonic() - started
    assert health.status_code == 200 and health_s < 1.0, f"/health took {health_s:.2f} s"
    assert {answer.status_code for answer in answers} == {503}
    assert storm_s < 10, f"{STORM} /ready calls took {storm_s:.1f} s"
    problem = answers[0].json()
    assert [error["field"] for error in problem["errors"]] == ["broker"]
    # Keyless readiness names no host or port.
    assert str(redis.port) not in answers[0].text and "127.0.0.1" not in answers[0].text
    # Other routes still answer from the pool.
    assert httpx.get(f"{service.url}/v1/bundles", headers=service.auth("read"), timeout=10).status_code == 200
    os.kill(redis.popen.pid, signal.SIGCONT)
    deadline = time.monotonic() + 15
    while httpx.get(f"{service.url}/ready", timeout=10).status_code != 200:
        assert time.monotonic() < deadline, "readiness did not recover after the broker came back"
        time.sleep(0.3)


def test_a_killed_serve_takes_its_worker_with_it(tmp_path):
    """SIGKILL of `crowdbake serve` used to orphan its Celery worker, which kept taking jobs."""
    port = free_port()
    env = {key: value for key, value in os.environ.items() if not key.startswith("CROWDBAKE_")}
    env.update(CROWDBAKE_DATA_DIR=str(tmp_path / "data"), CROWDBAKE_BROKER_URL="filesystem://", PYTHONUNBUFFERED="1")
    log = open(tmp_path / "serve.log", "wb")
    serve = subprocess.Popen([sys.executable, "-m", "crowdbake", "serve", "--port", str(port), "--workers", "1"],
                             env=env, stdout=log, stderr=subprocess.STDOUT)
    log.close()
    try:
        deadline = time.monotonic() + 90
        workers: list[int] = []
        while not workers:
            assert serve.poll() is None, (tmp_path / "serve.log").read_text()
            assert time.monotonic() < deadline, "serve started no worker"
            workers = child_pids(serve.pid)
            time.sleep(0.3)
        serve.kill()
        serve.wait()
        deadline = time.monotonic() + 60
        while any(_alive(pid) for pid in workers):
            assert time.monotonic() < deadline, f"worker {workers} outlived its serve"
            time.sleep(0.3)
    finally:
        if serve.poll() is None:
            serve.kill()
        for pid in child_pids(serve.pid):
            os.kill(pid, signal.SIGKILL)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False
