"""How a stage task of the service runs: it claims its unit in the database, beats while it runs, records
its outcome and queues what comes next, exactly once per delivery (crowdbake.jobs.tasks defines the
tasks; crowdbake.jobs.sweeper re-sends what a lost worker held).

Deliveries: a task first claims its stage (or part) in the database (records.claim_delivery), so of
two messages for one unit only one runs it: a duplicate (sent twice, a visibility timeout, a message
the sweeper re-sent) is dropped, and a late original that lost its unit records nothing. While a task
runs, a thread writes its heartbeat every CROWDBAKE_HEARTBEAT_INTERVAL seconds; the sweeper
(crowdbake.jobs.sweeper) re-queues a unit whose heartbeat stopped. The next stage is queued in the
same transaction that records a stage's success, and its message sent after the commit: if the
broker is away, the sweeper sends it later, so no bake is left waiting on a message never sent.

Errors: the stages' InputError and VersionConflict, and any other error that a rerun cannot fix,
fail the bake with a one-line reason; transient errors (a locked database, a full disk) are retried
with exponential backoff up to `task_max_retries`. Cancellation reaches running stages: the heartbeat
thread sees the bake's state every heartbeat, the progress callback then raises BakeCancelled, and a
stage that does not report progress within CANCEL_GRACE_BEATS heartbeats has its pool process ended
(the message comes back, finds the bake cancelled and is dropped).
"""
from __future__ import annotations

import datetime as dt
import json
import logging
import os
import random
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from celery import group, signals
from celery.exceptions import Reject
from kombu.exceptions import OperationalError as KombuOperationalError
from sqlalchemy.orm import Session, sessionmaker

from crowdbake.jobs.celery_app import TASK_NAMES, app
from crowdbake.jobs.failures import describe_error, is_transient
from crowdbake.settings import Settings, get_settings
from crowdbake.stages import STAGES, plan
from crowdbake.storage import records
from crowdbake.storage.blobs import BlobStore
from crowdbake.storage.bundle_store import BundleStore
from crowdbake.storage.db import fork_guarded_scope, make_engine, make_sessionmaker, session_scope
from crowdbake.storage.exports import ExportStore
from crowdbake.storage.models import Bake, utcnow
from crowdbake.storage.store import open_store

logger = logging.getLogger(__name__)

# Lines of a stage's own log kept in the bake's log (a chatty stage must not fill the database).
MAX_CAPTURED_LINES = 200

TASK_OPTIONS = dict(bind=True, acks_late=True, reject_on_worker_lost=True, ignore_result=True)
# How long a worker keeps trying to hand a finished stage to the next one while the broker is away
# (a Redis restart or failover): about 15 s (0.5 + 1.5 + ... + 5 s, 6 tries). Past that the next
# stage stays queued without a message and the sweeper sends it once the broker is back.
BROKER_PUBLISH_RETRY = {"max_retries": 6, "interval_start": 0.5, "interval_step": 1.0, "interval_max": 5.0}
# Heartbeats a stopped stage (cancelled, or its unit handed to another delivery) gets to notice and
# return before its pool process is ended: a stage in a long loop without progress reports (a huge
# mesh in the cycle search) would otherwise run to its end, holding its memory.
CANCEL_GRACE_BEATS = 3


class BakeStopped(Exception):
    """The bake was cancelled, failed elsewhere, or a newer attempt replaced this one."""


class BakeCancelled(BakeStopped):
    """Raised by the progress callback in a running stage once its bake was cancelled (or its unit was
    handed to another delivery)."""


@dataclass
class WorkerServices:
    settings: Settings
    sessions: sessionmaker[Session]
    blobs: BlobStore
    bundles: BundleStore
    exports: ExportStore

    @property
    def exchanges_work(self) -> bool:
        """Whether stage outputs travel through the blob store (private data folders, see the module
        docstring); with local folders every worker shares one work folder instead."""
        return self.settings.store == "s3"


_services: WorkerServices | None = None
_services_pid: int | None = None


def services() -> WorkerServices:
    """This process's database sessions and blob store, created after the prefork fork (engines and
    their connections must not be shared between processes)."""
    global _services, _services_pid
    if _services is None or _services_pid != os.getpid():
        if _services is not None:
            # Inherited from the worker's main process across the fork (it marks received messages):
            # drop its pooled connections without closing them, which would close the parent's too.
            _services.sessions.kw["bind"].dispose(close=False)
        settings = get_settings()
        stores = open_store(settings)
        _services = WorkerServices(settings, make_sessionmaker(make_engine(settings.database_url)), stores.blobs, stores.bundles, stores.exports)
        _services_pid = os.getpid()
    return _services


def work_dir(settings: Settings, input_key: str) -> Path:
    return settings.work_dir / input_key


def _jsonable(value: Any) -> Any:
    if isinstance(value, Path):
        return {"path": str(value)}
    return json.loads(json.dumps(value, default=str)) if value is not None else None


# ------------------------------------------------------------------------------------ stage runner


class _LogCapture(logging.Handler):
    """Collects the crowdbake loggers' records while a stage runs, for the bake's log."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.lines: list[tuple[str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.lines) < MAX_CAPTURED_LINES and not record.name.startswith("crowdbake.jobs"):
            self.lines.append((record.levelname, f"{record.name}: {record.getMessage()}"))


@dataclass
class StageContext:
    """What a stage body gets: the bake, its work folder and a progress callback."""

    services: WorkerServices
    bake_id: str
    attempt: int
    stage: str
    work: Path
    owner: str = ""
    part: str | None = None
    stop_reason: str | None = None
    _last_report: float = 0.0

    def session(self):
        return session_scope(self.services.sessions)

    def check_live(self, session: Session) -> Bake:
        bake = session.get(Bake, self.bake_id)
        if bake is None or bake.attempt != self.attempt or records.is_final(bake):
            raise BakeCancelled(f"bake {self.bake_id} attempt {self.attempt} is no longer running")
        return bake

    def progress(self, _stage: str, done: int, total: int) -> None:
        """The stages' progress callback: raises BakeCancelled once the heartbeat saw the bake stop,
        records done/total (at most every progress_interval seconds, and always at the end) and checks
        the bake's state then too."""
        if self.stop_reason is not None:
            raise BakeCancelled(self.stop_reason)
        now = time.monotonic()
        if done < total and now - self._last_report < self.services.settings.progress_interval:
            return
        self._last_report = now
        with self.session() as session:
            self.check_live(session)
            records.set_progress(session, self.bake_id, self.stage, done, total)


def _in_pool_process() -> bool:
    """True in a Celery prefork pool process, which its worker replaces when it exits."""
    from billiard.process import current_process

    return current_process().name.startswith(("ForkPoolWorker", "PoolWorker"))


@dataclass
class Heartbeat:
    """A thread that writes the running delivery's heartbeat every `interval` seconds, and stops the
    stage when the bake stops: it sets `ctx.stop_reason` (the next progress report raises), and after
    CANCEL_GRACE_BEATS more beats without the stage returning it ends this pool process."""

    ctx: StageContext
    interval: float
    _stopped: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def __enter__(self) -> "Heartbeat":
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{self.ctx.part or self.ctx.stage}", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *_exc) -> None:
        self._stopped.set()
        if self._thread is not None:
            self._thread.join(timeout=self.interval + 5)

    def _run(self) -> None:
        ctx, beats_since_stop = self.ctx, 0
        while not self._stopped.wait(self.interval):
            if ctx.stop_reason is None:
                try:
                    with ctx.session() as session:
                        alive = records.heartbeat(session, ctx.bake_id, ctx.attempt, ctx.stage, ctx.part, ctx.owner)
                except Exception as error:  # a busy database: the next beat tries again
                    logger.warning("heartbeat of bake %s %s failed: %s", ctx.bake_id, ctx.part or ctx.stage, error)
                    continue
                if not alive:
                    ctx.stop_reason = f"bake {ctx.bake_id} attempt {ctx.attempt}: {ctx.part or ctx.stage} stopped (cancelled, failed or handed to another worker)"
                    logger.info("%s", ctx.stop_reason)
                continue
            beats_since_stop += 1
            if beats_since_stop >= CANCEL_GRACE_BEATS and _in_pool_process():
                logger.warning("%s, and the stage did not return within %d heartbeats: ending pool process %d",
                               ctx.stop_reason, CANCEL_GRACE_BEATS, os.getpid())
                logging.shutdown()
                os._exit(1)


def run_stage(task, bake_id: str, attempt: int, stage: str, body: Callable[[StageContext], Any],
              after: Callable[[StageContext, Any, float], None], log_start: bool = True, part: str | None = None) -> None:
    """Run `body` as stage `stage` of the bake (or its fan-out part `part`), then `after(ctx, result,
    seconds)`, recording state, timings, captured log lines and errors; retries transient errors with
    backoff, and gives up on a task whose worker keeps dying (a poison job: acks_late with
    reject_on_worker_lost would otherwise hand it out forever).

    First the delivery claims its unit (records.claim_delivery): a duplicate is dropped, and a message
    handed out again because the process running it died (this host), or whose unit's heartbeat
    stopped, takes over and counts one retry, for every broker (the filesystem one sets no
    `redelivered` flag)."""
    svc = services()
    settings = svc.settings
    label = part or stage
    owner = records.delivery_owner(task.request.id)
    stale_before = utcnow() - dt.timedelta(seconds=settings.heartbeat_timeout)
    with session_scope(svc.sessions) as session:
        claim = records.claim_delivery(session, bake_id, attempt, stage, part, owner, stale_before)
        if not claim.won:
            logger.info("dropping a %s task: %s", label, claim.reason)
            return
        bake = session.get(Bake, bake_id)
        if claim.lost_owner is not None:
            records.append_log(session, bake_id, "WARNING", stage,
                               f"{label}: delivered again in attempt {attempt}, retry {claim.retries} of {settings.task_max_retries}: "
                               f"the worker running it ({claim.lost_owner}) was lost (killed, out of memory or crashed)")
            if claim.retries > settings.task_max_retries:
                logger.error("bake %s: %s lost its worker %d times; giving up", bake_id, label, claim.retries)
                records.fail_bake(session, bake, stage, {
                    "type": "worker-lost", "title": f"the {stage} stage keeps losing its worker",
                    "detail": f"{label} was handed out again {claim.retries} times, more than {settings.task_max_retries} "
                              "(CROWDBAKE_TASK_MAX_RETRIES), because the worker running it was lost each time "
                              "(killed, out of memory or crashed); retry the bake, with fewer or smaller views if memory is the cause",
                })
                return
        if log_start:
            records.append_log(session, bake_id, "INFO", stage, f"{stage} started (attempt {attempt}, delivery {task.request.retries + 1})")
        key = bake.input_key
    ctx = StageContext(svc, bake_id, attempt, stage, work_dir(svc.settings, key), owner=owner, part=part)
    ctx.work.mkdir(parents=True, exist_ok=True)

    capture = _LogCapture()
    package_logger = logging.getLogger("crowdbake")
    previous_level = package_logger.level
    package_logger.addHandler(capture)
    if package_logger.getEffectiveLevel() > logging.INFO:
        package_logger.setLevel(logging.INFO)
    start = time.perf_counter()
    error: BaseException | None = None
    try:
        try:
            with Heartbeat(ctx, settings.heartbeat_interval):
                result = body(ctx)
        finally:
            package_logger.removeHandler(capture)
            package_logger.setLevel(previous_level)
            seconds = time.perf_counter() - start
            if capture.lines:
                with session_scope(svc.sessions) as session:
                    for level, message in capture.lines:
                        records.append_log(session, bake_id, level, stage, message)
        # Recording the outcome and enqueueing the next stage fail like the stage itself: a retry
        # reruns the (idempotent, by then cached) stage and tries again.
        after(ctx, result, seconds)
    except BakeStopped as stopped:
        logger.info("%s", stopped)
        with session_scope(svc.sessions) as session:
            records.release_delivery(session, bake_id, stage, part, owner)
        return
    except Exception as caught:  # every failure is recorded; nothing escapes unrecorded
        error = caught
    if error is None:
        return

    retries = task.request.retries
    # A broker error here means BROKER_PUBLISH_RETRY already waited for it in vain; a retry would need
    # that same broker, so the bake fails with the reason instead (and can be retried from the API).
    if is_transient(error) and not isinstance(error, KombuOperationalError) and retries < svc.settings.task_max_retries:
        countdown = min(svc.settings.task_retry_backoff_max, 2.0**retries) * (0.5 + random.random())
        with session_scope(svc.sessions) as session:
            if records.still_owner(session, bake_id, attempt, stage, part, owner) is None:
                return  # cancelled meanwhile, or the unit belongs to another delivery now
            records.release_delivery(session, bake_id, stage, part, owner)
            row = records.stage_row(session, bake_id, stage)
            row.state, row.retries = "retrying", row.retries + 1
            records.append_log(session, bake_id, "WARNING", stage, f"transient error, retry {retries + 1} in {countdown:.1f} s: {type(error).__name__}: {error}")
        try:
            raise task.retry(exc=error, countdown=countdown, max_retries=svc.settings.task_max_retries, retry=True, retry_policy=BROKER_PUBLISH_RETRY)
        except Reject as rejected:  # Celery could not queue the retry (the broker is unreachable)
            error = rejected.reason if isinstance(rejected.reason, BaseException) else error
    logger.error("bake %s: %s failed", bake_id, stage, exc_info=error)
    with session_scope(svc.sessions) as session:
        bake = records.still_owner(session, bake_id, attempt, stage, part, owner)
        if bake is not None:
            records.fail_bake(session, bake, stage, describe_error(error, stage))


def finish(ctx: StageContext, session: Session, result: Any, seconds: float) -> Bake:
    """Record the stage's success, if this delivery still owns it (else BakeStopped: a late original
    whose stage was re-queued records nothing; its replacement does)."""
    bake = records.still_owner(session, ctx.bake_id, ctx.attempt, ctx.stage, None, ctx.owner)
    if bake is None:
        raise BakeStopped(f"bake {ctx.bake_id} attempt {ctx.attempt}: {ctx.stage} is no longer this delivery's")
    records.finish_stage(session, ctx.bake_id, ctx.stage, seconds, _jsonable(result))
    records.append_log(session, ctx.bake_id, "INFO", ctx.stage, f"{ctx.stage} finished in {seconds:.2f} s")
    return bake


def send_queued(stage: str, bake_id: str, attempt: int, *parts: str) -> None:
    """Send the message(s) of a stage queued by a committed transaction, then mark them sent. When the
    broker stays away past BROKER_PUBLISH_RETRY the stage stays queued without a message, and the
    sweeper sends it later: the bake waits instead of failing, and nothing is lost."""
    queue = services().settings.queue
    try:
        if parts:
            task = TASK_NAMES[plan.fan_out_of(stage).name]
            group(app.signature(task, args=[bake_id, attempt, part], queue=queue, immutable=True) for part in parts) \
                .apply_async(retry=True, retry_policy=BROKER_PUBLISH_RETRY)
        else:
            app.send_task(TASK_NAMES[stage], args=[bake_id, attempt], queue=queue, retry=True, retry_policy=BROKER_PUBLISH_RETRY)
    except KombuOperationalError as error:
        logger.warning("bake %s: could not send %s (%s); the sweeper sends it once the broker answers", bake_id, stage, error)
        with session_scope(services().sessions) as session:
            records.append_log(session, bake_id, "WARNING", stage, f"the job queue did not take {stage} ({type(error).__name__}); "
                               "it stays queued and is sent once the broker answers")
        return
    with session_scope(services().sessions) as session:
        records.mark_sent(session, bake_id, attempt, stage, parts)


# ------------------------------------------------------------------- messages held by a worker


# Which unit a task message is for: (stage, part) from the task name and its args.
_STAGE_OF_TASK = {TASK_NAMES[plan.fan_out_of(stage).name if plan.runs_in_parallel(stage) else stage]: stage for stage in STAGES}
_received_beat: threading.Thread | None = None


@signals.task_received.connect
def _mark_received(sender=None, request=None, **_kwargs) -> None:
    """In the worker's main process, as a message arrives (records.mark_received): a worker lost while
    it holds messages no pool process has started yet leaves marks that stop beating."""
    stage = _STAGE_OF_TASK.get(getattr(request, "task_name", None))
    args = list(getattr(request, "args", None) or [])
    if stage is None or len(args) < 2:
        return
    part = args[2] if plan.runs_in_parallel(stage) and len(args) > 2 else None
    try:
        with fork_guarded_scope(services().sessions) as session:
            records.mark_received(session, args[0], int(args[1]), stage, part, records.delivery_owner(request.id))
    except Exception as error:  # a busy database: the task's own claim still works without the mark
        logger.warning("could not mark %s of bake %s as received: %s", part or stage, args[0], error)
    _start_received_beat()


def _start_received_beat() -> None:
    global _received_beat
    if _received_beat is not None and _received_beat.is_alive():
        return

    def beat() -> None:
        while True:
            time.sleep(services().settings.heartbeat_interval)
            try:
                owners = held_owners(records.delivery_owner)
                with fork_guarded_scope(services().sessions) as session:  # this thread's beat vs the pool's forks
                    records.beat_received(session, owners)
            except Exception as error:
                logger.warning("heartbeat of received messages failed: %s", error)

    _received_beat = threading.Thread(target=beat, name="received-heartbeat", daemon=True)
    _received_beat.start()


def held_owners(owner_of: Callable[[str], str]) -> list[str]:
    """The receipt marks (`owner_of(task id)`) of the messages this worker's main process holds now:
    received and waiting for a pool process, or just handed to one. Celery forgets the waiting ones
    when its broker connection drops (the broker redelivers them), so their marks stop beating and
    the sweeper re-queues their units (records.beat_received)."""
    from celery.worker import state

    for _ in range(5):  # the consumer thread may change the sets while this thread reads them
        try:
            held = list(state.reserved_requests) + list(state.active_requests)
            break
        except RuntimeError:
            time.sleep(0.01)
    else:
        return []
    return sorted({owner_of(request.id) for request in held if getattr(request, "id", None)})
