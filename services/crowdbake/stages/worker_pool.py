"""The local runner's worker processes and their tuning for one machine: how many, how they start, how
their heap behaves. Nothing here changes what a bake makes, only how fast and in how much memory.

Workers fork from a fork server that imports the stages and pyrender once for them all (start_pool);
each runs WORKER_ITEMS items and is replaced by a fresh one; their malloc is set to reuse its own pages
(WORKER_MALLOC). Items whose peak memory should add to no worker's high-water mark run in a process of
their own (one_shot_pool).
"""
from __future__ import annotations

import atexit
import ctypes
import ctypes.util
import logging
import multiprocessing
import os
import resource
import threading
from concurrent.futures import Future, InvalidStateError, ProcessPoolExecutor
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

# At most this many worker processes: the two independent branches of the plan (poses, impostor tasks)
# keep two busy.
MAX_WORKERS = 2
# Items a worker process runs before a fresh one (forked from the fork server in milliseconds) replaces
# it: a worker's resident size otherwise creeps up from item to item (the heap's fragments, pyrender's
# caches) to twice what one item needs. A fresh worker starts with none of its pages (WORKER_MALLOC).
WORKER_ITEMS = 16

# The workers' malloc: a worker's items allocate and free the same large arrays item after item, and
# every page glibc hands back to the kernel (a freed array over the dynamic mmap threshold, the heap's top
# above the trim threshold) is zeroed again on its next use, llvmpipe's buffers included. Arrays up to
# 32 MiB (glibc's largest fixed threshold) come from the heap and the heap is never trimmed, so a worker
# reuses its own pages; the high-water mark that bounds a worker's memory does not grow from it (each is
# replaced after WORKER_ITEMS items). services/benchmarks/bench_bake.py measures the page faults.
WORKER_MALLOC = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 40)}

# What the fork server imports once for every worker: the runner, the stages its nodes run
# (plan.STAGE_MODULES), pyrender, and jsonschema, which the pack stage, publishing and the export each
# verify a bundle with. A worker forked after these imports starts its first item at once.
def preload() -> list[str]:
    from crowdbake.stages.plan import STAGE_MODULES

    return ["crowdbake.stages.runner", *STAGE_MODULES, "pyrender", "jsonschema"]


def usable_cores() -> int:
    """Processors this process may run on (its affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_workers() -> int:
    """Worker processes for a local bake: 2 where two cores are usable, else 0 (every node in process)."""
    return MAX_WORKERS if usable_cores() >= 2 and "forkserver" in multiprocessing.get_all_start_methods() else 0


def trim_heap() -> None:
    """Return the C heap's free pages to the system (glibc only; elsewhere nothing): NumPy's and OpenCV's
    many mid-sized temporaries otherwise leave the runner's resident size at its high-water mark."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        libc = None
    trim = getattr(libc, "malloc_trim", None)
    if trim is not None:
        trim(0)


def cpu_seconds(who: int = resource.RUSAGE_SELF) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def fork_server_cpu_seconds() -> float:
    """CPU seconds of the fork server so far (its imports), from /proc; 0 where it cannot be read."""
    from multiprocessing import forkserver

    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)  # no public accessor
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, TypeError):
        return 0.0


def start_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of `workers` processes forked from the fork server, which starts now (in the background, while
    this process validates and searches the cycle) and imports preload() once for them all."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(preload())
    from multiprocessing import forkserver

    # glibc reads its malloc settings from the environment when a process starts: the fork server's
    # (and so every worker's) are set here, this process's are left as they were.
    saved = {name: os.environ.get(name) for name in WORKER_MALLOC}
    os.environ.update(WORKER_MALLOC)
    try:
        forkserver.ensure_running()
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    if not _STOP_REGISTERED:
        atexit.register(_stop_fork_server)
        _STOP_REGISTERED.append(True)
    return ProcessPoolExecutor(workers, mp_context=context, max_tasks_per_child=WORKER_ITEMS)


def one_shot_pool() -> ProcessPoolExecutor:
    """One process from the fork server (start_pool started it) that runs a single item and exits: for an item
    whose peak memory should not add to a worker's high-water mark."""
    return ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("forkserver"), max_tasks_per_child=1)


def submit_in_background(pool: ProcessPoolExecutor, *call: Any) -> Future:
    """pool.submit(*call) from a thread, and a future of its result. A pool's first item waits for its
    worker to fork, which waits for the fork server's imports (start_pool): the caller need not."""
    outcome: Future = Future()

    def settle(done: Future) -> None:
        # The runner cancels what it still waits for when a bake fails: nobody reads this outcome then.
        try:
            if done.cancelled():
                outcome.cancel()
            elif done.exception() is not None:
                outcome.set_exception(done.exception())
            else:
                outcome.set_result(done.result())
        except InvalidStateError:
            pass

    def submit() -> None:
        try:
            pool.submit(*call).add_done_callback(settle)
        except BaseException as error:  # noqa: BLE001 - the pool shut down first: handed to whoever waits
            if not outcome.cancelled():
                outcome.set_exception(error)

    threading.Thread(target=submit, name="submit", daemon=True).start()
    return outcome


_STOP_REGISTERED: list[bool] = []


def _stop_fork_server() -> None:
    """At exit, stop the fork server and wait for it, so that the process's own accounting (its children's
    CPU seconds, `time`'s figures) includes the server and the workers it reaped. multiprocessing leaves it
    to die unwaited; its stop method is private, so only where it exists."""
    from multiprocessing import forkserver

    stop = getattr(forkserver._forkserver, "_stop", None)
    if stop is not None:
        try:
            stop()
        except OSError:
            logger.debug("stopping the fork server failed", exc_info=True)
