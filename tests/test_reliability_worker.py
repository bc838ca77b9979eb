"""Workers die in the middle of a bake: nothing is lost and nothing is done twice.

Real processes: a private redis-server, uvicorn and a Celery worker (prefork) on a temporary data
folder, baking the procedural sample. The faults are real SIGKILLs, sent once the impostor fan-out is
under way:

* a pool process rendering impostor views is killed (what the kernel's OOM killer does): Celery's
  `acks_late` + `reject_on_worker_lost` put the message back, the idempotent stage reruns, the
  database barrier lets exactly one finishing task enqueue `pack`, and the bundle is byte-identical
  to the same bake run undisturbed in one process (crowdbake.stages.runner.run_bake);
* a poison job kills every pool process that runs it: it stops after its retry budget and says why.
  Regression (fixed in crowdbake.jobs.deliveries.run_stage): `reject_on_worker_lost` handed such a message
  out forever; a delivery that takes over the unit of a dead process counts one retry
  (records.claim_delivery) and the bake fails past CROWDBAKE_TASK_MAX_RETRIES;
* the whole worker is killed (its process group: main process and pool): its messages wait in Redis
  for the visibility timeout, but its running units stop beating and the API's sweeper re-queues them
  (crowdbake.jobs.sweeper); the bake finishes with no manual step, once, byte-identical.
"""
from __future__ import annotations

import os
import signal
import time

import pytest
from sqlalchemy import select

from crowdbake.formats.bundle import verify_bundle
from service_fixtures import database_env, published_files, store_env
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
# The lost-worker test's sweeper: heartbeats every 0.5 s, a unit without one for 4 s is re-queued,
# sweeps every 0.5 s (the defaults are 10 s, 60 s and 15 s).
LOST_WORKER_SETTINGS = {"CROWDBAKE_HEARTBEAT_INTERVAL": "0.5", "CROWDBAKE_HEARTBEAT_TIMEOUT": "4", "CROWDBAKE_SWEEP_INTERVAL": "0.5"}
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


# The kill lands on the richest store the tests have: PostgreSQL + S3 when scripts/test.sh started them
# (partial uploads to clean up, a second database), else local folders. The kill's handling does not
# depend on the store, and the other tests here run on local folders; one store keeps CI's time.
KILL_STORE = "s3" if os.environ.get("CROWDBAKE_TEST_S3_URL") else "local"


@pytest.fixture
def service_on_kill_store(tmp_path):
    """The service on KILL_STORE."""
    yield from running_service(tmp_path, concurrency=2, store=KILL_STORE)


@pytest.fixture
def poisoned_service(tmp_path):
    yield from running_service(tmp_path, concurrency=1, CROWDBAKE_TASK_MAX_RETRIES=str(POISON_RETRIES))


def test_sigkill_during_impostor_views_completes_exactly_once_with_identical_bytes(service_on_kill_store, sample, tmp_path):
    from crowdbake.storage.models import BakeLog, Bundle

    service = service_on_kill_store
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


@pytest.fixture
def lost_worker_service(tmp_path):
    """A service whose sweeper acts within seconds (heartbeats every 0.5 s, lost after 4 s), and a
    worker in a process group of its own, to be lost whole."""
    redis = RedisServer(tmp_path / "redis").start()
    service = make_service(tmp_path / "service", redis.url, **LOST_WORKER_SETTINGS)
    service.start_api()
    service.start_worker(concurrency=2, own_group=True)
    try:
        yield service
    finally:
        service.stop()
        redis.stop()


def test_a_lost_worker_is_recovered_by_the_sweeper_exactly_once_with_identical_bytes(lost_worker_service, sample, tmp_path):
    """The whole worker dies (SIGKILL of its process group: main process and pool, as when a machine
    is lost). Its messages stay unacknowledged in Redis for the visibility timeout, so before the
    heartbeats the bake stalled until someone cancelled and retried it. Now the running units stop
    beating, the API's sweeper re-queues them after CROWDBAKE_HEARTBEAT_TIMEOUT (a retry each, in the
    log), a fresh worker runs them, and the bake finishes with no manual step: once, and with the bytes
    of an undisturbed bake."""
    from crowdbake.storage.models import BakeLog, Bundle

    service = lost_worker_service
    worker = service.workers[0]
    with service.client() as client:
        ids = upload_sample(client, sample)
        bake_id = client.post("/v1/bakes", json=bake_body(ids, "lost-walker", "1.0.0", dict(SLOW_IMPOSTOR_PARAMS, close="hermite", accept_out_of_bounds=True))).json()["id"]
        deadline = time.monotonic() + BAKE_TIMEOUT_S
        while True:
            bake = client.get(f"/v1/bakes/{bake_id}").json()
            impostors = next(stage for stage in bake["stages"] if stage["stage"] == "impostors")
            if impostors["state"] == "running" and busy_children(worker.popen.pid, window_s=0.2, min_ticks=3):
                break
            assert bake["state"] not in ("succeeded", "failed") and time.monotonic() < deadline, bake
            time.sleep(0.05)
        os.killpg(worker.popen.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        worker.popen.wait(timeout=30)
        replacement = service.start_worker(concurrency=2)

        requeued_at = None
        while (bake := client.get(f"/v1/bakes/{bake_id}").json())["state"] not in ("succeeded", "failed", "cancelled"):
            if requeued_at is None and any("lost its worker" in line["message"] for line in bake["log"]):
                requeued_at = time.monotonic()
            assert time.monotonic() < deadline, replacement.tail(60)
            time.sleep(0.2)
        finished_at = time.monotonic()
        assert bake["state"] == "succeeded" and bake["attempt"] == 0, (bake["error"], replacement.tail(60))

    with service.sessions()() as session:
        lines = [row.message for row in session.scalars(select(BakeLog).where(BakeLog.bake_id == bake_id).order_by(BakeLog.id))]
        bundles = session.scalars(select(Bundle).where(Bundle.name == "lost-walker")).all()
    lost = [line for line in lines if "lost its worker" in line]
    assert lost and all("re-queued, retry " in line for line in lost), lines
    assert sum(line.startswith("pack finished") for line in lines) == 1, lines
    assert sum(line.startswith("publish finished") for line in lines) == 1, lines
    assert lines.count("bake succeeded") == 1 and len(bundles) == 1 and bundles[0].bake_id == bake_id
    requeue_s = (requeued_at or finished_at) - killed_at
    print(f"\nlost worker: process group killed during the impostor views; {len(lost)} units re-queued by the sweeper "
          f"{requeue_s:.1f} s later (heartbeat timeout {LOST_WORKER_SETTINGS['CROWDBAKE_HEARTBEAT_TIMEOUT']} s); "
          f"succeeded {finished_at - killed_at:.1f} s after the kill, with no manual step")
    # Bounded: the timeout, a sweep and a heartbeat of slack before the re-queue.
    assert requeue_s < float(LOST_WORKER_SETTINGS["CROWDBAKE_HEARTBEAT_TIMEOUT"]) + 10, requeue_s

    published = service.settings.bundles_dir / "lost-walker" / "1.0.0"
    verify_bundle(published)
    # The work folder went with the success.
    assert not (service.settings.work_dir / bake["input_key"]).exists()
    reference = reference_bake(service, bake, tmp_path / "reference")
    got, expected = tree_bytes(published), tree_bytes(reference)
    assert sorted(got) == sorted(expected)
    assert not [path for path in expected if got[path] != expected[path]], "files differ from the undisturbed bake"
