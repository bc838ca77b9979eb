"""Several machines for real: the API and two workers, each with its own private data folder, sharing
only Redis, PostgreSQL and an S3 bucket.

Each process gets another CROWDBAKE_DATA_DIR, as separate hosts would, so nothing can pass through a
shared folder: uploads go to the bucket, each stage stores what it wrote as blobs and the next stage,
on whichever worker, fetches them (crowdbake.storage.work_outputs). The bake fans its impostor views
out over both workers; then one worker's whole process group (the Celery main process and its pool,
as when its machine is lost) is SIGKILLed in the middle of an impostor task. Its task stops beating;
the API's sweeper re-queues it (crowdbake.jobs.sweeper), the surviving worker runs it, and the bake
finishes with no manual step, exactly once, its bundle byte for byte the same bake run undisturbed in
one process (crowdbake.stages.runner.run_bake).

Needs the servers scripts/test.sh starts: PostgreSQL (CROWDBAKE_TEST_DATABASE_URL) and S3
(CROWDBAKE_TEST_S3_URL); the Redis server is the test's own.
"""
from __future__ import annotations

import os
import shutil
import signal
import time

import pytest
from sqlalchemy import select

from crowdbake.formats.bundle import verify_bundle
from reliability_fixtures import (
    SLOW_IMPOSTOR_PARAMS,
    RedisServer,
    bake_body,
    child_pids,
    files_under,
    inputs_created,
    make_service,
    run_reference_bake,
    tree_bytes,
    upload_sample,
    wait_for_bake,
)
from service_fixtures import database_env, published_files, store_env

pytestmark = [pytest.mark.integration, pytest.mark.slow]

BAKE_TIMEOUT_S = 300
# A sweeper that acts within seconds: heartbeats every 0.5 s, a task without one for 4 s is lost.
QUICK_SWEEP = {"CROWDBAKE_HEARTBEAT_INTERVAL": "0.5", "CROWDBAKE_HEARTBEAT_TIMEOUT": "4", "CROWDBAKE_SWEEP_INTERVAL": "0.5"}
NAME, VERSION = "multihost-walker", "1.0.0"
# Enough impostor tasks (8 frames asked; the rule keeps 6 x 2 rings of 12 views within the budget) that both
# hosts are still rendering when one is lost.
MULTIHOST_PARAMS = {**SLOW_IMPOSTOR_PARAMS, "impostor_frames": 8, "impostor_motion_texels": None}
# The Celery log line of a finished impostor task (crowdbake.jobs.celery_app.TASK_NAMES["impostor_views"]).
IMPOSTOR_DONE = "crowdbake.stage.impostor_views["


@pytest.fixture
def hosts(tmp_path):
    if not os.environ.get("CROWDBAKE_TEST_DATABASE_URL") or not os.environ.get("CROWDBAKE_TEST_S3_URL"):
        pytest.skip("needs CROWDBAKE_TEST_DATABASE_URL and CROWDBAKE_TEST_S3_URL (scripts/test.sh starts PostgreSQL and S3)")
    redis = RedisServer(tmp_path / "redis").start()
    # The API's data folder is host-api's; each worker gets its own below.
    service = make_service(tmp_path / "host-api", redis.url, **database_env(), **store_env("s3"), **QUICK_SWEEP)
    service.start_api()
    for host in ("host-a", "host-b"):
        # A session of its own: the worker's main process and its pool share one process group to kill.
        service.start_worker(concurrency=1, extra_env={"CROWDBAKE_DATA_DIR": str(tmp_path / host / "data")}, preexec_fn=os.setsid)
    try:
        yield service
    finally:
        service.stop()
        redis.stop()


def impostor_tasks_done(worker) -> int:
    return sum(IMPOSTOR_DONE in line and "succeeded" in line for line in worker.log.read_text(errors="replace").splitlines())


def holder_of_an_unfinished_part(service, sessions, bake_id: str):
    """The worker whose pool process owns an impostor part not yet done (claimed, so rendering it), or
    None. Choosing by CPU alone could pick a process finishing a part already marked done, or between
    tasks: killing it would lose nothing for the sweeper to find."""
    from crowdbake.storage.models import BakePart

    with sessions() as session:
        owners = session.scalars(select(BakePart.owner).where(BakePart.bake_id == bake_id, BakePart.done.is_(False), BakePart.owner.is_not(None))).all()
    pids = {int(owner.split(":")[1]) for owner in owners if owner.count(":") >= 2 and owner.split(":")[1].isdigit()}
    return next((worker for worker in service.workers if set(child_pids(worker.popen.pid)) & pids), None)


def test_a_bake_fans_out_over_two_hosts_and_survives_losing_one(hosts, sample, tmp_path):
    from crowdbake.storage.models import BakeLog, Bundle

    service = hosts
    with service.client() as client:
        ids = upload_sample(client, sample)
        started = time.monotonic()
        created = client.post("/v1/bakes", json=bake_body(ids, NAME, VERSION, MULTIHOST_PARAMS))
        assert created.status_code == 202, created.text
        bake_id = created.json()["id"]

        # Both hosts render impostor views; then the one rendering right now loses its machine.
        victim, sessions = None, service.sessions()
        deadline = time.monotonic() + BAKE_TIMEOUT_S
        while victim is None:
            bake = client.get(f"/v1/bakes/{bake_id}").json()
            assert bake["state"] not in ("succeeded", "failed"), f"the bake ended before a host was lost: {bake['state']} {bake['error']}"
            assert time.monotonic() < deadline, service.worker_logs()[-4000:]
            if all(impostor_tasks_done(worker) >= 1 for worker in service.workers):
                victim = holder_of_an_unfinished_part(service, sessions, bake_id)
            time.sleep(0.05)
        fanned_out = [impostor_tasks_done(worker) for worker in service.workers]
        os.killpg(os.getpgid(victim.popen.pid), signal.SIGKILL)
        killed_at = time.monotonic()
        survivor = next(worker for worker in service.workers if worker is not victim)

        # No manual step: the sweeper re-queues what the lost host was running.
        bake = wait_for_bake(client, bake_id, BAKE_TIMEOUT_S, explain=lambda: survivor.tail(80))
        recovered_s = time.monotonic() - killed_at
        assert bake["state"] == "succeeded" and bake["attempt"] == 0, (bake["error"], survivor.tail(80))
    print(f"\nmultihost: impostor tasks done per host before the loss {fanned_out}; bake {time.monotonic() - started:.1f} s in all, "
          f"succeeded {recovered_s:.1f} s after the host was lost")

    with service.sessions()() as session:
        lines = [row.message for row in session.scalars(select(BakeLog).where(BakeLog.bake_id == bake_id).order_by(BakeLog.id))]
        bundles = session.scalars(select(Bundle).where(Bundle.name == NAME)).all()
    # Exactly once: one pack, one publish, one success, one bundle record; the loss is in the log.
    assert any("lost its worker" in line and "re-queued, retry 1 of" in line for line in lines), lines
    assert sum(line.startswith("pack finished") for line in lines) == 1, lines
    assert sum(line.startswith("publish finished") for line in lines) == 1, lines
    assert lines.count("bake succeeded") == 1, lines
    assert len(bundles) == 1 and bundles[0].bake_id == bake_id

    # Nothing went through a folder of another host: the API's data folder holds no work and no
    # bundle, no worker holds a published bundle, and the bundle is read back from the bucket.
    api_data = service.settings.data_dir
    assert files_under(api_data / "work") == [] and files_under(api_data / "bundles") == [] and files_under(api_data / "blobs") == []
    for host in ("host-a", "host-b"):
        assert files_under(tmp_path / host / "data" / "bundles") == []
    published = published_files(service.settings, NAME, VERSION)
    downloaded = tmp_path / "downloaded"
    for path, data in published.items():
        (downloaded / path).parent.mkdir(parents=True, exist_ok=True)
        (downloaded / path).write_bytes(data)
    verify_bundle(downloaded)

    # Byte for byte the bake run undisturbed in one process, from the uploaded files.
    sources = tmp_path / "sources"
    sources.mkdir()
    for name in ("character.glb", "cloth.pc2", "cloth.obj"):
        shutil.copy(sample / name, sources / name)
    (sources / "textures").mkdir()
    for name in bake["inputs"]["textures"]:
        shutil.copy(sample / "textures" / name, sources / "textures" / name)
    reference = run_reference_bake(sources, service.env, bake, inputs_created(service.sessions(), bake), tmp_path / "reference")
    expected = tree_bytes(reference)
    assert sorted(published) == sorted(expected)
    differing = [path for path in expected if published[path] != expected[path]]
    assert not differing, f"files differ from the undisturbed bake: {differing}"
