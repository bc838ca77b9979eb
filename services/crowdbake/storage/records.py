"""What the API and the workers write about a bake, in one place: creation, stage state and progress,
the log, the fan-in barrier, cancel and retry.

Every function takes an open Session and leaves committing to the caller (crowdbake.storage.db.
session_scope), so a route or a task changes a bake in one transaction.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import json
import uuid
from typing import Any

from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session

from crowdbake import __version__
from crowdbake.stages import STAGES
from crowdbake.storage.models import FINAL_BAKE_STATES, Bake, BakeLog, BakePart, BakeStage, utcnow

# Share of a bake's time each stage takes, for one overall progress figure (measured on the sample
# character: the cycle search and the impostor renders dominate).
STAGE_WEIGHTS = {"validate": 0.02, "cycle": 0.28, "poses": 0.12, "impostors": 0.43, "pack": 0.12, "publish": 0.03}
IMPOSTOR_PART_PREFIX = "impostors/"


def new_id(prefix: str) -> str:
    return f"{prefix}_{uuid.uuid4().hex[:20]}"


def code_version() -> str:
    """What, besides inputs and parameters, decides a bake's bytes: the package version."""
    return __version__


def input_key(digests: dict[str, Any], name: str, version: str, params: dict[str, Any], created: str | None = None) -> str:
    """sha256 of everything that decides a bake's output; names the bake's work folder. `created` (the
    manifest time) counts only when given, so the keys of bakes without one are what they were."""
    identity = {"inputs": digests, "name": name, "version": version, "params": params, "code": code_version()}
    if created is not None:
        identity["created"] = created
    canonical = json.dumps(identity, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def create_bake(
    session: Session, *, name: str, version: str, params: dict[str, Any], inputs: dict[str, Any], key: str,
    publish: bool, public: bool, created_by: str | None,
) -> Bake:
    bake = Bake(
        id=new_id("bk"), state="queued", name=name, version=version, params=params, inputs=inputs,
        input_key=key, publish=publish, public=public, created_by=created_by, attempt=0,
        created_at=utcnow(), updated_at=utcnow(),
    )
    bake.stages = [BakeStage(stage=stage, position=position, state="pending", done=0, total=0, retries=0) for position, stage in enumerate(STAGES)]
    session.add(bake)
    append_log(session, bake.id, "INFO", None, f"bake {name}/{version} queued (input key {key[:12]})")
    return bake


def reusable_bake(session: Session, key: str) -> Bake | None:
    """The newest bake with this input key that did not fail or get cancelled (idempotent resubmission)."""
    return session.scalars(
        select(Bake).where(Bake.input_key == key, Bake.state.not_in(("failed", "cancelled"))).order_by(Bake.created_at.desc())
    ).first()


def append_log(session: Session, bake_id: str, level: str, stage: str | None, message: str) -> None:
    session.add(BakeLog(bake_id=bake_id, level=level, stage=stage, message=message, at=utcnow()))


def log_lines(session: Session, bake_id: str, limit: int | None = None) -> list[BakeLog]:
    query = select(BakeLog).where(BakeLog.bake_id == bake_id).order_by(BakeLog.id.desc())
    if limit:
        query = query.limit(limit)
    return list(reversed(session.scalars(query).all()))


def record_redelivery(session: Session, bake_id: str, attempt: int, stage: str, label: str) -> int:
    """Log that a stage task (label: the stage, or a fan-out part's id) arrived again in this attempt,
    which happens when the worker running it was lost (killed, out of memory, crashed) and the broker
    handed the message back. Returns how many times that has happened (this time included).

    The log is the count: no schema change, and the user sees every redelivery in the bake's log.
    """
    marker = f"{label}: delivered again in attempt {attempt}"
    earlier = session.scalar(
        select(func.count()).select_from(BakeLog)
        .where(BakeLog.bake_id == bake_id, BakeLog.message.startswith(marker + ",", autoescape=True))
    )
    count = int(earlier) + 1
    append_log(session, bake_id, "WARNING", stage, f"{marker}, redelivery {count}: the worker running it was lost (killed, out of memory or crashed)")
    return count


def stage_row(session: Session, bake_id: str, stage: str) -> BakeStage:
    row = session.get(BakeStage, (bake_id, stage))
    if row is None:
        raise LookupError(f"bake {bake_id} has no stage {stage!r}")
    return row


def overall_progress(bake: Bake) -> float:
    """0..1: each stage's share (STAGE_WEIGHTS) times its fraction done."""
    total = 0.0
    for row in bake.stages:
        weight = STAGE_WEIGHTS.get(row.stage, 0.0)
        if row.state in ("succeeded", "skipped"):
            total += weight
        elif row.total > 0:
            total += weight * min(row.done / row.total, 1.0)
    return round(min(total, 1.0), 4)


def mark_running(session: Session, bake: Bake, stage: str) -> BakeStage:
    now = utcnow()
    if bake.state == "queued":
        bake.state = "running"
    bake.started_at = bake.started_at or now
    row = stage_row(session, bake.id, stage)
    if row.state in ("pending", "retrying", "failed", "cancelled"):
        row.state = "running"
    row.started_at = row.started_at or now
    return row


def finish_stage(session: Session, bake_id: str, stage: str, seconds: float, result: dict[str, Any] | None) -> None:
    row = stage_row(session, bake_id, stage)
    row.state = "succeeded"
    row.finished_at = utcnow()
    row.seconds = round((row.seconds or 0.0) + seconds, 3) if stage == "impostors" else round(seconds, 3)
    if row.total == 0:
        row.done = row.total = 1
    else:
        row.done = row.total
    row.result = result


def set_progress(session: Session, bake_id: str, stage: str, done: int, total: int) -> None:
    session.execute(
        update(BakeStage).where(BakeStage.bake_id == bake_id, BakeStage.stage == stage, BakeStage.state == "running")
        .values(done=int(done), total=int(total))
    )


def fail_bake(session: Session, bake: Bake, stage: str, error: dict[str, Any]) -> None:
    """Record the bake as failed at `stage` with `error` ({title, detail, type, field?})."""
    now = utcnow()
    bake.state = "failed"
    bake.error = {"stage": stage, **error}
    bake.finished_at = now
    row = stage_row(session, bake.id, stage)
    row.state = "failed"
    row.finished_at = now
    append_log(session, bake.id, "ERROR", stage, f"{error.get('title', 'failed')}: {error.get('detail', '')}")


def succeed_bake(session: Session, bake: Bake) -> None:
    bake.state = "succeeded"
    bake.finished_at = utcnow()
    append_log(session, bake.id, "INFO", None, "bake succeeded")


def cancel_bake(session: Session, bake: Bake) -> None:
    """Mark the bake cancelled; running tasks see it at their next progress report and stop."""
    now = utcnow()
    bake.state = "cancelled"
    bake.finished_at = now
    for row in bake.stages:
        if row.state in ("pending", "running", "retrying"):
            row.state = "cancelled"
    append_log(session, bake.id, "INFO", None, "bake cancelled")


def reset_for_retry(session: Session, bake: Bake) -> None:
    """Start a failed or cancelled bake again as a new attempt. Stage outputs stay in the work folder,
    so stages that had finished return at once; messages of the old attempt are ignored."""
    bake.attempt += 1
    bake.state = "queued"
    bake.error = None
    bake.finished_at = None
    bake.fan_in_attempt = None
    for row in bake.stages:
        row.state, row.done, row.total, row.retries = "pending", 0, 0, 0
        row.seconds = row.started_at = row.finished_at = row.result = None
    session.execute(delete(BakePart).where(BakePart.bake_id == bake.id))
    append_log(session, bake.id, "INFO", None, f"retry: attempt {bake.attempt}")


def is_final(bake: Bake) -> bool:
    return bake.state in FINAL_BAKE_STATES


# ------------------------------------------------------------------------------------- fan-out/in


def record_fan_out(session: Session, bake_id: str, impostor_tasks: list[dict[str, Any]], stages: tuple[str, ...] = ()) -> list[str]:
    """Register the parts the pack stage waits for: one per impostor-views task (crowdbake.stages.impostors.impostor_tasks,
    which needs the impostor plan only), and one per stage in `stages` that runs beside them (the poses
    stage: its part id is the stage's name). Returns the impostor part ids in task order."""
    session.execute(delete(BakePart).where(BakePart.bake_id == bake_id))
    for stage in stages:
        session.add(BakePart(bake_id=bake_id, part=stage, stage=stage, spec={}, done=False))
    part_ids = []
    for index, spec in enumerate(impostor_tasks):
        part_id = f"{IMPOSTOR_PART_PREFIX}{spec.get('id', index)}"
        part_ids.append(part_id)
        session.add(BakePart(bake_id=bake_id, part=part_id, stage="impostors", spec=spec, done=False))
    impostors = stage_row(session, bake_id, "impostors")
    impostors.total, impostors.done = len(impostor_tasks), 0
    return part_ids


def complete_part(session: Session, bake_id: str, part: str) -> int:
    """Mark one part done; returns how many parts are still undone.

    Call it first thing in a fresh transaction: it starts by writing the bake's row, which serialises
    finishing parts (a row lock in PostgreSQL, the write lock in SQLite), so the last of two parts
    finishing together sees the other's mark and no count is taken from a stale snapshot.
    """
    session.execute(update(Bake).where(Bake.id == bake_id).values(updated_at=utcnow()))
    session.execute(update(BakePart).where(BakePart.bake_id == bake_id, BakePart.part == part).values(done=True))
    if part.startswith(IMPOSTOR_PART_PREFIX):
        done = session.scalar(
            select(func.count()).select_from(BakePart)
            .where(BakePart.bake_id == bake_id, BakePart.stage == "impostors", BakePart.done.is_(True))
        )
        session.execute(update(BakeStage).where(BakeStage.bake_id == bake_id, BakeStage.stage == "impostors").values(done=done))
    return int(session.scalar(select(func.count()).select_from(BakePart).where(BakePart.bake_id == bake_id, BakePart.done.is_(False))))


def impostor_parts_left(session: Session, bake_id: str) -> int:
    return int(session.scalar(
        select(func.count()).select_from(BakePart)
        .where(BakePart.bake_id == bake_id, BakePart.stage == "impostors", BakePart.done.is_(False))
    ))


def claim_fan_in(session: Session, bake_id: str, attempt: int) -> bool:
    """True for exactly one caller per attempt: the one that may enqueue the pack stage. A conditional
    UPDATE is atomic in SQLite and PostgreSQL alike, so two parts finishing together cannot both win."""
    result = session.execute(
        update(Bake)
        .where(Bake.id == bake_id, Bake.attempt == attempt, (Bake.fan_in_attempt.is_(None)) | (Bake.fan_in_attempt < attempt))
        .values(fan_in_attempt=attempt)
    )
    return result.rowcount == 1


def to_utc(value: dt.datetime | None) -> dt.datetime | None:
    """SQLite returns naive datetimes; everything stored is UTC."""
    if value is not None and value.tzinfo is None:
        return value.replace(tzinfo=dt.timezone.utc)
    return value
