"""What the workers and the sweeper write about a bake, in one place: stage state and progress, the
log, a bake's end, the delivery bookkeeping of the sweeper (which stage is due, which delivery runs it,
its heartbeat) and the fan-in barrier. What a caller's request does (submit, cancel, retry, publish
later) is in crowdbake.storage.bake_requests, built on this module.

Every function takes an open Session and leaves committing to the caller (crowdbake.storage.db.
session_scope), so a route or a task changes a bake in one transaction.

State transitions that two callers may race for (retry, cancel, publish later, a worker claiming a
stage, the sweeper re-queuing one) start with `lock_bake`: a conditional UPDATE of the bake's row,
which takes the row lock in PostgreSQL and the write lock in SQLite, so the checks that follow read
what every earlier transition committed and exactly one of two racing callers wins (the rowcount of
the UPDATE decides).
"""
from __future__ import annotations

import datetime as dt
import math
import os
import re
import socket
import uuid
from dataclasses import dataclass
from typing import Any, Iterable

from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session

from crowdbake.stage_names import FAN_OUT_STAGES
from crowdbake.storage.models import FINAL_BAKE_STATES, Bake, BakeLog, BakePart, BakeStage, utcnow

LIVE_BAKE_STATES = ("queued", "running")

# Share of a bake's time each stage takes, for one overall progress figure (measured on the sample
# character: the cycle search and the impostor renders dominate; the loops stage searches a timeline's
# clips, the cycle stage then joins them or, for one clip, searches it).
STAGE_WEIGHTS = {"validate": 0.02, "loops": 0.12, "cycle": 0.12, "probes": 0.06, "poses": 0.10, "impostors": 0.43, "pack": 0.12, "publish": 0.03}


def new_id(prefix: str) -> str:
    return f"{prefix}_{uuid.uuid4().hex[:20]}"


# Ids that come from outside (paths, request bodies) are looked up only when they could be ids at all:
# PostgreSQL refuses a text parameter holding NUL with an error, and no id is longer than this.
_ID_SHAPE = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def by_id(session: Session, model: type, ident: str):
    """The `model` row whose primary key is the caller-given `ident`, or None, also when `ident` cannot
    be an id (wrong characters or length): a malformed id names nothing, like an unknown one."""
    if not isinstance(ident, str) or not _ID_SHAPE.fullmatch(ident):
        return None
    return session.get(model, ident)


def release_reservations(bake: Bake) -> None:
    """A bake that ended lets go of its input key and version: a failed or cancelled one can be
    submitted again as a new bake, and a published version is held by its bundle row from then on."""
    bake.live_key = None
    bake.publish_slot = None


def append_log(session: Session, bake_id: str, level: str, stage: str | None, message: str) -> None:
    session.add(BakeLog(bake_id=bake_id, level=level, stage=stage, message=message, at=utcnow()))


def log_lines(session: Session, bake_id: str, limit: int | None = None) -> list[BakeLog]:
    query = select(BakeLog).where(BakeLog.bake_id == bake_id).order_by(BakeLog.id.desc())
    if limit:
        query = query.limit(limit)
    return list(reversed(session.scalars(query).all()))


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
    if row.state in ("pending", "queued", "retrying", "failed", "cancelled"):
        row.state = "running"
    row.started_at = row.started_at or now
    return row


def json_safe(value: Any) -> Any:
    """`value` with every non-finite float (a PSNR of identical pictures is +inf) as None: JSON has no
    Infinity or NaN, and PostgreSQL's json type refuses them where SQLite stored them."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    return value


def finish_stage(session: Session, bake_id: str, stage: str, seconds: float, result: dict[str, Any] | None) -> None:
    row = stage_row(session, bake_id, stage)
    row.state = "succeeded"
    row.finished_at = utcnow()
    row.owner = row.heartbeat_at = None
    row.seconds = round((row.seconds or 0.0) + seconds, 3) if stage in FAN_OUT_STAGES else round(seconds, 3)
    if row.total == 0:
        row.done = row.total = 1
    else:
        row.done = row.total
    row.result = json_safe(result)


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
    release_reservations(bake)
    row = stage_row(session, bake.id, stage)
    row.state = "failed"
    row.finished_at = now
    row.owner = row.heartbeat_at = None
    append_log(session, bake.id, "ERROR", stage, f"{error.get('title', 'failed')}: {error.get('detail', '')}")


def succeed_bake(session: Session, bake: Bake) -> None:
    bake.state = "succeeded"
    bake.finished_at = utcnow()
    release_reservations(bake)
    append_log(session, bake.id, "INFO", None, "bake succeeded")


def lock_bake(session: Session, bake_id: str, attempt: int | None = None, states: Iterable[str] | None = None) -> Bake | None:
    """Lock the bake's row for this transaction (call first in a fresh transaction) and return it,
    freshly read; None when it does not exist or is not at `attempt` / in one of `states`.

    The lock is a conditional UPDATE: PostgreSQL holds the row lock and SQLite the database's write
    lock until commit, so every check made after this sees the latest committed state, and two
    transitions of one bake (a retry and a retry, a cancel and a publish claim) run one after the other."""
    query = update(Bake).where(Bake.id == bake_id)
    if attempt is not None:
        query = query.where(Bake.attempt == attempt)
    if states is not None:
        query = query.where(Bake.state.in_(tuple(states)))
    if session.execute(query.values(updated_at=utcnow())).rowcount != 1:
        return None
    return session.scalars(select(Bake).where(Bake.id == bake_id).execution_options(populate_existing=True)).one()


def is_final(bake: Bake) -> bool:
    return bake.state in FINAL_BAKE_STATES


# ------------------------------------------------------------------------------------- deliveries


def queue_stage(session: Session, bake_id: str, stage: str) -> BakeStage:
    """Make `stage` due: state queued, no message sent yet (the caller sends it and calls `mark_sent`;
    if it never does, the sweeper sends it after CROWDBAKE_DISPATCH_AFTER seconds)."""
    row = stage_row(session, bake_id, stage)
    row.state, row.queued_at, row.sent_at, row.owner, row.heartbeat_at = "queued", utcnow(), None, None, None
    return row


def mark_sent(session: Session, bake_id: str, attempt: int, stage: str, parts: Iterable[str] = ()) -> None:
    """Record that the message of a queued stage (or of its fan-out parts) went to the broker."""
    live = select(Bake.id).where(Bake.id == bake_id, Bake.attempt == attempt).scalar_subquery()
    parts = list(parts)
    if parts:
        session.execute(update(BakePart).where(BakePart.bake_id == live, BakePart.part.in_(parts), BakePart.sent_at.is_(None)).values(sent_at=utcnow()))
    else:
        session.execute(update(BakeStage).where(BakeStage.bake_id == live, BakeStage.stage == stage, BakeStage.state == "queued",
                                                BakeStage.sent_at.is_(None)).values(sent_at=utcnow()))


def this_host() -> str:
    return socket.gethostname()


def delivery_owner(task_id: str | None) -> str:
    """Who runs a delivery: "host:pid:task id" (the pid tells a redelivery on the same host whether
    the process that had the message is gone)."""
    return f"{this_host()}:{os.getpid()}:{task_id or '-'}"


def owner_is_dead(owner: str) -> bool:
    """True when `owner` ran on this host and its process is gone (or a zombie); False when it is
    alive or on another host (there only its heartbeat can tell)."""
    host, _, rest = owner.partition(":")
    pid_text = rest.partition(":")[0]
    if host != this_host() or not pid_text.isdigit():
        return False
    pid = int(pid_text)
    if pid == os.getpid():
        return False
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except (FileNotFoundError, ProcessLookupError):
        return True
    except OSError:
        return False


def _host_pid(owner: str) -> tuple[str, int | None]:
    host, _, rest = owner.partition(":")
    pid_text = rest.partition(":")[0]
    return host, int(pid_text) if pid_text.isdigit() else None


def _marked_by_my_worker(owner: str) -> bool:
    """True when `owner` is the receipt mark of this pool process's own worker (see `mark_received`)."""
    host, pid = _host_pid(owner)
    return host == this_host() and pid == os.getppid()


def mark_received(session: Session, bake_id: str, attempt: int, stage: str, part: str | None, owner: str) -> bool:
    """A worker's main process took this unit's message from the broker (before a pool process runs
    it): the unit is marked as that worker's, and the worker's heartbeat (`beat_received`) keeps the
    mark fresh. If the worker dies holding the message (a lost machine; the filesystem broker loses
    such a message, Redis keeps it for its visibility timeout), the mark goes stale and the sweeper
    re-queues the unit. Only an unowned, unfinished unit of a live attempt is marked."""
    table = BakePart if part else BakeStage
    key = (BakePart.part == part) if part else (BakeStage.stage == stage)
    live = select(Bake.id).where(Bake.id == bake_id, Bake.attempt == attempt, Bake.state.in_(LIVE_BAKE_STATES)).scalar_subquery()
    query = update(table).where(table.bake_id == live, key, table.owner.is_(None))
    query = query.where(BakePart.done.is_(False)) if part else query.where(BakeStage.state.in_(("pending", "queued", "retrying")))
    return session.execute(query.values(owner=owner, heartbeat_at=utcnow())).rowcount == 1


def beat_received(session: Session, owners: Iterable[str]) -> int:
    """Refresh the marks of the units a worker's main process received, still holds, and no pool
    process has claimed yet (`owners`: their "host:pid:task id" marks). Only what the worker still
    holds: a worker that loses its broker connection drops the messages it had not started (Celery
    clears its reserved requests; the broker hands them out again), and a mark kept beating for such
    a message would hide it from the sweeper for ever. Returns how many."""
    owners = sorted(set(owners))
    if not owners:
        return 0
    now, count = utcnow(), 0
    for table in (BakeStage, BakePart):
        count += session.execute(update(table).where(table.owner.in_(owners)).values(heartbeat_at=now)).rowcount
    return count


@dataclass(frozen=True)
class Claim:
    """The outcome of a delivery's claim: `won` (run it), with `retries` taken so far and `lost_owner`
    when it took over from a delivery whose worker was lost; else `reason` says why to drop it."""

    won: bool
    reason: str = ""
    retries: int = 0
    lost_owner: str | None = None


def _unit(session: Session, bake_id: str, stage: str, part: str | None):
    return session.get(BakePart, (bake_id, part)) if part else session.get(BakeStage, (bake_id, stage))


def claim_delivery(session: Session, bake_id: str, attempt: int, stage: str, part: str | None, owner: str,
                   stale_before: dt.datetime) -> Claim:
    """Decide whether this delivery of `stage` (or fan-out `part`) runs it. Exactly one delivery owns a
    unit at a time; a duplicate message (sent twice, a visibility timeout, the sweeper) finds it done
    or owned by a live delivery and is dropped, so a late original never runs beside its replacement.

    A unit owned by a delivery whose process is gone (this host) or whose heartbeat is older than
    `stale_before` is taken over: its worker was lost, which counts one retry."""
    bake = lock_bake(session, bake_id, attempt=attempt, states=LIVE_BAKE_STATES)
    if bake is None:
        return Claim(False, f"bake {bake_id} attempt {attempt} is no longer live")
    unit = _unit(session, bake_id, stage, part)
    if unit is None:
        return Claim(False, f"bake {bake_id} has no {part or stage} in attempt {attempt}")
    finished = unit.done if part else unit.state in ("succeeded", "skipped", "failed", "cancelled")
    if finished:
        return Claim(False, f"{part or stage} of bake {bake_id} is already {('done' if part else unit.state)}")
    lost_owner = None
    if unit.owner is not None and unit.owner != owner and not _marked_by_my_worker(unit.owner):
        beat = to_utc(unit.heartbeat_at)
        if not owner_is_dead(unit.owner) and beat is not None and beat >= stale_before:
            return Claim(False, f"{part or stage} of bake {bake_id} is running elsewhere ({unit.owner})")
        lost_owner = unit.owner
        unit.retries += 1
        if part:
            stage_row(session, bake_id, stage).retries += 1
    now = utcnow()
    unit.owner, unit.heartbeat_at = owner, now
    if part:
        # The fan-out stage's row shows its parts as a whole.
        mark_running(session, bake, stage)
    else:
        if bake.state == "queued":
            bake.state = "running"
        bake.started_at = bake.started_at or now
        unit.state = "running"
        unit.started_at = unit.started_at or now
    return Claim(True, retries=unit.retries, lost_owner=lost_owner)


def still_owner(session: Session, bake_id: str, attempt: int, stage: str, part: str | None, owner: str) -> Bake | None:
    """Lock the bake and return it if this delivery still owns its unit in a live attempt, else None
    (a worker finishing a stage checks this before it records the result and queues the next one:
    a late original whose unit was handed to another delivery records nothing)."""
    bake = lock_bake(session, bake_id, attempt=attempt, states=LIVE_BAKE_STATES)
    if bake is None:
        return None
    unit = _unit(session, bake_id, stage, part)
    return bake if unit is not None and unit.owner == owner else None


def release_delivery(session: Session, bake_id: str, stage: str, part: str | None, owner: str) -> None:
    """The delivery stopped owning its unit (finished, failed or handed to a Celery retry). The release
    stays in `heartbeat_at` as the unit's last sign of life: a unit handed to a Celery retry is sent
    again by the sweeper only if the retry's message does not take it in time (sweeps.resend_due)."""
    table = BakePart if part else BakeStage
    key = (BakePart.part == part) if part else (BakeStage.stage == stage)
    session.execute(update(table).where(table.bake_id == bake_id, key, table.owner == owner).values(owner=None, heartbeat_at=utcnow()))


def heartbeat(session: Session, bake_id: str, attempt: int, stage: str, part: str | None, owner: str) -> bool:
    """One heartbeat of a running delivery. False when it should stop: the bake was cancelled or
    failed, a newer attempt replaced it, or the sweeper gave its unit to another delivery."""
    table = BakePart if part else BakeStage
    key = (BakePart.part == part) if part else (BakeStage.stage == stage)
    live = select(Bake.id).where(Bake.id == bake_id, Bake.attempt == attempt, Bake.state.in_(LIVE_BAKE_STATES)).scalar_subquery()
    result = session.execute(update(table).where(table.bake_id == live, key, table.owner == owner).values(heartbeat_at=utcnow()))
    return result.rowcount == 1


# ------------------------------------------------------------------------------------- fan-out/in


def record_fan_out(session: Session, bake_id: str, items: list[dict[str, Any]], stage: str = "impostors") -> list[str]:
    """Register the parts of a fan-out stage (crowdbake.stage_names.FAN_OUT_STAGES), one per item of its
    node (a JSON object; its "id", else its position, names the part "<stage>/<id>"), which the next
    stage waits for. Returns the part ids in item order. Parts of other stages stay (their listings
    tell later stages what to fetch)."""
    session.execute(delete(BakePart).where(BakePart.bake_id == bake_id, BakePart.stage == stage))
    part_ids = []
    now = utcnow()
    for index, spec in enumerate(items):
        part_id = f"{stage}/{spec.get('id', index)}"
        part_ids.append(part_id)
        session.add(BakePart(bake_id=bake_id, part=part_id, stage=stage, spec=spec, done=False, retries=0, queued_at=now))
    row = stage_row(session, bake_id, stage)
    row.total, row.done = len(items), 0
    if row.state == "pending":
        row.state, row.queued_at = "queued", now
    return part_ids


def complete_part(session: Session, bake_id: str, part: str) -> int:
    """Mark one part done; returns how many parts of its stage are still undone.

    Call it first thing in a fresh transaction: it starts by writing the bake's row, which serialises
    finishing parts (a row lock in PostgreSQL, the write lock in SQLite), so the last of two parts
    finishing together sees the other's mark and no count is taken from a stale snapshot.
    """
    session.execute(update(Bake).where(Bake.id == bake_id).values(updated_at=utcnow()))
    session.execute(update(BakePart).where(BakePart.bake_id == bake_id, BakePart.part == part).values(done=True, owner=None, heartbeat_at=None))
    stage = part.partition("/")[0]
    done = session.scalar(
        select(func.count()).select_from(BakePart).where(BakePart.bake_id == bake_id, BakePart.stage == stage, BakePart.done.is_(True))
    )
    session.execute(update(BakeStage).where(BakeStage.bake_id == bake_id, BakeStage.stage == stage).values(done=done))
    return parts_left(session, bake_id, stage)


def parts_left(session: Session, bake_id: str, stage: str) -> int:
    """How many parts of a fan-out stage are not done."""
    return int(session.scalar(
        select(func.count()).select_from(BakePart)
        .where(BakePart.bake_id == bake_id, BakePart.stage == stage, BakePart.done.is_(False))
    ))


def claim_fan_in(session: Session, bake_id: str, attempt: int, stage: str = "pack") -> bool:
    """True for exactly one caller per attempt: the one that may enqueue `stage`, the stage after a
    fan-out, which queues it here. A conditional UPDATE of its row (pending, in this attempt) is atomic
    in SQLite and PostgreSQL alike, so two parts finishing together cannot both win; a retry sets the
    row pending again, so each attempt has its own barrier."""
    live = select(Bake.id).where(Bake.id == bake_id, Bake.attempt == attempt).scalar_subquery()
    result = session.execute(
        update(BakeStage).where(BakeStage.bake_id == live, BakeStage.stage == stage, BakeStage.state == "pending")
        .values(state="queued", queued_at=utcnow(), sent_at=None, owner=None, heartbeat_at=None)
    )
    return result.rowcount == 1


def to_utc(value: dt.datetime | None) -> dt.datetime | None:
    """SQLite returns naive datetimes; everything stored is UTC."""
    if value is not None and value.tzinfo is None:
        return value.replace(tzinfo=dt.timezone.utc)
    return value
