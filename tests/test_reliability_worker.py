"""Workers die in the middle of a bake: nothing is lost and nothing is done twice.

Real processes: a private redis-server, uvicorn and a Celery worker (prefork) on a temporary data
folder, baking the procedural sample. The faults are real SIGKILLs, sent once the impostor fan-out is
under way:

* a pool process rendering impostor views is killed (what the kernel's OOM killer does): Celery's
  `acks_late` + `reject_on_worker_lost` put the message back, the idempotent stage reruns, the
  database barrier lets exactly one finishing task enqueue `pack`, and the bundle is byte-identical
  to the same bake run undisturbed in one process (crowdbake.stages.runner.run_bake);
* a poison job kills every pool process that runs it: it stops after its retry budget and says why.
  Regression (fixed in crowdbake.jobs.tasks.run_stage): `reject_on_worker_lost` handed such a message
  out forever; redeliveries are now counted per task (records.record_redelivery) and the bake fails
  once a task has been redelivered more than CROWDBAKE_TASK_MAX_RETRIES times;
* the whole worker is killed (main process and pool): its messages wait in Redis for the visibility
  timeout, and cancel + retry recovers the bake from the stages already done.
"""
from __future__ import annotations

import os
import signal
import time

import pytest
from sqlalchemy import select

from crowdbake.formats.bundle import verify_bundle
from service_fixtures import STORES, database_env, published_files, store_env
from reliability_fixtures import (
    SLOW_IMPOSTOR_PARAMS,
    RedisServer,
    bake_body,
    busy_children,
    child_pids,
    cpu_ticks,
    kill,
    make_service,
    reference_bake,
    tree_bytes,
    upload_sample,
    wait_for_bake,
)

pytestmark = [pytest.mark.integration, pytest.mark.slow]

BAKE_TIMEOUT_S = 240
# Kill rounds tried before giving up on landing a signal inside an impostor task.
MAX_KILL_ROUNDS = 40
# The poison test's retry budget, and the kills after which it must have given up: a part may run once
# plus POISON_RETRIES times; the next delivery fails the bake. With 6 impostor parts, by pigeonhole at
# most 6 x (POISON_RETRIES + 1) kills leave some part with a delivery past its budget. A kill can also
# land on a pool process between two tasks (costing no part anything): twice that bound leaves room.
POISON_RETRIES = 1
POISON_MAX_KILLS = 2 * 6 * (POISON_RETRIES + 1)
POISON_CPU_S = 0.5
# Seconds without any change of a crashed bake's stages after which it counts as stalled.
STALL_S = 6.0
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def running_service(tmp_path, concurrency: int, store: str = "local", **settings_env: str):
    backends = {**database_env(), **store_env(store)} if store != "local" else {}  # PostgreSQL + S3 when the tests have them
    settings_env = {**backends, **settings_env}
    redis = RedisServer(tmp_path / "redis").start()
    service = make_service(tmp_path / "service", redis.url, **settings_env)
    service.start_api()
    service.start_worker(concurrency=concurrency)
    try:
        yield service
    finally:
        service.stop()
        redis.stop()


@pytest.fixture
def service(tmp_path):
    yield from running_service(tmp_path, concurrency=2)


@pytest.fixture(params=STORES)
def service_on_each_store(tmp_path, request):
    """The service on local folders, and on PostgreSQL + S3 when the tests have those servers."""
    yield from running_service(tmp_path, concurrency=2, store=request.param)


@pytest.fixture
def poisoned_service(tmp_path):
    yield from running_service(tmp_path, concurrency=1, CROWDBAKE_TASK_MAX_RETRIES=str(POISON_RETRIES))


def test_sigkill_during_impostor_views_completes_exactly_once_with_identical_bytes(service_on_each_store, sample, tmp_path):
    from crowdbake.storage.models import BakeLog, Bundle

    service = service_on_each_store
    worker = service.workers[0]
    with service.client() as client:
        ids = upload_sample(client, sample)
        created = client.post("/v1/bakes", json=bake_body(ids, "killed-walker", "1.0.0", SLOW_IMPOSTOR_PARAMS))
        assert created.status_code == 202, created.text
        bake_id = created.json()["id"]

        # Wait for the fan-out, then SIGKILL every pool process that is busy rendering.
        killed: list[int] = []
        for _ in range(MAX_KILL_ROUNDS * 20):
            bake = client.get(f"/v1/bakes/{bake_id}").json()
            impostors = next(stage for stage in bake["stages"] if stage["stage"] == "impostors")
            assert bake["state"] not in ("succeeded", "failed"), f"the bake ended before a kill landed: {bake['state']} {bake['error']}"
            if impostors["state"] == "running" and impostors["done"] < impostors["total"]:
                busy = busy_children(worker.popen.pid, window_s=0.2, min_ticks=3)
                killed += [pid for pid in busy if kill(pid, signal.SIGKILL)]
                if killed:
                    break
            time.sleep(0.05)
        assert killed, "no pool process was caught rendering impostor views"
        killed_at = time.monotonic()

        bake = wait_for_bake(client, bake_id, BAKE_TIMEOUT_S, explain=lambda: worker.tail(60))
        print(f"\nworker kill: {len(killed)} pool processes killed during the impostor views; succeeded {time.monotonic() - killed_at:.1f} s later")
        assert bake["state"] == "succeeded", (bake["error"], worker.tail(80))

    log = worker.log.read_text(errors="replace")
    # The kill hit a running task (Celery says so), and the master replaced the dead pool processes.
    assert "WorkerLostError" in log and "signal 9" in log, log[-4000:]

    with service.sessions()() as session:
        lines = [row.message for row in session.scalars(select(BakeLog).where(BakeLog.bake_id == bake_id).order_by(BakeLog.id))]
        bundles = session.scalars(select(Bundle).where(Bundle.name == "killed-walker")).all()
    # Exactly once: one pack, one publish, one success, one bundle record.
    assert sum(line.startswith("pack finished") for line in lines) == 1, lines
    assert sum(line.startswith("publish finished") for line in lines) == 1, lines
    assert lines.count("bake succeeded") == 1, lines
    assert len(bundles) == 1 and bundles[0].bake_id == bake_id
    # The killed tasks really ran again: Redis handed them back and the worker recorded it.
    assert sum("delivered again" in line for line in lines) >= 1, lines

    got = published_files(service.settings, "killed-walker", "1.0.0")
    reference = reference_bake(service, bake, tmp_path / "reference")
    verify_bundle(reference)
    expected = tree_bytes(reference)
    assert sorted(got) == sorted(expected)
    differing = [path for path in expected if got[path] != expected[path]]
    assert not differing, f"files differ from the undisturbed bake: {differing}"
    print(f"worker kill: all {len(expected)} files of the bundle (manifest included) identical to the undisturbed bake")


def test_a_job_that_kills_its_worker_every_time_stops_after_its_retry_budget(poisoned_service, sample):
    """A poison job: every pool process that runs this bake's impostor views dies (SIGKILL, as the OOM
    killer would do it). `reject_on_worker_lost` puts the message back each time, so without a budget
    the job would loop forever; with one, the bake fails once a part has been redelivered more than
    CROWDBAKE_TASK_MAX_RETRIES times, and its error says which part and why."""
    service = poisoned_service
    worker = service.workers[0]
    with service.client() as client:
        ids = upload_sample(client, sample)
        created = client.post("/v1/bakes", json=bake_body(ids, "poison-walker", "1.0.0", SLOW_IMPOSTOR_PARAMS))
        assert created.status_code == 202, created.text
        bake_id = created.json()["id"]
        killed: set[int] = set()
        deadline = time.monotonic() + BAKE_TIMEOUT_S
        while (bake := client.get(f"/v1/bakes/{bake_id}").json())["state"] not in ("succeeded", "failed", "cancelled"):
            assert time.monotonic() < deadline, worker.tail(60)
            assert len(killed) <= POISON_MAX_KILLS, f"still {bake['state']} after {len(killed)} kills: the poison job loops\n{worker.tail(40)}"
            impostors = next(stage for stage in bake["stages"] if stage["stage"] == "impostors")
            if impostors["state"] in ("running", "retrying"):
                # A pool process is forked fresh after each kill, so its CPU time is this task's: past
                # POISON_CPU_S it is rendering (the task's bookkeeping before that takes milliseconds).
                for pid in child_pids(worker.popen.pid):
                    if pid not in killed and cpu_ticks(pid) >= POISON_CPU_S * CLOCK_TICKS and kill(pid):
                        killed.add(pid)
            time.sleep(0.05)
    assert bake["state"] == "failed", bake
    print(f"\npoison job: stopped after {len(killed)} pool processes were killed: {bake['error']['detail'][:90]}")
    error = bake["error"]
    assert error["stage"] == "impostors" and error["type"] == "worker-lost", error
    assert "impostors/f" in error["detail"] and f"more than {POISON_RETRIES}" in error["detail"], error
    assert 2 <= len(killed) <= POISON_MAX_KILLS
    # The worker itself survived its pool processes and still serves other bakes.
    assert worker.popen.poll() is None


def test_a_whole_worker_crash_is_recovered_by_cancel_and_retry(service, sample):
    """The whole worker dies (SIGKILL of its main process and its pool, as when a machine is lost).
    Nobody is left to hand its messages back: they stay unacknowledged in Redis until the visibility
    timeout (REDIS_VISIBILITY_TIMEOUT_S, 6 h), so the bake stops progressing even with a new worker.
    Nothing is lost, though: cancel + retry (a new attempt) finishes it from the stages already done,
    and it is published exactly once."""
    from crowdbake.jobs.celery_app import REDIS_VISIBILITY_TIMEOUT_S
    from crowdbake.storage.models import BakeLog, Bundle

    worker = service.workers[0]
    with service.client() as client:
        ids = upload_sample(client, sample)
        bake_id = client.post("/v1/bakes", json=bake_body(ids, "crashed-walker", "1.0.0", SLOW_IMPOSTOR_PARAMS)).json()["id"]
        deadline = time.monotonic() + BAKE_TIMEOUT_S
        while True:
            bake = client.get(f"/v1/bakes/{bake_id}").json()
            impostors = next(stage for stage in bake["stages"] if stage["stage"] == "impostors")
            if impostors["state"] == "running" and busy_children(worker.popen.pid, window_s=0.2, min_ticks=3):
                break
            assert bake["state"] not in ("succeeded", "failed") and time.monotonic() < deadline, bake
            time.sleep(0.05)
        pool = child_pids(worker.popen.pid)
        kill(worker.popen.pid)
        for pid in pool:
            kill(pid)
        worker.popen.wait(timeout=30)
        replacement = service.start_worker(concurrency=2)

        # The new worker runs what was still queued; what the dead one held waits for the timeout.
        stalled_since, last = time.monotonic(), None
        while time.monotonic() - stalled_since < STALL_S:
            bake = client.get(f"/v1/bakes/{bake_id}").json()
            progress = [(stage["state"], stage["done"]) for stage in bake["stages"]]
            if progress != last:
                stalled_since, last = time.monotonic(), progress
            assert time.monotonic() < deadline, replacement.tail(40)
            time.sleep(0.25)
        assert bake["state"] == "running" and REDIS_VISIBILITY_TIMEOUT_S > BAKE_TIMEOUT_S, bake
        stalled = next(stage for stage in bake["stages"] if stage["stage"] == "impostors")

        assert client.post(f"/v1/bakes/{bake_id}/cancel").status_code == 202
        assert client.post(f"/v1/bakes/{bake_id}/retry").status_code == 202
        retried_at = time.monotonic()
        bake = wait_for_bake(client, bake_id, BAKE_TIMEOUT_S, explain=lambda: replacement.tail(60))
        assert bake["state"] == "succeeded" and bake["attempt"] == 1, bake["error"]
        print(f"\nwhole worker crash: stalled at {stalled['done']}/{stalled['total']} impostor tasks for {STALL_S:.0f} s under a new worker; "
              f"cancel + retry succeeded in {time.monotonic() - retried_at:.1f} s")
    verify_bundle(service.settings.bundles_dir / "crashed-walker" / "1.0.0")
    with service.sessions()() as session:
        lines = [row.message for row in session.scalars(select(BakeLog).where(BakeLog.bake_id == bake_id))]
        bundles = session.scalars(select(Bundle).where(Bundle.name == "crashed-walker")).all()
    assert lines.count("bake succeeded") == 1 and sum(line.startswith("publish finished") for line in lines) == 1
    assert len(bundles) == 1
