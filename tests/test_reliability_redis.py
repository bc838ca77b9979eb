"""Redis (the broker) restarts while bakes are queued and running: every bake still finishes, once.

Real processes: a private redis-server with its append-only file on (as a production broker runs:
a restart keeps queued and unacknowledged messages), uvicorn and two Celery workers. The broker is
stopped while stages are running and messages are queued, stays down for a few seconds, and comes
back on the same port; workers reconnect on their own.

Regression (fixed in crowdbake.jobs.tasks): a stage that finished while the broker was down could
not queue the next stage (kombu gives up publishing after about a second), its Celery retry could not
be queued either, and the bake stayed "running" forever. The next stage is now queued in the database
with the finished one, and its message sent by the worker or, once the broker is back, by the API's
sweeper (crowdbake.jobs.sweeper). A bake started while the broker is down is accepted as queued (202)
and sent the same way, instead of failing with a 503. The broker stays down here until a stage has
finished during the outage.
"""
from __future__ import annotations

import time

import pytest
from sqlalchemy import select

from crowdbake.jobs.sweeper import ENQUEUE_WAIT_S
from reliability_fixtures import FAST_PARAMS, RedisServer, bake_body, make_service, upload_sample, wait_for_bake

pytestmark = [pytest.mark.integration, pytest.mark.slow]

BAKES = 3
DOWNTIME_S = 3.0
MAX_DOWNTIME_S = 60.0
BAKE_TIMEOUT_S = 300


@pytest.fixture
def redis(tmp_path):
    server = RedisServer(tmp_path / "redis", durable=True).start()
    yield server
    server.stop()


@pytest.fixture
def service(tmp_path, redis):
    # A sweeper pass every 2 s sends what could not be sent while the broker was down.
    service = make_service(tmp_path / "service", redis.url, CROWDBAKE_SWEEP_INTERVAL="2")
    service.start_api()
    service.start_worker(concurrency=1)
    service.start_worker(concurrency=1)
    try:
        yield service
    finally:
        service.stop()


def finished_stages(client, bake_ids: list[str]) -> int:
    return sum(stage["state"] == "succeeded" for bake_id in bake_ids for stage in client.get(f"/v1/bakes/{bake_id}").json()["stages"])


def test_bakes_continue_across_a_broker_restart(service, redis, sample):
    from crowdbake.storage.models import BakeLog, Bundle

    with service.client() as client:
        ids = upload_sample(client, sample)
        bake_ids = []
        for index in range(BAKES):
            created = client.post("/v1/bakes", json=bake_body(ids, "redis-walker", f"1.0.{index}", FAST_PARAMS))
            assert created.status_code == 202, created.text
            bake_ids.append(created.json()["id"])
        # Restart the broker once stages are running and the other bakes wait in the queue.
        wait_for_bake(client, bake_ids[0], 120, states=("running",))
        time.sleep(1.0)
        finished_before = finished_stages(client, bake_ids)
        redis.stop()
        down_at = time.monotonic()
        during = []
        # Down for DOWNTIME_S at least, and until some stage has finished (and so needs the broker to
        # hand over to the next one) during the outage.
        while time.monotonic() - down_at < DOWNTIME_S or finished_stages(client, bake_ids) == finished_before:
            assert time.monotonic() - down_at < MAX_DOWNTIME_S, "no stage finished while the broker was down"
            # The API keeps answering from the database.
            during.append(client.get(f"/v1/bakes/{bake_ids[0]}").status_code)
            time.sleep(0.2)
        submitted_at = time.monotonic()
        accepted = client.post("/v1/bakes", json=bake_body(ids, "redis-walker", "9.0.0", FAST_PARAMS))
        submit_s = time.monotonic() - submitted_at
        redis.start()
        downtime, finished_while_down = time.monotonic() - down_at, finished_stages(client, bake_ids) - finished_before
        assert set(during) == {200}
        # Starting a bake while the queue is down: accepted as queued, within the enqueue bound.
        assert accepted.status_code == 202 and accepted.json()["state"] == "queued", accepted.text
        assert submit_s < ENQUEUE_WAIT_S + 1.0, f"POST /v1/bakes took {submit_s:.1f} s with the broker down"
        bake_ids.append(accepted.json()["id"])

        explain = lambda: service.worker_logs()[-6000:]
        bakes = [wait_for_bake(client, bake_id, BAKE_TIMEOUT_S, explain=explain) for bake_id in bake_ids]
    assert [bake["state"] for bake in bakes] == ["succeeded"] * len(bakes), [(bake["state"], bake["error"]) for bake in bakes]
    print(f"\nbroker restart: down {downtime:.1f} s, {finished_while_down} stages finished meanwhile; all {len(bakes)} bakes succeeded "
          f"{time.monotonic() - down_at - downtime:.1f} s after it came back")

    with service.sessions()() as session:
        for bake in bakes:
            lines = [row.message for row in session.scalars(select(BakeLog).where(BakeLog.bake_id == bake["id"]))]
            assert lines.count("bake succeeded") == 1 and sum(line.startswith("publish finished") for line in lines) == 1, lines
        versions = sorted(bundle.version for bundle in session.scalars(select(Bundle).where(Bundle.name == "redis-walker")))
    assert versions == sorted(bake["version"] for bake in bakes)
