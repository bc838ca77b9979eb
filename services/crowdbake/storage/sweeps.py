"""What the sweeper reads and changes in the database: deliveries whose worker stopped beating (re-queued
once, by whichever sweeper wins the row lock), deliveries sent but never taken (declared unsent again,
the same way), and stages queued but never sent (crowdbake.jobs.sweeper)."""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from sqlalchemy import or_, select
from sqlalchemy.orm import Session

from crowdbake.stage_names import FAN_OUT_STAGES
from crowdbake.storage import records
from crowdbake.storage.models import Bake, BakePart, BakeStage, utcnow


@dataclass(frozen=True)
class Delivery:
    """A unit of a bake the sweeper acts on: a stage, or one fan-out part of it."""

    bake_id: str
    attempt: int
    stage: str
    part: str | None = None
    owner: str | None = None
    heartbeat_at: dt.datetime | None = None
    sent_at: dt.datetime | None = None

    @property
    def label(self) -> str:
        return self.part or self.stage


def lost_deliveries(session: Session, stale_before: dt.datetime) -> list[Delivery]:
    """Running stages and parts of live bakes whose last heartbeat is older than `stale_before`."""
    live = Bake.state.in_(records.LIVE_BAKE_STATES)
    stages = session.execute(
        select(Bake.id, Bake.attempt, BakeStage.stage, BakeStage.owner, BakeStage.heartbeat_at).join(BakeStage, BakeStage.bake_id == Bake.id)
        .where(live, BakeStage.owner.is_not(None), BakeStage.heartbeat_at < stale_before)
    ).all()
    parts = session.execute(
        select(Bake.id, Bake.attempt, BakePart.stage, BakePart.part, BakePart.owner, BakePart.heartbeat_at).join(BakePart, BakePart.bake_id == Bake.id)
        .where(live, BakePart.done.is_(False), BakePart.owner.is_not(None), BakePart.heartbeat_at < stale_before)
    ).all()
    return ([Delivery(bake_id, attempt, stage, None, owner, beat) for bake_id, attempt, stage, owner, beat in stages]
            + [Delivery(bake_id, attempt, stage, part, owner, beat) for bake_id, attempt, stage, part, owner, beat in parts])


def requeue_lost(session: Session, lost: Delivery, max_retries: int) -> str | None:
    """Take a lost delivery's unit back (compare-and-set on its owner, so of several sweepers one
    wins) and queue it again, one retry counted; past `max_retries` fail the bake instead.
    Returns "requeued", "failed", or None when someone else got there first."""
    bake = records.lock_bake(session, lost.bake_id, attempt=lost.attempt, states=records.LIVE_BAKE_STATES)
    if bake is None:
        return None
    unit = records._unit(session, lost.bake_id, lost.stage, lost.part)
    if unit is None or unit.owner != lost.owner or records.to_utc(unit.heartbeat_at) != records.to_utc(lost.heartbeat_at):
        return None
    unit.retries += 1
    unit.owner = unit.heartbeat_at = None
    if lost.part:
        records.stage_row(session, lost.bake_id, lost.stage).retries += 1
    seen = records.to_utc(lost.heartbeat_at).strftime("%Y-%m-%dT%H:%M:%SZ") if lost.heartbeat_at else "?"
    if unit.retries > max_retries:
        records.fail_bake(session, bake, lost.stage, {
            "type": "worker-lost", "title": f"the {lost.stage} stage keeps losing its worker",
            "detail": f"{lost.label} lost its worker {unit.retries} times, more than {max_retries} (CROWDBAKE_TASK_MAX_RETRIES): "
                      f"no heartbeat since {seen}; retry the bake",
        })
        return "failed"
    now = utcnow()
    unit.queued_at, unit.sent_at = now, None
    if not lost.part:
        unit.state = "queued"
    records.append_log(session, lost.bake_id, "WARNING", lost.stage,
               f"stage {lost.label} lost its worker at {seen} (last heartbeat of {lost.owner}); re-queued, retry {unit.retries} of {max_retries}")
    return "requeued"


# Stage states in which an unowned stage row waits for a delivery to take it ("retrying": its delivery
# let go of it for a Celery retry; "running" without an owner should not happen, and is taken too).
_WAITING_STAGE_STATES = ("queued", "retrying", "running")


def resend_due(now: dt.datetime, timeout_s: float, retry_wait_s: float, queued_at: dt.datetime | None,
               sent_at: dt.datetime, released_at: dt.datetime | None) -> bool:
    """Whether a unit sent at `sent_at` that no delivery owns has waited long enough to be sent again.

    Nothing in the database tells a message lost with its worker (taken from the broker, then the worker
    died before its receipt committed: `mark_received`) from one still waiting behind others in the
    queue, so the wait grows with the unit's age: at least `timeout_s` (the heartbeat timeout) since the
    send, and at least as long as it had waited in the database before that send (`sent_at - queued_at`).
    Each resend moves `sent_at`, so a unit waiting behind a long queue is sent again after T, 2T, 4T, ...
    (a few copies, log2 of its wait; each extra copy is dropped by records.claim_delivery), never once per
    sweep. A unit a delivery let go of for a Celery retry (`released_at`, see records.release_delivery)
    waits `timeout_s` plus the longest retry countdown (`retry_wait_s`) from the release instead."""
    if released_at is not None:
        return (now - records.to_utc(released_at)).total_seconds() >= timeout_s + retry_wait_s
    sent_at = records.to_utc(sent_at)
    waited_before = (sent_at - records.to_utc(queued_at)).total_seconds() if queued_at is not None else 0.0
    return (now - sent_at).total_seconds() >= max(timeout_s, waited_before)


def silent_deliveries(session: Session, now: dt.datetime, timeout_s: float, retry_wait_s: float) -> list[Delivery]:
    """Stages and parts of live bakes whose message was sent, that no delivery owns or finished, and
    that are due to be sent again (`resend_due`): their message was most likely lost with a worker."""
    live = Bake.state.in_(records.LIVE_BAKE_STATES)
    quiet_before = now - dt.timedelta(seconds=timeout_s)
    stages = session.execute(
        select(Bake.id, Bake.attempt, BakeStage.stage, BakeStage.queued_at, BakeStage.sent_at, BakeStage.heartbeat_at)
        .join(BakeStage, BakeStage.bake_id == Bake.id)
        .where(live, BakeStage.state.in_(_WAITING_STAGE_STATES), BakeStage.stage.not_in(FAN_OUT_STAGES), BakeStage.owner.is_(None),
               BakeStage.sent_at < quiet_before, or_(BakeStage.heartbeat_at.is_(None), BakeStage.heartbeat_at < quiet_before))
    ).all()
    parts = session.execute(
        select(Bake.id, Bake.attempt, BakePart.stage, BakePart.part, BakePart.queued_at, BakePart.sent_at, BakePart.heartbeat_at)
        .join(BakePart, BakePart.bake_id == Bake.id)
        .where(live, BakePart.done.is_(False), BakePart.owner.is_(None),
               BakePart.sent_at < quiet_before, or_(BakePart.heartbeat_at.is_(None), BakePart.heartbeat_at < quiet_before))
    ).all()
    found = [(Delivery(bake_id, attempt, stage, None, None, beat, sent), queued) for bake_id, attempt, stage, queued, sent, beat in stages]
    found += [(Delivery(bake_id, attempt, stage, part, None, beat, sent), queued) for bake_id, attempt, stage, part, queued, sent, beat in parts]
    return [delivery for delivery, queued in found
            if resend_due(now, timeout_s, retry_wait_s, queued, delivery.sent_at, delivery.heartbeat_at)]


def take_back_silent(session: Session, silent: Delivery) -> bool:
    """Declare a silent delivery's unit unsent (sent_at empty, a stage queued again), so the sweeper
    sends it now and records the send. A compare-and-set on the unit's owner, sent_at and heartbeat_at
    under the bake's lock: of several sweepers one takes it, and a unit a worker took meanwhile (its
    receipt or claim committed after the read) is left alone. No retry is counted: nothing failed for
    sure (the message may only be waiting), and the copy that comes second is dropped by
    records.claim_delivery. A crash after this commit leaves the unit unsent, which the next pass sends."""
    bake = records.lock_bake(session, silent.bake_id, attempt=silent.attempt, states=records.LIVE_BAKE_STATES)
    if bake is None:
        return False
    unit = records._unit(session, silent.bake_id, silent.stage, silent.part)
    if unit is None or unit.owner is not None or (unit.done if silent.part else unit.state not in _WAITING_STAGE_STATES):
        return False
    if records.to_utc(unit.sent_at) != records.to_utc(silent.sent_at) or records.to_utc(unit.heartbeat_at) != records.to_utc(silent.heartbeat_at):
        return False
    sent = records.to_utc(unit.sent_at).strftime("%Y-%m-%dT%H:%M:%SZ")
    unit.sent_at = unit.heartbeat_at = None
    if not silent.part:
        unit.state = "queued"
    records.append_log(session, silent.bake_id, "WARNING", silent.stage,
                       f"{silent.label}: sent at {sent} and no worker has recorded taking it (its message was lost with a worker "
                       "that died before recording its receipt, or still waits behind others): sent again; a second copy is dropped")
    return True


def unsent_deliveries(session: Session, queued_before: dt.datetime) -> list[Delivery]:
    """Queued stages and parts of live bakes whose message was never sent, queued before `queued_before`."""
    live = Bake.state.in_(records.LIVE_BAKE_STATES)
    stages = session.execute(
        select(Bake.id, Bake.attempt, BakeStage.stage).join(BakeStage, BakeStage.bake_id == Bake.id)
        .where(live, BakeStage.state == "queued", BakeStage.sent_at.is_(None), BakeStage.owner.is_(None),
               BakeStage.queued_at < queued_before, BakeStage.stage.not_in(FAN_OUT_STAGES))
    ).all()
    parts = session.execute(
        select(Bake.id, Bake.attempt, BakePart.stage, BakePart.part).join(BakePart, BakePart.bake_id == Bake.id)
        .where(live, BakePart.done.is_(False), BakePart.sent_at.is_(None), BakePart.owner.is_(None), BakePart.queued_at < queued_before)
    ).all()
    return [Delivery(*row) for row in stages] + [Delivery(*row) for row in parts]


def current_delivery(session: Session, bake: Bake) -> Delivery | None:
    """The bake's stage that is queued and unsent, if any (a resubmit sends it at once)."""
    for row in bake.stages:
        if row.state == "queued" and row.sent_at is None and row.owner is None and row.stage not in FAN_OUT_STAGES:
            return Delivery(bake.id, bake.attempt, row.stage)
    return None
