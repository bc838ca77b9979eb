"""Redis (the broker) restarts while bakes are queued and running: every bake still finishes, once.

Real processes: a private redis-server with its append-only file on (as a production broker runs:
a restart keeps queued and unacknowledged messages), uvicorn and two Celery workers. The broker is
stopped while stages are running and messages are queued, stays down for a few seconds, and comes
back on the same port; workers reconnect on their own.

Regression (fixed in crowdbake.jobs.tasks): a stage that finished while the broker was down could
not queue the next stage (kombu gives up publishing after about a second), its Celery retry could not
be queued either, and the bake stayed "running" forever. Workers now keep trying to hand over for
about two minutes (BROKER_PUBLISH_RETRY), and past that the bake fails with a reason and can be
retried. The broker stays down here until a stage has finished during the outage.
"""
from __future__ import annotations

import time

import pytest
from sqlalchemy import select

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
    service = make_service(tmp_path / "service", redis.url)
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
            # The API keeps answering from the database; starting a bake needs the queue: 503.
            during.append(client.get(f"/v1/bakes/{bake_ids[0]}").status_code)
            time.sleep(0.2)
        refused = client.post("/v1/bakes", json=bake_body(ids, "redis-walker", "9.0.0", FAST_PARAMS))
        redis.start()
        downtime, finished_while_down = time.monotonic() - down_at, finished_stages(client, bake_ids) - finished_before
        assert set(during) == {200}
        assert refused.status_code == 503 and refused.headers["content-type"] == "application/problem+json", refused.text
        refused_id = client.get("/v1/bakes", params={"name": "redis-walker"}).json()
        failed = [bake for bake in refused_id["data"] if bake["version"] == "9.0.0"]
        assert len(failed) == 1 and failed[0]["state"] == "failed"
        # The refused bake was recorded as failed; once the broker is back it can be retried.
        retried = client.post(f"/v1/bakes/{failed[0]['id']}/retry")
        assert retried.status_code == 202, retried.text
        bake_ids.append(failed[0]["id"])

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
