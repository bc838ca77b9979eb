"""Bake state transitions, reservations, claims, heartbeats and the sweeper, on the real app and a
real SQLite file shared by threads (no worker: deliveries are driven through crowdbake.storage.records
and crowdbake.jobs.sweeper as a worker and the API drive them).

Regressions:
* two simultaneous retries of one failed bake both answered 202 with the same attempt, and the
  pipeline then ran twice in one work folder (FileNotFoundError, "Directory not empty"): a retry is
  now a compare-and-set on (state, attempt), one wins and the other is a 409;
* concurrent submits of one name/version from different inputs were all accepted (the loser failed
  after a whole bake), identical ones made several bakes sharing a work folder: the input key and
  the version are reserved by unique columns at submit;
* a cancel while `publish` ran left a bundle folder without a record (GET 404) and the next bake of
  that version failed `version-conflict`: a cancel is refused once publish has started;
* a stage whose worker vanished stayed `running` forever: the sweeper re-queues it after the
  heartbeat timeout, counts the retry and logs it; a late original then records nothing;
* a bake whose message never reached the broker stayed `queued` forever: the sweeper sends it;
* a bake stayed `running` for good after its worker was SIGKILLed between taking an impostor part's
  message from the broker and committing its receipt (sent, unowned, undone: neither lost nor unsent to
  the sweeper): such a unit is sent again after the heartbeat timeout, and the second copy is dropped;
* a huge bake was accepted and ran for minutes: the product of its impostor parameters is capped.
"""
from __future__ import annotations

import concurrent.futures
import datetime as dt
import threading
import time

import pytest
from sqlalchemy import select

from crowdbake.storage import bake_requests, records
from crowdbake.storage.db import session_scope
from crowdbake.storage.models import Bake, BakeLog, BakePart, BakeStage, utcnow
from service_fixtures import bake_body, make_api, upload_small_assets

PROBLEM = "application/problem+json"
CONCURRENT = 8


@pytest.fixture
def api(tmp_path):
    # The sweeper thread does not run under TestClient (no lifespan); the tests call sweep_once.
    return make_api(tmp_path, heartbeat_interval=0.2, heartbeat_timeout=2.0, dispatch_after=0.0)


@pytest.fixture
def assets(api, tmp_path):
    return upload_small_assets(api, tmp_path)


def at_once(count: int, call):
    """`call(index)` from `count` threads released together; their results in order."""
    barrier = threading.Barrier(count)

    def run(index):
        barrier.wait()
        return call(index)

    with concurrent.futures.ThreadPoolExecutor(count) as pool:
        return list(pool.map(run, range(count)))


def new_bake(api, assets, **changes) -> str:
    response = api.client.post("/v1/bakes", json=bake_body(assets, **changes), headers=api.auth("ci"))
    assert response.status_code == 202, response.text
    return response.json()["id"]


def claim(api, bake_id: str, stage: str, owner: str, part: str | None = None, stale_s: float | None = None) -> records.Claim:
    stale_before = utcnow() - dt.timedelta(seconds=stale_s if stale_s is not None else api.settings.heartbeat_timeout)
    with session_scope(api.sessions) as session:
        attempt = session.get(Bake, bake_id).attempt
        return records.claim_delivery(session, bake_id, attempt, stage, part, owner, stale_before)


def log_of(api, bake_id: str) -> list[str]:
    with session_scope(api.sessions) as session:
        return [row.message for row in session.scalars(select(BakeLog).where(BakeLog.bake_id == bake_id).order_by(BakeLog.id))]


# ---------------------------------------------------------------------------------- transitions


def test_of_simultaneous_retries_one_wins_and_the_other_is_a_conflict(api, assets):
    bake_id = new_bake(api, assets)
    assert api.client.post(f"/v1/bakes/{bake_id}/cancel", headers=api.auth("bake")).status_code == 202

    answers = at_once(CONCURRENT, lambda _: api.client.post(f"/v1/bakes/{bake_id}/retry", headers=api.auth("bake")))
    statuses = sorted(answer.status_code for answer in answers)
    assert statuses == [202] + [409] * (CONCURRENT - 1), [answer.text for answer in answers]
    winner = next(answer.json() for answer in answers if answer.status_code == 202)
    assert winner["attempt"] == 1
    loser = next(answer for answer in answers if answer.status_code == 409)
    assert loser.headers["content-type"] == PROBLEM and loser.json()["type"] == "/problems/invalid-state"
    assert sum(line == "retry: attempt 1" for line in log_of(api, bake_id)) == 1


def test_retry_compare_and_set_in_sql_lets_one_of_two_sessions_win(api, assets):
    """The same race below the API: two sessions retry attempt 0 at once; the UPDATE's rowcount decides."""
    bake_id = new_bake(api, assets)
    with session_scope(api.sessions) as session:
        bake_requests.cancel_bake(session, bake_id)

    def retry(_):
        try:
            with session_scope(api.sessions) as session:
                return bake_requests.retry_bake(session, bake_id, 0).attempt
        except bake_requests.TransitionRefused:
            return None

    outcomes = at_once(2, retry)
    assert sorted(outcomes, key=str) == [1, None]


def test_identical_concurrent_submits_make_one_bake(api, assets):
    answers = at_once(CONCURRENT, lambda _: api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci")))
    assert {answer.json().get("id") for answer in answers} == {answers[0].json().get("id")}, [answer.text for answer in answers]
    assert sorted(answer.status_code for answer in answers) == [200] * (CONCURRENT - 1) + [202]
    with session_scope(api.sessions) as session:
        assert session.scalar(select(Bake.id).where(Bake.name == "walker").limit(2).offset(1)) is None


def test_concurrent_submits_of_one_version_from_other_inputs_conflict_at_once(api, assets):
    answers = at_once(CONCURRENT, lambda index: api.client.post(
        "/v1/bakes", json=bake_body(assets, params={"impostor_frames": 2, "azimuths": 4, "tile_size": 32, "candidates": index + 1}),
        headers=api.auth("ci")))
    statuses = sorted(answer.status_code for answer in answers)
    assert statuses == [202] + [409] * (CONCURRENT - 1), [answer.text for answer in answers]
    conflict = next(answer for answer in answers if answer.status_code == 409)
    assert conflict.json()["type"] == "/problems/conflict" and "walker/1.0.0" in conflict.json()["detail"]
    # A bake that does not publish reserves no version; a failed or cancelled one lets it go.
    assert api.client.post("/v1/bakes", json=bake_body(assets, publish=False, params={"tile_size": 48}), headers=api.auth("ci")).status_code == 202
    winner = next(answer.json()["id"] for answer in answers if answer.status_code == 202)
    assert api.client.post(f"/v1/bakes/{winner}/cancel", headers=api.auth("bake")).status_code == 202
    assert api.client.post("/v1/bakes", json=bake_body(assets, params={"tile_size": 64}), headers=api.auth("ci")).status_code == 202


def test_a_bake_is_not_cancelled_once_publish_has_started(api, assets):
    bake_id = new_bake(api, assets)
    with session_scope(api.sessions) as session:
        for row in session.scalars(select(BakeStage).where(BakeStage.bake_id == bake_id)):
            row.state = "succeeded" if row.stage != "publish" else "pending"
        records.queue_stage(session, bake_id, "publish")
    assert claim(api, bake_id, "publish", "host:1:publish-task").won
    refused = api.client.post(f"/v1/bakes/{bake_id}/cancel", headers=api.auth("bake"))
    assert refused.status_code == 409 and "publishing" in refused.json()["detail"], refused.text
    assert api.client.get(f"/v1/bakes/{bake_id}", headers=api.auth("bake")).json()["state"] == "running"


# ------------------------------------------------------------------------- claims and heartbeats


def test_a_duplicate_delivery_is_dropped_while_the_owner_beats(api, assets):
    bake_id = new_bake(api, assets)
    first = claim(api, bake_id, "validate", "otherhost:1:task-a")
    assert first.won and first.lost_owner is None
    duplicate = claim(api, bake_id, "validate", "otherhost:2:task-b")
    assert not duplicate.won and "running elsewhere" in duplicate.reason


def test_a_delivery_of_a_dead_process_on_this_host_is_taken_over_and_counted(api, assets):
    bake_id = new_bake(api, assets)
    import subprocess
    import sys

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
    dead_owner = f"{records.this_host()}:{gone}:task-a"
    assert claim(api, bake_id, "validate", dead_owner).won
    again = claim(api, bake_id, "validate", records.delivery_owner("task-a"))
    assert again.won and again.lost_owner == dead_owner and again.retries == 1


def test_the_sweeper_requeues_a_lost_stage_counts_it_logs_it_and_the_late_original_records_nothing(api, assets):
    from crowdbake.jobs.sweeper import sweep_once

    bake_id = new_bake(api, assets)
    services = api.client.app.state.services
    lost_owner = "lost-host:4242:task-a"
    assert claim(api, bake_id, "validate", lost_owner).won
    # Not yet stale: nothing happens.
    assert sweep_once(services.sessions, services.celery, api.settings).requeued == []
    later = utcnow() + dt.timedelta(seconds=api.settings.heartbeat_timeout + 1)
    report = sweep_once(services.sessions, services.celery, api.settings, now=later)
    assert report.requeued == [f"{bake_id}:validate"] and report.sent == [f"{bake_id}:validate"], report
    with session_scope(api.sessions) as session:
        row = session.get(BakeStage, (bake_id, "validate"))
        assert (row.state, row.owner, row.retries) == ("queued", None, 1) and row.sent_at is not None
        # The late original comes back: it no longer owns the stage, records nothing, beats no more.
        assert records.still_owner(session, bake_id, 0, "validate", None, lost_owner) is None
        assert not records.heartbeat(session, bake_id, 0, "validate", None, lost_owner)
    line = next(line for line in log_of(api, bake_id) if "lost its worker" in line)
    assert line.startswith("stage validate lost its worker at ") and f"re-queued, retry 1 of {api.settings.task_max_retries}" in line
    # The new message claims it normally.
    assert claim(api, bake_id, "validate", "host-b:1:task-b").won


def test_a_stage_that_keeps_losing_its_worker_fails_the_bake_past_the_budget(api, assets):
    from crowdbake.jobs.sweeper import sweep_once

    bake_id = new_bake(api, assets)
    services = api.client.app.state.services
    for round_ in range(api.settings.task_max_retries + 1):
        assert claim(api, bake_id, "validate", f"lost-host:{round_}:task").won
        later = utcnow() + dt.timedelta(seconds=api.settings.heartbeat_timeout + 1)
        sweep_once(services.sessions, services.celery, api.settings, now=later)
    bake = api.client.get(f"/v1/bakes/{bake_id}", headers=api.auth("bake")).json()
    assert bake["state"] == "failed" and bake["error"]["type"] == "worker-lost", bake["error"]
    assert f"more than {api.settings.task_max_retries}" in bake["error"]["detail"]


def fan_out(api, bake_id: str, *parts: str) -> None:
    """The bake as the poses stage leaves it: the stages before it finished, and its impostor parts
    queued and their messages sent."""
    with session_scope(api.sessions) as session:
        for stage in ("validate", "cycle", "poses"):
            records.finish_stage(session, bake_id, stage, 0.1, None)
        records.record_fan_out(session, bake_id, [{"id": part} for part in parts])
        records.mark_sent(session, bake_id, 0, "impostors", [f"impostors/{part}" for part in parts])


def test_a_lost_impostor_part_is_requeued_alone(api, assets):
    from crowdbake.jobs.sweeper import sweep_once

    bake_id = new_bake(api, assets)
    services = api.client.app.state.services
    fan_out(api, bake_id, "f0", "f1")
    assert claim(api, bake_id, "impostors", "lost-host:1:a", part="impostors/f0").won
    assert claim(api, bake_id, "impostors", f"{records.this_host()}:1:b", part="impostors/f1").won
    with session_scope(api.sessions) as session:  # f1 keeps beating
        session.get(BakePart, (bake_id, "impostors/f1")).heartbeat_at = utcnow() + dt.timedelta(seconds=60)
    later = utcnow() + dt.timedelta(seconds=api.settings.heartbeat_timeout + 1)
    report = sweep_once(services.sessions, services.celery, api.settings, now=later)
    assert report.requeued == [f"{bake_id}:impostors/f0"] and report.sent == [f"{bake_id}:impostors/f0"]
    messages = [message for message in queued_messages(api) if message["task"] == "crowdbake.stage.impostor_views"]
    assert messages == [{"task": "crowdbake.stage.impostor_views", "args": repr([bake_id, 0, "impostors/f0"])}]


def test_the_heartbeat_stops_a_running_stage_when_the_bake_is_cancelled(api, assets):
    from crowdbake.jobs.deliveries import BakeCancelled, Heartbeat, StageContext, WorkerServices

    bake_id = new_bake(api, assets)
    owner = records.delivery_owner("task-a")
    assert claim(api, bake_id, "validate", owner).won
    services = WorkerServices(api.settings, api.sessions, None, None, None)
    ctx = StageContext(services, bake_id, 0, "validate", api.settings.work_dir / "unused", owner=owner)
    with Heartbeat(ctx, api.settings.heartbeat_interval):
        ctx.progress("validate", 0, 10)  # live: no exception
        with session_scope(api.sessions) as session:
            bake_requests.cancel_bake(session, bake_id)
        deadline = time.monotonic() + 5 * api.settings.heartbeat_interval
        while ctx.stop_reason is None:
            assert time.monotonic() < deadline, "the heartbeat did not see the cancel"
            time.sleep(0.05)
        with pytest.raises(BakeCancelled):
            ctx.progress("validate", 1, 10)


# ---------------------------------------------------------------------------------- dispatching


def queued_messages(api) -> list[dict]:
    import json
    from pathlib import Path

    messages = []
    for path in sorted((Path(api.settings.broker_dir) / "queue").glob("*.msg")):
        envelope = json.loads(path.read_bytes())
        messages.append({"task": envelope["headers"]["task"], "args": envelope["headers"]["argsrepr"]})
    return messages


def test_an_unsent_stage_is_sent_by_the_sweeper_and_by_a_resubmit(api, assets):
    from crowdbake.jobs.sweeper import sweep_once

    # A bake saved as queued whose message never went out (the broker did not answer in time).
    bake_id = new_bake(api, assets)
    for path in (api.settings.broker_dir / "queue").glob("*.msg"):
        path.unlink()
    with session_scope(api.sessions) as session:
        session.get(BakeStage, (bake_id, "validate")).sent_at = None
    # A resubmit of the same bake sends it now.
    again = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci"))
    assert again.status_code == 200 and again.json()["id"] == bake_id
    assert queued_messages(api) == [{"task": "crowdbake.stage.validate", "args": repr([bake_id, 0])}]
    # And the sweeper sends what nobody resubmits; a sent stage is not sent again.
    other = new_bake(api, assets, version="2.0.0")
    with session_scope(api.sessions) as session:
        session.get(BakeStage, (other, "validate")).sent_at = None
    services = api.client.app.state.services
    report = sweep_once(services.sessions, services.celery, api.settings, now=utcnow() + dt.timedelta(seconds=1))
    assert report.sent == [f"{other}:validate"]
    assert sweep_once(services.sessions, services.celery, api.settings, now=utcnow() + dt.timedelta(seconds=1)).sent == []


# ---------------------------------------------------------------------------------- work folders


def test_the_sweeper_deletes_work_folders_of_published_and_cancelled_bakes_and_keeps_failed_ones(api, assets):
    from crowdbake.jobs.sweeper import sweep_once

    services = api.client.app.state.services
    ids = {state: new_bake(api, assets, version=f"1.0.{index}") for index, state in enumerate(("succeeded", "cancelled", "failed", "queued"))}
    with session_scope(api.sessions) as session:
        bakes = {state: session.get(Bake, bake_id) for state, bake_id in ids.items()}
        for row in bakes["succeeded"].stages:
            row.state = "succeeded"
        records.succeed_bake(session, bakes["succeeded"])
        records.fail_bake(session, bakes["failed"], "cycle", {"type": "stage-failed", "title": "t", "detail": "d"})
        keys = {state: bake.input_key for state, bake in bakes.items()}
    with session_scope(api.sessions) as session:
        bake_requests.cancel_bake(session, ids["cancelled"])
    for key in keys.values():
        (api.settings.work_dir / key / "cycle").mkdir(parents=True)
    orphan = api.settings.work_dir / ("0" * 64)
    orphan.mkdir()

    soon = utcnow() + dt.timedelta(seconds=api.settings.heartbeat_timeout + 1)
    report = sweep_once(services.sessions, services.celery, api.settings, now=soon)
    assert sorted(report.removed_work) == sorted([keys["succeeded"], keys["cancelled"]])
    assert (api.settings.work_dir / keys["failed"]).is_dir() and (api.settings.work_dir / keys["queued"]).is_dir() and orphan.is_dir()
    much_later = utcnow() + dt.timedelta(seconds=api.settings.work_keep_seconds + 1)
    report = sweep_once(services.sessions, services.celery, api.settings, now=much_later)
    assert report.removed_work == [keys["failed"]]
    assert (api.settings.work_dir / keys["queued"]).is_dir()


def test_the_sweeper_removes_publish_folders_a_killed_publish_left_and_keeps_live_ones(api, assets):
    """A publish killed while copying (SIGKILL) leaves `<bundles>/<name>/.<version>.<random>` behind, and
    nothing else ever removes it. The sweeper removes such a folder once it has been quiet for the
    heartbeat timeout and no queued or running bake publishes that version."""
    import os
    import time

    services = api.client.app.state.services
    bake_id = new_bake(api, assets, version="1.0.0")  # queued: its publish may be under way
    with session_scope(api.sessions) as session:
        name = session.get(Bake, bake_id).name
    root = api.settings.bundles_dir / name
    old = time.time() - api.settings.heartbeat_timeout - 60
    folders = {"left": root / ".2.0.0.k1ll3d_x", "live bake": root / ".1.0.0.runn1ng_", "fresh": root / ".3.0.0.just_n0w",
               "published": root / "4.0.0", "not a staging name": root / ".cache"}
    for label, folder in folders.items():
        (folder / "poses").mkdir(parents=True)
        (folder / "poses" / "body.cbpc").write_bytes(b"partial")
        if label != "fresh":
            os.utime(folder, (old, old))

    report = sweep_at(api, utcnow())
    assert report.removed_partial == [f"{name}/.2.0.0.k1ll3d_x"]
    assert not folders["left"].exists()
    assert all(folder.is_dir() for label, folder in folders.items() if label != "left")
    with session_scope(api.sessions) as session:
        bake_requests.cancel_bake(session, bake_id)
    assert sweep_at(api, utcnow()).removed_partial == [f"{name}/.1.0.0.runn1ng_"]  # its bake ended


# ------------------------------------------------------------------------------------ parameters


def test_too_many_impostor_texels_is_a_422_naming_the_parameters(api, assets):
    from crowdbake.params import MAX_IMPOSTOR_TEXELS, BakeParams

    huge = {"impostor_frames": 256, "azimuths": 64, "elevations_deg": [0, 30], "tile_size": 1024}
    response = api.client.post("/v1/bakes", json=bake_body(assets, params=huge), headers=api.auth("ci"))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM, response.text
    message = response.text
    for name in ("impostor_frames", "azimuths", "elevations_deg", "tile_size", f"{MAX_IMPOSTOR_TEXELS:,}"):
        assert name in message, message
    # The same rule where the CLI and the workers read parameters.
    with pytest.raises(ValueError, match="tile_size"):
        BakeParams.from_dict(huge)
    # Exactly the cap is accepted (1 x 64 x 2 x 1024² = 2^27).
    BakeParams.from_dict({"impostor_frames": 1, "azimuths": 64, "elevations_deg": [0, 30], "tile_size": 1024})


def test_a_message_held_by_a_lost_worker_before_it_started_is_requeued(api, assets):
    """A worker's main process takes a message, then the machine is lost before a pool process starts
    it (the filesystem broker loses the message; Redis keeps it for hours): the receipt mark stops
    beating and the sweeper re-queues the stage. A pool process of the worker that holds the mark
    claims it without counting a retry."""
    import os

    from crowdbake.jobs.sweeper import sweep_once

    services = api.client.app.state.services
    lost = new_bake(api, assets)
    with session_scope(api.sessions) as session:
        assert records.mark_received(session, lost, 0, "validate", None, "lost-host:77:task-a")
        assert records.beat_received(session, ["lost-host:77:task-a"]) == 1
    later = utcnow() + dt.timedelta(seconds=api.settings.heartbeat_timeout + 1)
    report = sweep_once(services.sessions, services.celery, api.settings, now=later)
    assert report.requeued == [f"{lost}:validate"] and report.sent == [f"{lost}:validate"]

    mine = new_bake(api, assets, version="3.0.0")
    with session_scope(api.sessions) as session:
        assert records.mark_received(session, mine, 0, "validate", None, f"{records.this_host()}:{os.getppid()}:task-b")
    taken = claim(api, mine, "validate", records.delivery_owner("task-b"))
    assert taken.won and taken.lost_owner is None and taken.retries == 0


# ------------------------------------------------------------------------- sent but never taken


def sweep_at(api, now: dt.datetime):
    from crowdbake.jobs.sweeper import sweep_once

    services = api.client.app.state.services
    return sweep_once(services.sessions, services.celery, api.settings, now=now)


def test_a_part_whose_message_was_lost_before_its_receipt_committed_is_sent_again_once(api, assets):
    """Regression (60 uploads, 20 bakes, the worker SIGKILLed): the worker logged "received" for an
    impostor part about a second before the kill, but its receipt (records.mark_received) never
    committed. The part stayed sent, unowned and undone; the sweeper re-queued only owned or unsent
    units, and Redis hands an unacknowledged message out again only after its visibility timeout
    (6 h), so the bake stayed `running` 15 minutes later. Now such a unit is sent again once it has
    been quiet for the heartbeat timeout; exactly once still holds: the copy that comes second is
    dropped by claim_delivery, while the first runs and after it finished."""
    bake_id = new_bake(api, assets)
    fan_out(api, bake_id, "f0", "f1")
    # f1 was taken and beats; f0's message went down with the killed worker, nothing recorded.
    assert claim(api, bake_id, "impostors", "host-a:1:f1", part="impostors/f1").won
    with session_scope(api.sessions) as session:
        session.get(BakePart, (bake_id, "impostors/f1")).heartbeat_at = utcnow() + dt.timedelta(seconds=60)
    timeout = api.settings.heartbeat_timeout

    assert sweep_at(api, utcnow() + dt.timedelta(seconds=timeout / 2)).sent == []  # not quiet long enough
    report = sweep_at(api, utcnow() + dt.timedelta(seconds=timeout + 1))
    assert report.sent == [f"{bake_id}:impostors/f0"] and report.resent == [f"{bake_id}:impostors/f0"], report
    assert report.requeued == [] and report.failed == []
    messages = [message for message in queued_messages(api) if message["task"] == "crowdbake.stage.impostor_views"]
    assert messages == [{"task": "crowdbake.stage.impostor_views", "args": repr([bake_id, 0, "impostors/f0"])}]
    with session_scope(api.sessions) as session:
        part = session.get(BakePart, (bake_id, "impostors/f0"))
        assert part.sent_at is not None and part.owner is None and part.retries == 0  # a resend is no retry
    line = next(line for line in log_of(api, bake_id) if "no worker has recorded taking it" in line)
    assert line.startswith("impostors/f0: sent at ") and "sent again" in line
    # Just sent again: the next pass leaves it alone.
    assert sweep_at(api, utcnow() + dt.timedelta(seconds=timeout / 2)).sent == []

    # The new copy runs it; the original (Redis hands it out after its visibility timeout) is dropped.
    assert claim(api, bake_id, "impostors", "host-b:1:copy", part="impostors/f0").won
    late = claim(api, bake_id, "impostors", "host-c:1:original", part="impostors/f0")
    assert not late.won and "running elsewhere" in late.reason
    with session_scope(api.sessions) as session:
        records.complete_part(session, bake_id, "impostors/f0")
    late = claim(api, bake_id, "impostors", "host-c:1:original", part="impostors/f0")
    assert not late.won and "already done" in late.reason
    assert sweep_at(api, utcnow() + dt.timedelta(seconds=10 * timeout)).sent == []  # f0 done, f1 beats


def test_a_stage_sent_recently_or_after_a_long_wait_is_not_sent_again_yet(api, assets):
    """A message may simply wait behind others in the queue; the database cannot tell it from a lost
    one. So a unit is sent again only once it has been quiet for the heartbeat timeout and for as
    long as it waited before its last send: a long queue gets a few copies, not one per pass."""
    bake_id = new_bake(api, assets)  # validate: queued, its message sent just now
    timeout = api.settings.heartbeat_timeout
    assert sweep_at(api, utcnow() + dt.timedelta(seconds=timeout / 2)).sent == []

    # Queued 100 s before its message went out 10 s ago (the broker was away meanwhile).
    with session_scope(api.sessions) as session:
        row = session.get(BakeStage, (bake_id, "validate"))
        row.queued_at, row.sent_at = utcnow() - dt.timedelta(seconds=110), utcnow() - dt.timedelta(seconds=10)
    assert timeout < 10 and sweep_at(api, utcnow()).sent == []
    assert sweep_at(api, utcnow() + dt.timedelta(seconds=80)).sent == []
    assert sweep_at(api, utcnow() + dt.timedelta(seconds=91)).sent == [f"{bake_id}:validate"]
    with session_scope(api.sessions) as session:
        row = session.get(BakeStage, (bake_id, "validate"))
        assert (row.state, row.owner, row.retries) == ("queued", None, 0) and row.sent_at is not None


def test_a_stage_let_go_of_for_a_celery_retry_waits_for_the_retry_countdown(api, assets):
    """A delivery that hit a transient error releases its unit and leaves a Celery retry with a
    countdown of up to 1.5 x CROWDBAKE_TASK_RETRY_BACKOFF_MAX: the sweeper does not send a copy that
    would run before it, but does send one if that retry never takes the unit (its worker died)."""
    from crowdbake.jobs.sweeper import RETRY_JITTER_MAX

    bake_id = new_bake(api, assets)
    owner = "host-a:1:task-a"
    assert claim(api, bake_id, "validate", owner).won
    with session_scope(api.sessions) as session:  # what run_stage does before task.retry
        records.release_delivery(session, bake_id, "validate", None, owner)
        records.stage_row(session, bake_id, "validate").state = "retrying"
    countdown = api.settings.task_retry_backoff_max * RETRY_JITTER_MAX
    timeout = api.settings.heartbeat_timeout
    assert sweep_at(api, utcnow() + dt.timedelta(seconds=timeout + 1)).sent == []
    assert sweep_at(api, utcnow() + dt.timedelta(seconds=timeout + countdown - 1)).sent == []
    report = sweep_at(api, utcnow() + dt.timedelta(seconds=timeout + countdown + 1))
    assert report.sent == report.resent == [f"{bake_id}:validate"], report
    with session_scope(api.sessions) as session:
        assert records.stage_row(session, bake_id, "validate").state == "queued"
    assert claim(api, bake_id, "validate", "host-b:1:task-b").won


def test_only_messages_the_worker_still_holds_keep_their_marks_beating(api, assets):
    """Regression (seen when Redis restarted): a worker received a message, lost its broker connection
    before a pool process started it, and Celery dropped the request (the broker redelivers it). The
    worker's heartbeat refreshed every mark with its host:pid prefix, the dropped one too, so the
    sweeper never re-queued the unit and the bake waited for ever. Only held requests beat now."""
    from celery.worker import state

    from crowdbake.jobs.deliveries import held_owners

    held, dropped = new_bake(api, assets), new_bake(api, assets, version="3.0.0")
    with session_scope(api.sessions) as session:
        assert records.mark_received(session, held, 0, "validate", None, "host-a:5:task-held")
        assert records.mark_received(session, dropped, 0, "validate", None, "host-a:5:task-dropped")

    class Request:  # what Celery keeps per reserved message: its task id is all the beat reads
        def __init__(self, id):
            self.id = id

    reserved = Request("task-held")
    state.reserved_requests.add(reserved)
    try:
        owners = held_owners(lambda task_id: f"host-a:5:{task_id}")
    finally:
        state.reserved_requests.discard(reserved)
    assert owners == ["host-a:5:task-held"]
    time.sleep(0.05)  # the beat's time is later than the marks'
    with session_scope(api.sessions) as session:
        assert records.beat_received(session, owners) == 1
        assert records.beat_received(session, []) == 0
        rows = {bake_id: records.stage_row(session, bake_id, "validate").heartbeat_at for bake_id in (held, dropped)}
    assert records.to_utc(rows[held]) > records.to_utc(rows[dropped])


def test_a_fork_waits_for_a_guarded_transaction_of_another_thread(tmp_path):
    """Regression: a Celery worker's main process forked a pool process while its received-heartbeat
    thread was inside a SQLite write; the child inherited SQLite's record of that lock with nobody to
    release it, and every claim it tried failed with "database is locked" after the busy timeout, so a
    bake waited for ever. A fork now waits for a transaction opened with fork_guarded_scope."""
    import os
    import sqlite3

    from sqlalchemy import text

    from crowdbake.storage.db import fork_guarded_scope, make_engine, make_sessionmaker

    path = tmp_path / "fork.sqlite"
    engine = make_engine(f"sqlite:///{path}")
    with engine.begin() as connection:
        connection.exec_driver_sql("CREATE TABLE marks (x INTEGER)")
    inside = threading.Event()

    def write_slowly() -> None:
        with fork_guarded_scope(make_sessionmaker(engine)) as session:
            session.execute(text("INSERT INTO marks VALUES (1)"))  # holds the write lock until commit
            inside.set()
            time.sleep(0.5)

    writer = threading.Thread(target=write_slowly)
    writer.start()
    assert inside.wait(10)
    pid = os.fork()
    if pid == 0:  # the pool process: a fresh connection of its own writes
        code = 1
        try:
            child = sqlite3.connect(path, timeout=2)
            child.execute("INSERT INTO marks VALUES (2)")
            child.commit()
            code = 0
        finally:
            os._exit(code)
    writer.join()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "the forked process could not write: database is locked"
    with engine.connect() as connection:
        assert sorted(row[0] for row in connection.exec_driver_sql("SELECT x FROM marks")) == [1, 2]
    engine.dispose()
