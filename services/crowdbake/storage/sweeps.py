"""What the sweeper reads and changes in the database: deliveries whose worker stopped beating (re-queued
once, by whichever sweeper wins the row lock), and stages queued but never sent (crowdbake.jobs.sweeper)."""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

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


def unsent_deliveries(session: Session, queued_before: dt.datetime) -> list[Delivery]:
    """Queued stages and parts of live bakes whose message was never sent, queued before `queued_before`."""
    live = Bake.state.in_(records.LIVE_BAKE_STATES)
    stages = session.execute(
        select(Bake.id, Bake.attempt, BakeStage.stage).join(BakeStage, BakeStage.bake_id == Bake.id)
        .where(live, BakeStage.state == "queued", BakeStage.sent_at.is_(None), BakeStage.owner.is_(None),
               BakeStage.queued_at < queued_before, BakeStage.stage != "impostors")
    ).all()
    parts = session.execute(
        select(Bake.id, Bake.attempt, BakePart.stage, BakePart.part).join(BakePart, BakePart.bake_id == Bake.id)
        .where(live, BakePart.done.is_(False), BakePart.sent_at.is_(None), BakePart.owner.is_(None), BakePart.queued_at < queued_before)
    ).all()
    return [Delivery(*row) for row in stages] + [Delivery(*row) for row in parts]


def current_delivery(session: Session, bake: Bake) -> Delivery | None:
    """The bake's stage that is queued and unsent, if any (a resubmit sends it at once)."""
    for row in bake.stages:
        if row.state == "queued" and row.sent_at is None and row.owner is None and row.stage != "impostors":
            return Delivery(bake.id, bake.attempt, row.stage)
    return None
