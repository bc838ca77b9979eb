"""The Celery application: configuration from Settings, and how stage tasks are enqueued.

Start a worker with the same CROWDBAKE_* environment as the API:

    celery -A crowdbake.jobs.celery_app worker -Q crowdbake --concurrency 2

Choices, and why:
  * `task_acks_late` + `task_reject_on_worker_lost`: a message is acknowledged only after its task
    finished, so a worker killed mid-stage hands the stage to another worker. This is safe because
    every stage is idempotent (outputs keyed by the hash of inputs, parameters and code version).
  * `worker_prefetch_multiplier = 1`: stages run for seconds to minutes; a worker holding several
    queued messages would starve its idle neighbours.
  * No result backend: the database records every stage's state and progress, and the fan-in of a
    fan-out's tasks is a barrier in the database (crowdbake.storage.records), not a Celery chord.
  * Redis in production (`visibility_timeout` above the longest stage: a long stage redelivered while
    it runs would be dropped anyway, its unit being claimed by a live delivery, but need not be). The
    filesystem transport for the one-command demo needs no server; each message is written under a
    hidden name and renamed into the queue (crowdbake.jobs.fs_transport), and it hands each message to
    one worker by renaming the file, and puts back the message of a pool process that died. What a whole worker had
    taken is lost with it on either broker until the visibility timeout: the heartbeats and the sweeper
    (crowdbake.jobs.sweeper) re-queue those stages.
"""
from __future__ import annotations

import logging
import time
from typing import Any

from celery import Celery, signals

from crowdbake.settings import Settings, get_settings

logger = logging.getLogger(__name__)

# Task names, one per stage; a fan-out stage's under its node's name (crowdbake.stages.plan.fan_out_of):
# the loops stage runs a "clip_loop" task per clip, the probes stage an "impostor_probe" task per probe,
# the impostors stage many "impostor_views" tasks.
TASK_NAMES = {
    "validate": "crowdbake.stage.validate",
    "clip_loop": "crowdbake.stage.clip_loop",
    "cycle": "crowdbake.stage.cycle",
    "impostor_probe": "crowdbake.stage.impostor_probe",
    "poses": "crowdbake.stage.poses",
    "impostor_views": "crowdbake.stage.impostor_views",
    "pack": "crowdbake.stage.pack",
    "publish": "crowdbake.stage.publish",
}
# Redis redelivers a message nobody acknowledged within this many seconds; longer than any stage.
REDIS_VISIBILITY_TIMEOUT_S = 6 * 3600
# How often a filesystem-broker consumer looks for new messages (kombu's default is 1 s).
FILESYSTEM_POLL_S = 0.1
# The filesystem broker's transport class (kombu's, with atomic writes: crowdbake.jobs.fs_transport).
FILESYSTEM_TRANSPORT = "crowdbake.jobs.fs_transport:Transport"
# Processed filesystem-broker messages older than this are deleted when a worker starts.
PROCESSED_MESSAGE_TTL_S = 3600
# Seconds any one Redis socket operation may block. Without it a broker that accepts connections but
# never answers (a stopped process, a stalled fsync, a partition) blocks the caller forever: an API
# thread enqueueing a bake, or a readiness probe.
REDIS_SOCKET_TIMEOUT_S = 5.0
# Enqueueing retries this often before it gives up and the bake is left for the dispatcher to send.
PUBLISH_RETRY_POLICY = {"max_retries": 2, "interval_start": 0.2, "interval_step": 0.5, "interval_max": 1.0}


def broker_transport_options(settings: Settings) -> dict[str, Any]:
    if settings.uses_filesystem_broker:
        queue_dir = str(settings.broker_dir / "queue")
        return {
            "data_folder_in": queue_dir,
            "data_folder_out": queue_dir,
            # Moving a claimed message within one file system is an atomic rename, so two workers can
            # never both take it; kombu's default moves it to /tmp, which may be another file system.
            "store_processed": True,
            "processed_folder": str(settings.broker_dir / "processed"),
            "control_folder": str(settings.broker_dir / "control"),
            "polling_interval": FILESYSTEM_POLL_S,
        }
    if settings.broker_url.startswith(("redis://", "rediss://")):
        return {
            "visibility_timeout": REDIS_VISIBILITY_TIMEOUT_S,
            "socket_timeout": REDIS_SOCKET_TIMEOUT_S,
            "socket_connect_timeout": REDIS_SOCKET_TIMEOUT_S,
        }
    return {}


def make_celery(settings: Settings) -> Celery:
    """A Celery app for `settings` (the API uses it to enqueue; the worker runs the tasks module).

    Creates nothing on disk; the API (and a worker, at start) call `settings.ensure_dirs()`."""
    app = Celery("crowdbake", broker=settings.broker_url, include=["crowdbake.jobs.tasks"])
    app.conf.update(
        broker_transport_options=broker_transport_options(settings),
        broker_connection_retry_on_startup=True,
        task_default_queue=settings.queue,
        task_serializer="json",
        accept_content=["json"],
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_ignore_result=True,
        result_backend=None,
        worker_prefetch_multiplier=1,
        worker_hijack_root_logger=False,
        task_store_errors_even_if_ignored=False,
        # Transient failures (a locked SQLite file, a full disk) are retried by the tasks themselves.
        task_publish_retry=True,
        task_publish_retry_policy=PUBLISH_RETRY_POLICY,
        broker_connection_timeout=REDIS_SOCKET_TIMEOUT_S,
    )
    if settings.uses_filesystem_broker:
        # kombu's filesystem transport, writing each message whole before a consumer can see it.
        app.conf.broker_transport = FILESYSTEM_TRANSPORT
    return app


def send_stage(celery: Celery, settings: Settings, stage: str, bake_id: str, attempt: int, *extra: Any) -> None:
    """Enqueue one stage task; tasks take ids (and small JSON), never arrays."""
    celery.send_task(TASK_NAMES[stage], args=[bake_id, attempt, *extra], queue=settings.queue)


def broker_reachable(celery: Celery, timeout: float = 2.0) -> str | None:
    """None when the broker answers a round trip, else why not (for /ready).

    A TCP connect alone proves nothing (a stopped Redis still accepts connections), so this asks the
    transport for a queue declaration, which needs an answer. Callers bound the wall time themselves
    (crowdbake.api.readiness): the socket timeouts above are the second line of defence."""
    try:
        with celery.connection_for_write() as connection:
            connection.ensure_connection(max_retries=1, timeout=timeout)
            channel = connection.default_channel
            channel.queue_declare(queue=celery.conf.task_default_queue, passive=False, durable=True, auto_delete=False)
    except Exception as error:  # any transport error means "not ready"
        return type(error).__name__
    return None


@signals.worker_init.connect
def _create_dirs(sender=None, **_kwargs) -> None:
    get_settings().ensure_dirs()


@signals.worker_ready.connect
def _clean_processed_messages(sender=None, **_kwargs) -> None:
    settings = get_settings()
    if not settings.uses_filesystem_broker:
        return
    cutoff = time.time() - PROCESSED_MESSAGE_TTL_S
    for path in (settings.broker_dir / "processed").glob("*.msg"):
        try:
            if path.stat().st_mtime < cutoff:
                path.unlink()
        except OSError:
            pass


_app: Celery | None = None


def __getattr__(name: str) -> Celery:
    """`app`, the worker's Celery app (`celery -A crowdbake.jobs.celery_app`), built from the
    environment's settings on first use, so importing this module reads no settings."""
    global _app
    if name == "app":
        if _app is None:
            _app = make_celery(get_settings())
        return _app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
