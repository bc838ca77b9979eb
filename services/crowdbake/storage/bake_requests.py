"""What a caller's request does to a bake (the API's submit, cancel, retry and publish routes): the input
key that names its work, its creation with the reservations it holds while live (the input key and the
"<name>/<version>" it will publish), and the transitions a user starts: cancel, retry, publish later.

What workers and the sweeper write (stage state, progress, the log, deliveries, the fan-in barrier) is in
crowdbake.storage.records, which this module builds on (never the other way round). As there, every
function takes an open Session and leaves committing to the caller, and a transition two callers may
race for starts with `records.lock_bake`.
"""
from __future__ import annotations

import hashlib
import json
from typing import Any

from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session

from crowdbake import __version__
from crowdbake.stage_names import STAGES
from crowdbake.storage.models import Bake, BakePart, BakeStage, utcnow
from crowdbake.storage.records import (
    LIVE_BAKE_STATES, append_log, lock_bake, new_id, queue_stage, release_reservations, stage_row,
)


def code_version() -> str:
    """What, besides inputs and parameters, decides a bake's bytes: the package version."""
    return __version__


def input_key(digests: dict[str, Any], name: str, version: str, params: dict[str, Any], created: str | None = None) -> str:
    """sha256 of everything that decides a bake's output; names the bake's work folder. `created` (the
    manifest time) counts only when given, so leaving it out adds nothing to the key."""
    identity = {"inputs": digests, "name": name, "version": version, "params": params, "code": code_version()}
    if created is not None:
        identity["created"] = created
    canonical = json.dumps(identity, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def create_bake(
    session: Session, *, name: str, version: str, params: dict[str, Any], inputs: dict[str, Any], key: str,
    publish: bool, public: bool, created_by: str | None,
) -> Bake:
    """A new queued bake holding its reservations (`live_key`, and `publish_slot` when it publishes).
    The caller's commit raises IntegrityError when a live bake holds either already (`live_bake`,
    `slot_holder`); its first stage is queued, its message not yet sent."""
    now = utcnow()
    bake = Bake(
        id=new_id("bk"), state="queued", name=name, version=version, params=params, inputs=inputs,
        input_key=key, publish=publish, public=public, created_by=created_by, attempt=0,
        created_at=now, updated_at=now, live_key=key, publish_slot=publish_slot(name, version) if publish else None,
    )
    bake.stages = [BakeStage(stage=stage, position=position, state="pending", done=0, total=0, retries=0) for position, stage in enumerate(STAGES)]
    bake.stages[0].state, bake.stages[0].queued_at = "queued", now
    session.add(bake)
    append_log(session, bake.id, "INFO", None, f"bake {name}/{version} queued (input key {key[:12]})")
    return bake


def publish_slot(name: str, version: str) -> str:
    return f"{name}/{version}"


def reusable_bake(session: Session, key: str) -> Bake | None:
    """The newest bake with this input key that did not fail or get cancelled (idempotent resubmission)."""
    return session.scalars(
        select(Bake).where(Bake.input_key == key, Bake.state.not_in(("failed", "cancelled"))).order_by(Bake.created_at.desc())
    ).first()


def live_bake(session: Session, key: str) -> Bake | None:
    """The queued or running bake holding this input key, if any."""
    return session.scalars(select(Bake).where(Bake.live_key == key)).first()


def slot_holder(session: Session, name: str, version: str) -> Bake | None:
    """The queued or running bake that will publish name/version, if any (once published, the bundle's
    own row holds the version)."""
    return session.scalars(select(Bake).where(Bake.publish_slot == publish_slot(name, version))).first()


class TransitionRefused(Exception):
    """A state transition lost its race or does not apply to the bake's state (the API answers 409)."""


def cancel_bake(session: Session, bake_id: str) -> Bake:
    """Cancel a queued or running bake; running tasks see it within a heartbeat and stop.

    A bake whose publish stage is running is not cancelled (TransitionRefused): the bundle folder and
    its record are written together, and a cancel between the two left a folder without a record."""
    bake = lock_bake(session, bake_id, states=LIVE_BAKE_STATES)
    if bake is None:
        current = session.get(Bake, bake_id)
        raise TransitionRefused(f"bake {bake_id} already {current.state if current else 'gone'}")
    publish = stage_row(session, bake_id, "publish")
    if publish.started_at is not None and publish.state in ("queued", "running", "retrying"):
        raise TransitionRefused(f"bake {bake_id} is publishing {bake.name}/{bake.version}; a publish is not interrupted")
    now = utcnow()
    bake.state = "cancelled"
    bake.finished_at = now
    release_reservations(bake)
    for row in bake.stages:
        if row.state in ("pending", "queued", "running", "retrying"):
            row.state = "cancelled"
    append_log(session, bake.id, "INFO", None, "bake cancelled")
    return bake


def retry_bake(session: Session, bake_id: str, seen_attempt: int) -> Bake:
    """Start a failed or cancelled bake again as a new attempt, if it is still at `seen_attempt`.

    A compare-and-set: of two retries of the same attempt exactly one gets the row (the other
    TransitionRefused), so the pipeline never runs twice in one work folder. The retry takes the
    bake's reservations back; IntegrityError at commit means another live bake holds one now.
    Stage outputs stay in the work folder, so stages that had finished return at once; messages of
    the old attempt are dropped by the attempt check."""
    result = session.execute(
        update(Bake).where(Bake.id == bake_id, Bake.attempt == seen_attempt, Bake.state.in_(("failed", "cancelled")))
        .values(attempt=Bake.attempt + 1, state="queued", error=None, finished_at=None, fan_in_attempt=None, updated_at=utcnow())
    )
    if result.rowcount != 1:
        current = session.get(Bake, bake_id)
        raise TransitionRefused(f"bake {bake_id} is {current.state if current else 'gone'} at attempt "
                                f"{current.attempt if current else '-'}; only a failed or cancelled bake can be retried, once")
    bake = session.scalars(select(Bake).where(Bake.id == bake_id).execution_options(populate_existing=True)).one()
    bake.live_key = bake.input_key
    bake.publish_slot = publish_slot(bake.name, bake.version) if bake.publish else None
    now = utcnow()
    for row in bake.stages:
        row.state, row.done, row.total, row.retries = "pending", 0, 0, 0
        row.seconds = row.started_at = row.finished_at = row.result = None
        row.queued_at = row.sent_at = row.owner = row.heartbeat_at = None
    bake.stages[0].state, bake.stages[0].queued_at = "queued", now
    session.execute(delete(BakePart).where(BakePart.bake_id == bake.id))
    append_log(session, bake.id, "INFO", None, f"retry: attempt {bake.attempt}")
    return bake


def request_publish(session: Session, bake_id: str) -> Bake:
    """Queue the publish stage of a bake that succeeded without publishing (TransitionRefused if it
    is not one, or lost the race); IntegrityError at commit when another bake holds the version."""
    bake = lock_bake(session, bake_id, states=("succeeded",))
    if bake is None:
        current = session.get(Bake, bake_id)
        raise TransitionRefused(f"bake {bake_id} is {current.state if current else 'gone'}; only a finished bake can be published")
    stages = {row.stage: row for row in bake.stages}
    if stages["pack"].state != "succeeded":
        raise TransitionRefused(f"bake {bake_id} was not packed; only a finished bake can be published")
    if stages["publish"].state == "succeeded":
        raise TransitionRefused(f"bake {bake_id} is already published")
    bake.publish, bake.state, bake.finished_at = True, "running", None
    bake.publish_slot = publish_slot(bake.name, bake.version)
    queue_stage(session, bake_id, "publish")
    append_log(session, bake.id, "INFO", "publish", "publish requested")
    return bake
