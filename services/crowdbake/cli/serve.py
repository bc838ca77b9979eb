"""`crowdbake serve`: the API and its bake workers on one machine, for local use and demos."""
from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from typing import Callable

from crowdbake.cli.common import CommandError

logger = logging.getLogger(__name__)

DESCRIPTION = """\
Starts the crowdbake API (uvicorn) and N Celery bake workers as subprocesses, all reading the same
settings. Without --broker (or CROWDBAKE_BROKER_URL) the job queue is Celery's filesystem transport
under the data folder, so nothing else needs to run; give --broker redis://... to share a Redis.
The database is migrated at start. A worker that dies is restarted, and the stage it was running is
re-queued by the API's sweeper once its heartbeat stops (CROWDBAKE_HEARTBEAT_TIMEOUT).
Create a key first: crowdbake keys create --data DIR --scopes ..."""

# Seconds an idle keep-alive connection stays open (uvicorn --timeout-keep-alive; the deploy manifests match).
KEEP_ALIVE_S = 5
# Seconds a worker gets to finish its current task on shutdown before it is killed.
WORKER_STOP_TIMEOUT_S = 20
# How often the supervisor looks whether the worker is still there, and the waits before restarting
# one that died: doubling from the first to the last, back to the first once a worker lived a minute
# (a worker that dies at start, from a broken setting, must not spin).
SUPERVISE_POLL_S = 0.5
RESTART_BACKOFF_S = (0.5, 30.0)
STABLE_WORKER_S = 60.0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("serve", help="run the API and bake workers locally", description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    parser.add_argument("--workers", type=int, default=2, metavar="N", help="concurrent bake tasks (default 2; 0 = API only)")
    parser.add_argument("--data", metavar="DIR", help="data folder (default CROWDBAKE_DATA_DIR or ./crowdbake-data)")
    parser.add_argument("--broker", metavar="URL", help="Celery broker URL (default CROWDBAKE_BROKER_URL or the filesystem broker)")
    parser.add_argument("--database", metavar="URL", help="database URL (default CROWDBAKE_DATABASE_URL or SQLite in the data folder)")
    parser.set_defaults(func=run)


def _worker_command(settings, workers: int) -> list[str]:
    return [
        sys.executable, "-m", "celery", "-A", "crowdbake.jobs.celery_app", "worker",
        "--loglevel", "INFO", "--pool", "prefork", "--concurrency", str(workers),
        "--queues", settings.queue, "--hostname", f"crowdbake-{os.getpid()}@%h", "--without-gossip", "--without-mingle",
    ]


# prctl(2) option: the signal a child receives when its parent dies.
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Runs in the worker child before exec: ask the kernel for SIGTERM when `serve` dies, however it dies
    (SIGKILL included), so a killed `serve` never leaves a worker taking jobs on its own."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def start_worker(settings, workers: int, env: dict[str, str] | None = None) -> subprocess.Popen:
    """A Celery worker subprocess with `workers` prefork children, using this process's settings; it stops
    (warm shutdown) when this process dies."""
    return subprocess.Popen(_worker_command(settings, workers), env=env or os.environ.copy(), preexec_fn=_die_with_parent)


def stop_worker(process: subprocess.Popen) -> None:
    """Warm shutdown (finish the current task), then kill after WORKER_STOP_TIMEOUT_S."""
    if process.poll() is not None:
        return
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(timeout=WORKER_STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


class WorkerSupervisor:
    """Keeps one Celery worker subprocess running for `crowdbake serve`: when it dies (killed, out of
    memory, crashed) it is reaped (no zombie) and started again, with a growing wait if it keeps
    dying at start. What it was running is recovered by the sweeper (its heartbeats stop)."""

    def __init__(self, start: Callable[[], subprocess.Popen]):
        self._start = start
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self.process = start()
        self.started_at = time.monotonic()
        self.restarts = 0
        self._thread = threading.Thread(target=self._watch, name="worker-supervisor", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        backoff = RESTART_BACKOFF_S[0]
        while not self._stopping.wait(SUPERVISE_POLL_S):
            with self._lock:
                code = self.process.poll()  # reaps the child once it exited
                if code is None or self._stopping.is_set():
                    continue
                lived = time.monotonic() - self.started_at
            backoff = RESTART_BACKOFF_S[0] if lived > STABLE_WORKER_S else backoff
            logger.warning("crowdbake serve: the bake worker (pid %d) exited with %s after %.0f s; restarting in %.1f s",
                           self.process.pid, code, lived, backoff)
            print(f"crowdbake serve: the bake worker exited ({code}); restarting it", file=sys.stderr)
            if self._stopping.wait(backoff):
                return
            backoff = min(backoff * 2, RESTART_BACKOFF_S[1])
            with self._lock:
                if self._stopping.is_set():
                    return
                self.process = self._start()
                self.started_at = time.monotonic()
                self.restarts += 1

    def stop(self) -> None:
        self._stopping.set()
        with self._lock:
            stop_worker(self.process)
        self._thread.join(timeout=5)


def _exit_on_signal(signum, _frame) -> None:
    raise SystemExit(128 + signum)


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from crowdbake.settings import Settings, get_settings, redact_url

    if args.workers < 0:
        raise CommandError("--workers must be >= 0")
    # The workers read their settings from the environment: put every override there.
    for option, variable in ((args.data, "CROWDBAKE_DATA_DIR"), (args.broker, "CROWDBAKE_BROKER_URL"), (args.database, "CROWDBAKE_DATABASE_URL")):
        if option:
            os.environ[variable] = str(option)
    get_settings.cache_clear()
    try:
        settings = Settings()
    except ValidationError as error:
        raise CommandError(f"refusing to start: {error.errors()[0]['msg']}") from None
    os.environ["CROWDBAKE_DATA_DIR"] = str(settings.data_dir)

    import uvicorn
    from sqlalchemy import func, select

    from crowdbake.api.app import create_app
    from crowdbake.api.slow_clients import HeaderTimeoutProtocol
    from crowdbake.storage.models import ApiKey

    app = create_app(settings)
    with app.state.services.sessions() as session:
        if not session.scalar(select(func.count()).select_from(ApiKey).where(ApiKey.revoked_at.is_(None))):
            print(f"crowdbake serve: no API keys yet; create one with: crowdbake keys create --data {settings.data_dir} --scopes upload,bake,publish,read",
                  file=sys.stderr)
    # uvicorn handles SIGTERM itself and, once shut down, raises it again with the handler that was there
    # before it started: make that handler an exception, so the `finally` below stops the workers.
    signal.signal(signal.SIGTERM, _exit_on_signal)
    worker = WorkerSupervisor(lambda: start_worker(settings, args.workers)) if args.workers else None
    print(f"crowdbake serve: API on http://{args.host}:{args.port} (docs at /docs), {args.workers} worker(s), "
          f"data {settings.data_dir}, broker {redact_url(settings.broker_url)}", file=sys.stderr)
    try:
        # Slow clients: a deadline on request headers (the protocol) and a short keep-alive; the body's
        # minimum rate is the app's own middleware (crowdbake.api.slow_clients).
        uvicorn.run(app, host=args.host, port=args.port, log_level="info", http=HeaderTimeoutProtocol, timeout_keep_alive=KEEP_ALIVE_S)
    finally:
        if worker is not None:
            worker.stop()
    return 0
