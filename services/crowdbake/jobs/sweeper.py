"""The sweeper: no bake is left queued or running forever.

One pass (`sweep_once`) does five things, each safe to run in several processes at once:

1. **Lost workers.** A running stage (or fan-out part) whose heartbeat is older than
   CROWDBAKE_HEARTBEAT_TIMEOUT lost its worker (the machine died, the process group was killed, the
   host was partitioned away). It is re-queued with a new message, one retry counted against
   CROWDBAKE_TASK_MAX_RETRIES, and the bake's log says so; past the budget the bake fails with type
   `worker-lost`. The re-queue is a compare-and-set on the unit's owner and heartbeat
   (sweeps.requeue_lost), so of several sweepers exactly one re-queues it.
2. **Messages sent but never taken.** A stage or part whose message was sent but that no delivery
   owns or finished lost its message with a worker that died between taking it from the broker and
   committing its receipt (records.mark_received); Redis hands such a message out again only after
   its visibility timeout (hours). It is sent again once it has been quiet for the heartbeat timeout
   and for as long as it had waited before its last send (sweeps.resend_due: a unit waiting behind a
   long queue gets a few copies, not one per pass), counted as no retry; the copy that comes second
   is dropped by records.claim_delivery. A unit let go of for a Celery retry waits for the retry's
   countdown first.
3. **Unsent messages.** A stage queued in the database whose message never reached the broker (the
   broker was down or frozen when the API or a worker tried) is sent once it has waited
   CROWDBAKE_DISPATCH_AFTER seconds. Sending twice is harmless: the second delivery finds the unit
   claimed or done and is dropped (records.claim_delivery).
4. **Work folders.** A bake's work folder is deleted when it is of no more use: published bakes (the
   worker deletes it right away; this catches the rest), cancelled bakes once their workers had time
   to stop, failed and unpublished bakes CROWDBAKE_WORK_KEEP_SECONDS after they ended, and folders no
   bake names.
5. **Partial publishes.** A publish cut short (the worker killed while copying a bundle) leaves its
   hidden staging folder beside the bundle's versions (crowdbake.storage.bundle_store.staging_folders).
   It is removed once no queued or running bake publishes that name and version and the folder has
   not changed for the heartbeat timeout (a live publish's worker keeps its bake running).

`Sweeper` runs passes every CROWDBAKE_SWEEP_INTERVAL seconds in a daemon thread of the API process
(crowdbake.api.app starts it), so `crowdbake serve` and every API replica have one.
"""
from __future__ import annotations

import concurrent.futures
import datetime as dt
import logging
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from celery import Celery
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from crowdbake.jobs.celery_app import send_stage
from crowdbake.settings import Settings
from crowdbake.stages import plan
from crowdbake.storage import records, sweeps
from crowdbake.storage.bundle_store import staging_folders
from crowdbake.storage.db import session_scope
from crowdbake.storage.models import Bake, utcnow

logger = logging.getLogger(__name__)

# Longest a request waits for the broker to take a message (a frozen Redis never answers; the
# message is then left for the sweeper and the request answers at once).
ENQUEUE_WAIT_S = 3.0
# Threads that send messages for requests: a frozen broker ties them up for its socket timeout, and
# requests beyond these wait ENQUEUE_WAIT_S at most and leave their message to the sweeper.
SEND_THREADS = 4
# run_stage's Celery retry countdown is the backoff times (0.5 + random()), at most 1.5 times
# CROWDBAKE_TASK_RETRY_BACKOFF_MAX (crowdbake.jobs.tasks): a unit let go of for a retry is not sent
# again before that countdown could have run out.
RETRY_JITTER_MAX = 1.5


@dataclass
class SweepReport:
    requeued: list[str] = field(default_factory=list)
    resent: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    sent: list[str] = field(default_factory=list)
    unsent: list[str] = field(default_factory=list)
    removed_work: list[str] = field(default_factory=list)
    removed_partial: list[str] = field(default_factory=list)


def send_delivery(celery: Celery, settings: Settings, delivery: sweeps.Delivery) -> None:
    """Send the message of a stage or of one part of a fan-out stage."""
    if delivery.part:
        send_stage(celery, settings, plan.fan_out_of(delivery.stage).name, delivery.bake_id, delivery.attempt, delivery.part)
    else:
        send_stage(celery, settings, delivery.stage, delivery.bake_id, delivery.attempt)


def send_and_mark(sessions: sessionmaker[Session], celery: Celery, settings: Settings, delivery: sweeps.Delivery) -> None:
    """Send, then record the unit as sent (in that order: a crash in between sends it twice, which is
    harmless, never zero times)."""
    send_delivery(celery, settings, delivery)
    with session_scope(sessions) as session:
        records.mark_sent(session, delivery.bake_id, delivery.attempt, delivery.stage, [delivery.part] if delivery.part else ())


def requeue_lost_workers(sessions: sessionmaker[Session], settings: Settings, now: dt.datetime, report: SweepReport) -> list[sweeps.Delivery]:
    stale_before = now - dt.timedelta(seconds=settings.heartbeat_timeout)
    with session_scope(sessions) as session:
        lost = sweeps.lost_deliveries(session, stale_before)
    requeued = []
    for delivery in lost:
        with session_scope(sessions) as session:
            outcome = sweeps.requeue_lost(session, delivery, settings.task_max_retries)
        if outcome == "requeued":
            logger.warning("bake %s: %s lost its worker %s; re-queued", delivery.bake_id, delivery.label, delivery.owner)
            report.requeued.append(f"{delivery.bake_id}:{delivery.label}")
            requeued.append(delivery)
        elif outcome == "failed":
            logger.error("bake %s: %s lost its worker past the retry budget; failed", delivery.bake_id, delivery.label)
            report.failed.append(f"{delivery.bake_id}:{delivery.label}")
    return requeued


def take_back_silent(sessions: sessionmaker[Session], settings: Settings, now: dt.datetime, report: SweepReport) -> list[sweeps.Delivery]:
    """Units whose message was sent but never taken (module docstring, 2.), declared unsent: the caller
    sends them in this pass."""
    retry_wait = settings.task_retry_backoff_max * RETRY_JITTER_MAX
    with session_scope(sessions) as session:
        silent = sweeps.silent_deliveries(session, now, settings.heartbeat_timeout, retry_wait)
    taken = []
    for delivery in silent:
        with session_scope(sessions) as session:
            if not sweeps.take_back_silent(session, delivery):
                continue
        logger.warning("bake %s: %s was sent at %s and never taken; sending it again", delivery.bake_id, delivery.label, delivery.sent_at)
        report.resent.append(f"{delivery.bake_id}:{delivery.label}")
        taken.append(delivery)
    return taken


def dispatch_unsent(sessions: sessionmaker[Session], celery: Celery, settings: Settings, queued_before: dt.datetime,
                    report: SweepReport, also: list[sweeps.Delivery] = ()) -> None:
    """Send every unit queued before `queued_before` without a message (and `also`: units re-queued in
    this pass). Stops at the first failed send: the broker is away, and the next pass tries again."""
    with session_scope(sessions) as session:
        unsent = sweeps.unsent_deliveries(session, queued_before)
    seen = {(delivery.bake_id, delivery.stage, delivery.part) for delivery in unsent}
    unsent += [delivery for delivery in also if (delivery.bake_id, delivery.stage, delivery.part) not in seen]
    for delivery in unsent:
        try:
            send_and_mark(sessions, celery, settings, delivery)
        except Exception as error:  # the broker is unreachable or frozen
            logger.warning("sweeper: could not send %s of bake %s: %s", delivery.label, delivery.bake_id, error)
            report.unsent.extend(f"{item.bake_id}:{item.label}" for item in unsent[unsent.index(delivery):])
            return
        report.sent.append(f"{delivery.bake_id}:{delivery.label}")


def work_folder_expired(bakes: list[Bake], now: dt.datetime, settings: Settings) -> bool:
    """Whether the work folder shared by `bakes` (same input key; newest first) may go.

    Kept while any of them is queued or running. Otherwise by the newest: published, delete; cancelled,
    delete once its workers had a heartbeat timeout to notice and stop; failed or succeeded without
    publishing (it may still be published later, which needs the packed bundle), delete after
    CROWDBAKE_WORK_KEEP_SECONDS."""
    if any(bake.state in records.LIVE_BAKE_STATES for bake in bakes):
        return False
    newest = bakes[0]
    ended = records.to_utc(newest.finished_at) or records.to_utc(newest.updated_at) or now
    age = (now - ended).total_seconds()
    stages = {row.stage: row.state for row in newest.stages}
    if newest.state == "succeeded" and stages.get("publish") == "succeeded":
        return True
    if newest.state == "cancelled":
        return age > settings.heartbeat_timeout
    return age > settings.work_keep_seconds


def clean_work_folders(sessions: sessionmaker[Session], settings: Settings, now: dt.datetime, report: SweepReport) -> None:
    work_root = Path(settings.work_dir)
    if not work_root.is_dir():
        return
    for folder in sorted(work_root.iterdir()):
        if not folder.is_dir():
            continue
        with session_scope(sessions) as session:
            bakes = list(session.scalars(select(Bake).where(Bake.input_key == folder.name).order_by(Bake.created_at.desc())))
            if bakes:
                expired = work_folder_expired(bakes, now, settings)
            else:  # a folder no bake names (its bakes were deleted): by its age
                try:
                    expired = time.time() - folder.stat().st_mtime > settings.work_keep_seconds
                except OSError:
                    expired = False
        if expired:
            shutil.rmtree(folder, ignore_errors=True)
            report.removed_work.append(folder.name)


def clean_partial_publishes(sessions: sessionmaker[Session], settings: Settings, report: SweepReport) -> None:
    """Remove staging folders of publishes that no live bake owns (module docstring, 5.)."""
    if settings.store != "local":  # an object store stages under keys no reader lists (crowdbake.storage.s3_bundles)
        return
    for folder, name, version in staging_folders(Path(settings.bundles_dir)):
        try:
            quiet_s = time.time() - folder.stat().st_mtime
        except OSError:  # its publish just finished or gave up
            continue
        if quiet_s <= settings.heartbeat_timeout:
            continue
        with session_scope(sessions) as session:
            live = session.scalars(select(Bake.id).where(Bake.name == name, Bake.version == version,
                                                         Bake.state.in_(records.LIVE_BAKE_STATES)).limit(1)).first()
        if live is None:
            shutil.rmtree(folder, ignore_errors=True)
            logger.warning("sweeper: removed %s, left by a publish of %s/%s that did not finish", folder.name, name, version)
            report.removed_partial.append(f"{name}/{folder.name}")


def sweep_once(sessions: sessionmaker[Session], celery: Celery, settings: Settings, now: dt.datetime | None = None) -> SweepReport:
    """One pass of the sweeper (module docstring). `now` is for tests that age records."""
    now = now or utcnow()
    report = SweepReport()
    requeued = requeue_lost_workers(sessions, settings, now, report)
    requeued += take_back_silent(sessions, settings, now, report)
    dispatch_unsent(sessions, celery, settings, now - dt.timedelta(seconds=settings.dispatch_after), report, also=requeued)
    clean_work_folders(sessions, settings, now, report)
    clean_partial_publishes(sessions, settings, report)
    return report


class Sweeper:
    """`sweep_once` every CROWDBAKE_SWEEP_INTERVAL seconds in a daemon thread; `stop()` ends it."""

    def __init__(self, sessions: sessionmaker[Session], celery: Celery, settings: Settings):
        self.sessions, self.celery, self.settings = sessions, celery, settings
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "Sweeper":
        if self.settings.sweep_interval > 0 and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="crowdbake-sweeper", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stopped.set()

    def _run(self) -> None:
        while not self._stopped.wait(self.settings.sweep_interval):
            try:
                report = sweep_once(self.sessions, self.celery, self.settings)
            except Exception:  # a busy or unreachable database: the next pass tries again
                logger.exception("sweeper pass failed")
                continue
            if report.requeued or report.resent or report.failed or report.sent or report.removed_work or report.removed_partial:
                logger.info("sweeper: re-queued %s, sent again %s, failed %s, sent %s, removed %d work folder(s) and %d partial publish(es)",
                            report.requeued, report.resent, report.failed, report.sent, len(report.removed_work), len(report.removed_partial))


class Dispatcher:
    """Sends the messages of requests (a new bake, a retry, a publish) in a few threads of its own, so a
    request waits at most ENQUEUE_WAIT_S for the broker; what is not sent by then the thread sends
    when the broker answers, or the sweeper does."""

    def __init__(self, sessions: sessionmaker[Session], celery: Celery, settings: Settings, threads: int = SEND_THREADS):
        self.sessions, self.celery, self.settings = sessions, celery, settings
        self._pool = concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="crowdbake-send")

    def send(self, delivery: sweeps.Delivery, wait_s: float = ENQUEUE_WAIT_S) -> bool:
        """True when the message was sent within `wait_s` seconds."""
        future = self._pool.submit(send_and_mark, self.sessions, self.celery, self.settings, delivery)
        try:
            future.result(timeout=wait_s)
            return True
        except concurrent.futures.TimeoutError:
            future.add_done_callback(_log_late_failure(delivery))
            return False
        except Exception as error:  # the broker refused or is unreachable
            logger.warning("could not send %s of bake %s: %s; the sweeper sends it", delivery.label, delivery.bake_id, error)
            return False


def _log_late_failure(delivery: sweeps.Delivery) -> Callable[[concurrent.futures.Future], None]:
    def done(future: concurrent.futures.Future) -> None:
        if future.exception() is not None:
            logger.warning("could not send %s of bake %s: %s; the sweeper sends it", delivery.label, delivery.bake_id, future.exception())

    return done
