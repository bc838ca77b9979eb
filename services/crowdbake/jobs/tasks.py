"""The bake's Celery tasks: one thin task per stage of crowdbake.stages.

Each task takes the bake's id and attempt (and, for an impostor task, its part id), loads what it needs
from the database, calls the stage function (crowdbake.stages.<stage>) on the bake's work folder, records the outcome,
and enqueues what comes next:

    validate -> cycle (+ impostor plan) -> poses | impostor_views x N (all in parallel) -> pack -> publish

(The impostor tasks need only the impostor plan, which the cycle task draws from the cycle's output,
crowdbake.stages.impostors.stage_impostor_plan, so they run beside the poses stage; pack waits for both.)

The work folder is named by the bake's input key (hash of inputs, parameters and code version), and the
stage functions are idempotent, so a redelivered or retried task finds its outputs and returns at once.
With an object store (CROWDBAKE_STORE=s3) every machine has its own data folder: each stage then
stores what it wrote as blobs (crowdbake.storage.work_outputs.push, the listing's digest goes into its
stage row, or into its part row for an impostor task) and the next stage, on whichever machine, first
fetches what it reads (`pull`), so a bake fans out over machines that share only the database, the
broker and the bucket.
The fan-in before pack is a barrier in the database (crowdbake.storage.records.complete_part/claim_fan_in).

Errors: the stages' InputError and VersionConflict, and any other error that a rerun cannot fix,
fail the bake with a one-line reason; transient errors (a locked database, a full disk) are retried
with exponential backoff up to `task_max_retries`. Cancellation is cooperative: the bake's state in the
database is checked before each stage and at every progress report.
"""
from __future__ import annotations

import errno
import importlib
import json
import logging
import os
import random
import shutil
import time
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Callable

from celery import group
from celery.exceptions import Reject
from kombu.exceptions import OperationalError as KombuOperationalError
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from crowdbake.errors import InputError, VersionConflict
from crowdbake.jobs.celery_app import TASK_NAMES, app
from crowdbake.params import BakeParams
from crowdbake.settings import Settings, get_settings
from crowdbake.storage import records, work_outputs
from crowdbake.storage.blobs import BlobStore
from crowdbake.storage.bundle_store import BundleStore
from crowdbake.storage.bundles import BundleConflict, register_bundle
from crowdbake.storage.db import make_engine, make_sessionmaker, session_scope
from crowdbake.storage.models import Asset, Bake, BakePart, BakeStage
from crowdbake.storage.store import open_store

logger = logging.getLogger(__name__)

# OS errors a later attempt can get past; others (a missing file, a permission) would fail again.
TRANSIENT_ERRNOS = frozenset({errno.ENOSPC, errno.EIO, errno.EAGAIN, errno.EBUSY, errno.ETIMEDOUT, errno.EMFILE, errno.ENFILE, errno.EINTR})
# Lines of a stage's own log kept in the bake's log (a chatty stage must not fill the database).
MAX_CAPTURED_LINES = 200

TASK_OPTIONS = dict(bind=True, acks_late=True, reject_on_worker_lost=True, ignore_result=True)
# How long a worker keeps trying to hand a finished stage to the next one while the broker is away
# (a Redis restart or failover): about two minutes (0.5 + 1.5 + ... + 5 s, 30 tries). Kombu's default
# gives up after about one second, which dropped the bake's next stage on any broker restart.
BROKER_PUBLISH_RETRY = {"max_retries": 30, "interval_start": 0.5, "interval_step": 1.0, "interval_max": 5.0}


# The poses stage runs beside the impostor tasks: pack waits for this part as for theirs.
POSES_PART = "poses"


class BakeStopped(Exception):
    """The bake was cancelled, failed elsewhere, or a newer attempt replaced this one."""


@dataclass
class WorkerServices:
    settings: Settings
    sessions: sessionmaker[Session]
    blobs: BlobStore
    bundles: BundleStore

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
        settings = get_settings()
        stores = open_store(settings)
        _services = WorkerServices(settings, make_sessionmaker(make_engine(settings.database_url)), stores.blobs, stores.bundles)
        _services_pid = os.getpid()
    return _services


def work_dir(settings: Settings, input_key: str) -> Path:
    return settings.work_dir / input_key


# What each stage writes in the work folder (crowdbake.stages.workdir), pushed to the blob store when
# work travels between machines, and the earlier stages whose outputs it reads. An impostor task writes
# impostor/parts/<id>.npz and .json (`_part_outputs`); pack reads every part.
# The cycle task also writes the impostor plan (impostor/record.json, stage.json, scene.npz), which is all
# an impostor task reads, so impostor tasks run beside the poses stage.
STAGE_OUTPUTS = {"validate": ("validate", "inputs"), "cycle": ("cycle", "impostor/record.json", "impostor/stage.json", "impostor/scene.npz"),
                 "poses": ("poses",), "pack": ("pack", "bundle")}
STAGE_READS = {"cycle": ("validate",), "poses": ("validate", "cycle"), "impostors": ("cycle",),
               "pack": ("validate", "cycle", "poses"), "publish": ("pack",)}


def _part_outputs(part_id: str) -> tuple[str, ...]:
    task_id = part_id.removeprefix(records.IMPOSTOR_PART_PREFIX)
    return (f"impostor/parts/{task_id}.npz", f"impostor/parts/{task_id}.json")


def _stage(name: str):
    """A stage module (crowdbake.stages.<name>), imported when a task first runs it: the renderer and the
    numeric stack load in the worker's pool processes, not in every process that imports this module."""
    return importlib.import_module(f"crowdbake.stages.{name}")


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
    _last_report: float = 0.0

    def session(self):
        return session_scope(self.services.sessions)

    def check_live(self, session: Session) -> Bake:
        bake = session.get(Bake, self.bake_id)
        if bake is None or bake.attempt != self.attempt or records.is_final(bake):
            raise BakeStopped(f"bake {self.bake_id} attempt {self.attempt} is no longer running")
        return bake

    def progress(self, _stage: str, done: int, total: int) -> None:
        """The stages' progress callback: records done/total (at most every progress_interval
        seconds, and always at the end) and stops the stage if the bake was cancelled."""
        now = time.monotonic()
        if done < total and now - self._last_report < self.services.settings.progress_interval:
            return
        self._last_report = now
        with self.session() as session:
            self.check_live(session)
            records.set_progress(session, self.bake_id, self.stage, done, total)


def push_outputs(ctx: StageContext, roots: tuple[str, ...]) -> str | None:
    """Store what the stage wrote under `roots` of its work folder; the listing's digest, or None when
    work does not travel between machines."""
    if not ctx.services.exchanges_work:
        return None
    return work_outputs.push(ctx.services.blobs, ctx.work, roots)


def pull_inputs(ctx: StageContext, stage: str) -> None:
    """Fetch into this machine's work folder what `stage` reads from the earlier stages (STAGE_READS),
    and for pack every impostor part, from the listings their rows name."""
    if not ctx.services.exchanges_work:
        return
    with ctx.session() as session:
        ctx.check_live(session)
        wanted = STAGE_READS.get(stage, ())
        rows = session.query(BakeStage).filter(BakeStage.bake_id == ctx.bake_id, BakeStage.stage.in_(wanted)).all()
        listings = {row.stage: (row.result or {}).get("outputs") for row in rows}
        missing = [name for name in wanted if not listings.get(name)]
        digests = [listings[name] for name in wanted]
        if stage == "pack":
            parts = session.query(BakePart).filter(BakePart.bake_id == ctx.bake_id, BakePart.stage == "impostors").all()
            missing += [part.part for part in parts if not part.spec.get("outputs")]
            digests += [part.spec["outputs"] for part in sorted(parts, key=lambda part: part.part) if part.spec.get("outputs")]
        if missing:  # a stage only starts after the ones it reads have recorded their outputs
            raise RuntimeError(f"the outputs of {', '.join(missing)} are not recorded, so {stage} cannot run on this machine")
    fetched = sum(work_outputs.pull(ctx.services.blobs, ctx.work, digest) for digest in digests)
    if fetched:
        logger.info("bake %s: fetched %d files of earlier stages for %s", ctx.bake_id, fetched, stage)


def _is_transient(error: BaseException) -> bool:
    if isinstance(error, (OperationalError, KombuOperationalError)):  # database busy, broker unreachable
        return True
    return isinstance(error, OSError) and error.errno in TRANSIENT_ERRNOS


def describe_error(error: BaseException, stage: str) -> dict[str, Any]:
    """A bake's error record: a problem type, a title, a one-line detail and the input field if known."""
    detail = " ".join(str(error).split()) or type(error).__name__
    if isinstance(error, OSError) and error.errno is not None and error.filename is not None:
        # The file name is a path in the server's work folder: the log has it, the API user gets the reason.
        detail = f"[Errno {error.errno}] {error.strerror}"
    if isinstance(error, InputError):
        record = {"type": "invalid-input", "title": "the inputs cannot be baked", "detail": detail}
        field = getattr(error, "field", None)
        if field:
            record["field"] = str(field)
        return record
    if isinstance(error, KombuOperationalError):
        return {"type": "not-ready", "title": "the job queue is unreachable",
                "detail": f"the {stage} stage could not queue what comes next: {detail}; retry the bake once the broker is back"}
    if isinstance(error, (BundleConflict, VersionConflict)):
        return {"type": "version-conflict", "title": "this version is already published with other bytes", "detail": detail}
    return {"type": "stage-failed", "title": f"the {stage} stage failed", "detail": f"{type(error).__name__}: {detail}"}


def _redelivered(task) -> bool:
    """True when the broker hands this message out again (Redis sets the flag when it restores an
    unacknowledged message: the worker running it was lost, or it was restored at a reconnection)."""
    return bool((task.request.delivery_info or {}).get("redelivered"))


def run_stage(task, bake_id: str, attempt: int, stage: str, body: Callable[[StageContext], Any],
              after: Callable[[StageContext, Any, float], None], log_start: bool = True, part: str | None = None) -> None:
    """Run `body` as stage `stage` of the bake (or its fan-out part `part`), then `after(ctx, result,
    seconds)`, recording state, timings, captured log lines and errors; retries transient errors with
    backoff, and gives up on a task whose worker keeps dying (a poison job: acks_late with
    reject_on_worker_lost would otherwise hand it out forever)."""
    svc = services()
    with session_scope(svc.sessions) as session:
        bake = session.get(Bake, bake_id)
        if bake is None:
            logger.warning("bake %s does not exist; dropping its %s task", bake_id, stage)
            return
        if bake.attempt != attempt or records.is_final(bake):
            logger.info("bake %s attempt %s is %s; dropping its %s task", bake_id, attempt, bake.state, stage)
            return
        if _redelivered(task):
            label = part or stage
            redeliveries = records.record_redelivery(session, bake_id, attempt, stage, label)
            records.stage_row(session, bake_id, stage).retries += 1
            if redeliveries > svc.settings.task_max_retries:
                logger.error("bake %s: %s lost its worker %d times; giving up", bake_id, label, redeliveries)
                records.fail_bake(session, bake, stage, {
                    "type": "worker-lost", "title": f"the {stage} stage keeps losing its worker",
                    "detail": f"{label} was handed out again {redeliveries} times, more than {svc.settings.task_max_retries} "
                              "(CROWDBAKE_TASK_MAX_RETRIES), because the worker running it was lost each time "
                              "(killed, out of memory or crashed); retry the bake, with fewer or smaller views if memory is the cause",
                })
                return
        records.mark_running(session, bake, stage)
        if log_start:
            records.append_log(session, bake_id, "INFO", stage, f"{stage} started (attempt {attempt}, delivery {task.request.retries + 1})")
        key = bake.input_key
    ctx = StageContext(svc, bake_id, attempt, stage, work_dir(svc.settings, key))
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
        return
    except Exception as caught:  # every failure is recorded; nothing escapes unrecorded
        error = caught
    if error is None:
        return

    retries = task.request.retries
    # A broker error here means BROKER_PUBLISH_RETRY already waited for it in vain; a retry would need
    # that same broker, so the bake fails with the reason instead (and can be retried from the API).
    if _is_transient(error) and not isinstance(error, KombuOperationalError) and retries < svc.settings.task_max_retries:
        countdown = min(svc.settings.task_retry_backoff_max, 2.0**retries) * (0.5 + random.random())
        with session_scope(svc.sessions) as session:
            row = records.stage_row(session, bake_id, stage)
            row.state, row.retries = "retrying", row.retries + 1
            records.append_log(session, bake_id, "WARNING", stage, f"transient error, retry {retries + 1} in {countdown:.1f} s: {type(error).__name__}: {error}")
        try:
            raise task.retry(exc=error, countdown=countdown, max_retries=svc.settings.task_max_retries, retry=True, retry_policy=BROKER_PUBLISH_RETRY)
        except Reject as rejected:  # Celery could not queue the retry (the broker is unreachable)
            error = rejected.reason if isinstance(rejected.reason, BaseException) else error
    logger.error("bake %s: %s failed", bake_id, stage, exc_info=error)
    with session_scope(svc.sessions) as session:
        bake = session.get(Bake, bake_id)
        if bake is not None and bake.attempt == attempt and not records.is_final(bake):
            records.fail_bake(session, bake, stage, describe_error(error, stage))


def _finish(ctx: StageContext, session: Session, result: Any, seconds: float) -> Bake:
    bake = ctx.check_live(session)
    records.finish_stage(session, ctx.bake_id, ctx.stage, seconds, _jsonable(result))
    records.append_log(session, ctx.bake_id, "INFO", ctx.stage, f"{ctx.stage} finished in {seconds:.2f} s")
    return bake


def _send(stage: str, bake_id: str, attempt: int, *extra: Any) -> None:
    app.send_task(TASK_NAMES[stage], args=[bake_id, attempt, *extra], queue=services().settings.queue,
                  retry=True, retry_policy=BROKER_PUBLISH_RETRY)


# ------------------------------------------------------------------------------------------ stages


def _materialize_inputs(ctx: StageContext, bake: Bake, session: Session):
    """Link the bake's input blobs into work/sources and build the stages' BakeInputs.

    Not work/inputs: stage_validate copies its inputs there and clears that folder first. The manifest's
    `created` is the time the newest input was uploaded (`inputs_created`): a property of the inputs
    that every machine reads alike from the database (a file's modification time would be the time a
    machine downloaded it), so every attempt of a bake, wherever it runs, produces the same bytes. A `created` given with the
    bake request (`bake.inputs["created"]`) wins over both."""
    blobs = ctx.services.blobs
    inputs_dir = ctx.work / "sources"
    if inputs_dir.exists():
        shutil.rmtree(inputs_dir)
    character = session.get(Asset, bake.inputs["character"])
    cloth = session.get(Asset, bake.inputs["cloth"])
    if character is None or cloth is None:
        raise InputError("an input asset no longer exists", "character" if character is None else "cloth")
    character_path = blobs.materialize(character.files["file"]["sha256"], inputs_dir / f"character.{character.info.get('format', 'glb')}")
    # The cache keeps its format's extension (.pc2, .mdd, .abc): the validate stage reads it by extension.
    cache_suffix = PurePosixPath(cloth.files["cache"].get("filename") or "cloth.pc2").suffix.lower() or ".pc2"
    cloth_path = blobs.materialize(cloth.files["cache"]["sha256"], inputs_dir / f"cloth{cache_suffix}")
    mesh_path = blobs.materialize(cloth.files["mesh"]["sha256"], inputs_dir / "cloth.obj") if "mesh" in cloth.files else None
    textures_dir = None
    assets = [character, cloth]
    if bake.inputs.get("textures"):
        textures_dir = inputs_dir / "textures"
        for name, asset_id in sorted(bake.inputs["textures"].items()):
            texture = session.get(Asset, asset_id)
            if texture is None:
                raise InputError(f"texture {name} no longer exists", f"textures.{name}")
            blobs.materialize(texture.files["file"]["sha256"], textures_dir / name)
            assets.append(texture)
    return _stage("validate").BakeInputs(
        character=character_path, cloth=cloth_path, cloth_mesh=mesh_path, textures=textures_dir, cycle=None,
        name=bake.name, version=bake.version, params=BakeParams.from_dict(bake.params),
        created=bake.inputs.get("created") or inputs_created(assets),
    )


def inputs_created(assets: list[Asset]) -> str:
    """RFC 3339 UTC time (whole seconds) the newest of `assets` was uploaded: the bundle's `created`."""
    newest = max(records.to_utc(asset.created_at) for asset in assets)
    return newest.strftime("%Y-%m-%dT%H:%M:%SZ")


@app.task(name=TASK_NAMES["validate"], **TASK_OPTIONS)
def validate(self, bake_id: str, attempt: int) -> None:
    def body(ctx: StageContext):
        with ctx.session() as session:
            bake = ctx.check_live(session)
            inputs = _materialize_inputs(ctx, bake, session)
        result = _stage("validate").stage_validate(inputs, ctx.work).to_json()
        return dict(result, outputs=push_outputs(ctx, STAGE_OUTPUTS["validate"]))

    def after(ctx: StageContext, result, seconds: float) -> None:
        with ctx.session() as session:
            _finish(ctx, session, result, seconds)
        _send("cycle", ctx.bake_id, ctx.attempt)

    run_stage(self, bake_id, attempt, "validate", body, after)


@app.task(name=TASK_NAMES["cycle"], **TASK_OPTIONS)
def cycle(self, bake_id: str, attempt: int) -> None:
    def body(ctx: StageContext):
        pull_inputs(ctx, "cycle")
        result = _stage("cycle").stage_cycle(ctx.work, progress=ctx.progress).to_json()
        impostors = _stage("impostors")
        impostors.stage_impostor_plan(ctx.work)
        specs = [task.to_json() for task in impostors.impostor_tasks(ctx.work)]
        return dict(result, outputs=push_outputs(ctx, STAGE_OUTPUTS["cycle"])), specs

    def after(ctx: StageContext, outcome, seconds: float) -> None:
        result, impostor_specs = outcome
        with ctx.session() as session:
            _finish(ctx, session, result, seconds)
            part_ids = records.record_fan_out(session, ctx.bake_id, impostor_specs, stages=(POSES_PART,))
            records.append_log(session, ctx.bake_id, "INFO", "impostors", f"fanning out {len(part_ids)} impostor-view tasks beside the poses stage")
        _send("poses", ctx.bake_id, ctx.attempt)
        if part_ids:
            queue = services().settings.queue
            group(
                app.signature(TASK_NAMES["impostor_views"], args=[ctx.bake_id, ctx.attempt, part_id], queue=queue, immutable=True)
                for part_id in part_ids
            ).apply_async(retry=True, retry_policy=BROKER_PUBLISH_RETRY)

    run_stage(self, bake_id, attempt, "cycle", body, after)


def _maybe_enqueue_pack(ctx: StageContext, parts_left: int) -> None:
    """The last part to finish enqueues pack. The claim commits only once the message is sent, so a
    failed send leaves the barrier open for the retry instead of losing the pack stage."""
    if parts_left:
        return
    with ctx.session() as session:
        ctx.check_live(session)
        if records.claim_fan_in(session, ctx.bake_id, ctx.attempt):
            _send("pack", ctx.bake_id, ctx.attempt)


@app.task(name=TASK_NAMES["poses"], **TASK_OPTIONS)
def poses(self, bake_id: str, attempt: int) -> None:
    def body(ctx: StageContext):
        pull_inputs(ctx, "poses")
        result = _stage("poses").stage_poses(ctx.work, progress=ctx.progress)
        return dict(result.to_json(), outputs=push_outputs(ctx, STAGE_OUTPUTS["poses"]))

    def after(ctx: StageContext, result, seconds: float) -> None:
        with ctx.session() as session:
            parts_left = records.complete_part(session, ctx.bake_id, POSES_PART)  # first: it serialises the fan-in
            _finish(ctx, session, result, seconds)
        _maybe_enqueue_pack(ctx, parts_left)

    run_stage(self, bake_id, attempt, "poses", body, after)


@app.task(name=TASK_NAMES["impostor_views"], **TASK_OPTIONS)
def impostor_views(self, bake_id: str, attempt: int, part_id: str) -> None:
    def body(ctx: StageContext):
        with ctx.session() as session:
            part = session.get(BakePart, (bake_id, part_id))
            if part is None:
                raise BakeStopped(f"bake {bake_id} has no part {part_id} (superseded)")
            spec = {key: value for key, value in part.spec.items() if key != "outputs"}
        pull_inputs(ctx, "impostors")
        path = _stage("impostors").stage_impostor_views(ctx.work, spec)
        return path, push_outputs(ctx, _part_outputs(part_id))

    def after(ctx: StageContext, outcome, seconds: float) -> None:
        _path, outputs = outcome
        with ctx.session() as session:
            if outputs is not None:  # what pack fetches from this part (see pull_inputs)
                part = session.get(BakePart, (ctx.bake_id, part_id))
                if part is not None:
                    part.spec = dict(part.spec, outputs=outputs)
            parts_left = records.complete_part(session, ctx.bake_id, part_id)
            ctx.check_live(session)
            row = records.stage_row(session, ctx.bake_id, "impostors")
            row.seconds = round((row.seconds or 0.0) + seconds, 3)  # summed render seconds over parts
            if records.impostor_parts_left(session, ctx.bake_id) == 0:
                row.state, row.finished_at = "succeeded", records.utcnow()
                row.done = row.total
                records.append_log(session, ctx.bake_id, "INFO", "impostors", f"all {row.total} impostor-view tasks finished ({row.seconds:.2f} s of rendering)")
        _maybe_enqueue_pack(ctx, parts_left)

    run_stage(self, bake_id, attempt, "impostors", body, after, log_start=False, part=part_id)


@app.task(name=TASK_NAMES["pack"], **TASK_OPTIONS)
def pack(self, bake_id: str, attempt: int) -> None:
    def body(ctx: StageContext):
        pull_inputs(ctx, "pack")
        result = _stage("pack").stage_pack(ctx.work, progress=ctx.progress).to_json()
        return dict(result, outputs=push_outputs(ctx, STAGE_OUTPUTS["pack"]))

    def after(ctx: StageContext, result, seconds: float) -> None:
        with ctx.session() as session:
            bake = _finish(ctx, session, result, seconds)
            publish_next = bake.publish
            if not publish_next:
                row = records.stage_row(session, ctx.bake_id, "publish")
                row.state = "skipped"
                records.succeed_bake(session, bake)
        if publish_next:
            _send("publish", ctx.bake_id, ctx.attempt)

    run_stage(self, bake_id, attempt, "pack", body, after)


@app.task(name=TASK_NAMES["publish"], **TASK_OPTIONS)
def publish(self, bake_id: str, attempt: int) -> None:
    def body(ctx: StageContext):
        pull_inputs(ctx, "publish")
        with ctx.session() as session:
            bake = ctx.check_live(session)
            name, version = bake.name, bake.version
        bundles = ctx.services.bundles
        published = bundles.publish(ctx.work / "bundle", name, version)  # BundleConflict: other bytes published
        if ctx.services.settings.store == "local":
            # The engine export beside the bundle, unless export=false (exports live in local folders only).
            _stage("publish").stage_export(ctx.work, ctx.services.settings.bundles_dir)
        with ctx.session() as session:
            bake = ctx.check_live(session)
            register_bundle(session, bundles, name, version, bake.public, bake.id)
        return {"name": name, "version": version, "manifest_sha256": published.sha256}

    def after(ctx: StageContext, result, seconds: float) -> None:
        with ctx.session() as session:
            bake = _finish(ctx, session, result, seconds)
            records.succeed_bake(session, bake)

    run_stage(self, bake_id, attempt, "publish", body, after)
