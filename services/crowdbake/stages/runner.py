"""Every stage of a bake from one process (`crowdbake bake`, the tests, the benchmarks).

The service runs the same stage functions as Celery tasks (crowdbake.jobs.tasks); this runner is the
one-machine version: validate → cycle → impostor plan → (poses ∥ impostor tasks) → pack → publish.
The poses stage's textures need only the validated job: a worker encodes them while this process searches
the cycle (crowdbake.stages.poses.stage_textures).

The poses stage and the impostor tasks need only the cycle's output (crowdbake.stages.impostors.
stage_impostor_plan), so where two cores are free they run side by side in a pool of two worker
processes (see start_pool). Between stages this process hands the
heap's free pages back to the system (glibc's malloc_trim): NumPy's and OpenCV's many mid-sized
temporaries otherwise leave the resident size at its high-water mark for the rest of the bake.

Timings (BakeSummary.timings): wall, CPU (this process and its workers) and seconds inside OpenGL
(crowdbake.render.offscreen.render_timings, read around every stage and in the workers), per stage and in all.
"""
from __future__ import annotations

import atexit
import ctypes
import logging
import ctypes.util
import multiprocessing
import os
import resource
import shutil
import tempfile
import threading
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from itertools import zip_longest
from pathlib import Path
from typing import Any, Callable

from crowdbake.render.offscreen import render_timings
from crowdbake.stages import STAGES
from crowdbake.stages.cycle import stage_cycle
from crowdbake.stages.impostors import (
    FIDELITY_SUPERSAMPLE, impostor_statistics, impostor_tasks, load_plan, load_poses, stage_impostor_plan, stage_impostor_views,
)
from crowdbake.stages.pack import score_frames, stage_pack, stage_pack_frame, stage_pack_scores
from crowdbake.stages.poses import stage_poses, stage_textures
from crowdbake.stages.publish import check_export_before_publishing, stage_export, stage_export_ahead, stage_publish
from crowdbake.storage.exports import commit_export, discard_export, export_home
from crowdbake.stages.records import PosesRecord
from crowdbake.stages.runtime_fidelity import between_references
from crowdbake.stages.validate import BakeInputs, stage_validate
from crowdbake.stages.workdir import Progress, read_json, report

logger = logging.getLogger(__name__)

# At most this many worker processes: the two independent stages (poses, impostor tasks) keep two busy.
MAX_WORKERS = 2
# Items a worker process runs before a fresh one (forked from the fork server in milliseconds) replaces
# it: a worker's resident size otherwise creeps up from item to item (the heap's fragments, pyrender's
# caches) to twice what one item needs. A fresh worker starts with none of its pages (WORKER_MALLOC):
# at 16 the sample's largest worker peaks as it did at 8 (608 to 612 MiB, bench_bake.py).
WORKER_ITEMS = 16

# The workers' malloc: a worker's items allocate and free the same large arrays item after item, and
# every page glibc hands back to the kernel (a freed array over the dynamic mmap threshold, the heap's top
# above the trim threshold) is zeroed again on its next use, llvmpipe's buffers included: 1.3 million page
# faults in a sample bake, 0.6 million with these settings (bench_bake.py's process_tree). Arrays up to
# 32 MiB (glibc's largest fixed threshold) come from the heap and the heap is never trimmed, so a worker
# reuses its own pages; the high-water mark that bounds a worker's memory stays as it was (each is
# replaced after WORKER_ITEMS items).
WORKER_MALLOC = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 40)}


def usable_cores() -> int:
    """Processors this process may run on (its affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_workers() -> int:
    """Worker processes for the poses ∥ impostors part: 2 where two cores are usable, else 0 (in process)."""
    return MAX_WORKERS if usable_cores() >= 2 and "forkserver" in multiprocessing.get_all_start_methods() else 0


def _trim_heap() -> None:
    """Return the C heap's free pages to the system (glibc only; elsewhere nothing)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        libc = None
    trim = getattr(libc, "malloc_trim", None)
    if trim is not None:
        trim(0)


def _cpu_seconds(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _fork_server_cpu_seconds() -> float:
    """CPU seconds of the fork server so far (its imports), from /proc; 0 where it cannot be read."""
    from multiprocessing import forkserver

    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)  # no public accessor
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, TypeError):
        return 0.0


@dataclass
class StageFigures:
    """One stage's wall, CPU and OpenGL seconds (in workers: summed over its tasks; wall of a stage that ran
    in a worker is its own time there)."""

    wall_s: float = 0.0
    cpu_s: float = 0.0
    render_s: float = 0.0
    renders: int = 0

    def add(self, other: dict[str, float]) -> None:
        self.wall_s += other["wall_s"]
        self.cpu_s += other["cpu_s"]
        self.render_s += other["render_s"]
        self.renders += int(other["renders"])


class _Meter:
    """Wall, CPU and GL seconds of blocks run in this process."""

    def __init__(self) -> None:
        self.stages: dict[str, StageFigures] = {stage: StageFigures() for stage in STAGES}
        self.parallel_wall_s = 0.0  # the poses ∥ impostors part, when it ran in the pool
        self.worker_peak_rss_mib: float | None = None  # the largest worker's high-water mark (from the fork on)
        self.worker_cpu_s: dict[int, float] = {}  # per worker process, its CPU seconds at its last item
        self.epoch = time.time()  # the bake's start, for the timeline
        self.timeline: list[dict[str, Any]] = []  # worker items: name, process, start and end seconds, CPU seconds

    def account_worker(self, figures: dict[str, Any]) -> None:
        """Note a worker item's process figures: its high-water mark, its process's CPU so far and its span."""
        name, began, ended = figures["span"]
        self.timeline.append({"item": name, "pid": figures["pid"], "start_s": began - self.epoch, "end_s": ended - self.epoch,
                              "cpu_s": figures["cpu_s"], "process_peak_rss_mib": figures["peak_rss_mib"]})
        self.worker_peak_rss_mib = max(self.worker_peak_rss_mib or 0.0, figures["peak_rss_mib"])
        self.worker_cpu_s[figures["pid"]] = max(self.worker_cpu_s.get(figures["pid"], 0.0), figures["process_cpu_s"])

    def figures(self, stage: str) -> StageFigures:
        return self.stages.setdefault(stage, StageFigures())

    def run(self, stage: str, body: Callable[[], Any]) -> Any:
        began = time.time()
        figures = measured(body)
        self.timeline.append({"item": stage, "pid": os.getpid(), "start_s": began - self.epoch,
                              "end_s": time.time() - self.epoch, "cpu_s": figures["cpu_s"]})
        self.figures(stage).add(figures)
        _trim_heap()
        return figures["result"]


class _Background:
    """Callables run one after another in a thread from start() on; result() waits and re-raises their
    error. Their CPU seconds (time.thread_time) are added to `figures`."""

    def __init__(self, name: str, calls: list[Callable[[], None]], figures: StageFigures):
        self._calls, self._figures, self._error = calls, figures, None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread (once; a second call does nothing)."""
        if self._thread.ident is None:
            self._thread.start()

    def _run(self) -> None:
        started = time.thread_time()
        try:
            for call in self._calls:
                call()
        except BaseException as error:  # noqa: BLE001 - handed to the caller by result()
            self._error = error
        self._figures.cpu_s += time.thread_time() - started

    def result(self) -> None:
        self.start()  # where nothing started it (an error before its moment)
        self._thread.join()
        if self._error is not None:
            raise self._error


def measured(body: Callable[[], Any]) -> dict[str, Any]:
    """Run body; its result and the wall, CPU (this process, every thread) and GL seconds it took."""
    gl, wall, cpu = render_timings(), time.perf_counter(), time.process_time()
    result = body()
    gl = render_timings().minus(gl)
    return {"result": result, "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
            "render_s": gl.seconds, "renders": gl.renders}


def _worker_item(work: str, item: str, task: dict | None = None, frame: int | None = None, out_root: str | None = None) -> dict[str, Any]:
    """One item of the poses ∥ impostors part, in a worker process: the poses stage's textures (during the
    cycle search), the poses stage with the pack stage's runtime-fidelity mesh references, one impostor
    task, or one baked frame's atlases for the pack stage (once that frame's tasks are done); then the pack
    stage, and the publish stage into `out_root` beside the engine export built ahead of it."""
    began = time.time()
    if item == "publish-bundle":
        figures = measured(lambda: str(stage_publish(Path(work), Path(out_root))))
    elif item == "export":
        figures = measured(lambda: None if (staging := stage_export_ahead(Path(work), Path(out_root))) is None else str(staging))
    elif item == "poses":
        # Then the pack stage's mesh references for the runtime scores, which need only the poses: in the
        # same worker, while this process plans the impostor tasks.
        figures = measured(lambda: (stage_poses(Path(work)).cached,
                                    len(between_references(Path(work), load_poses(Path(work)), FIDELITY_SUPERSAMPLE))))
    elif item == "textures":
        figures = measured(lambda: len(stage_textures(Path(work)).materials))
    elif item == "pack":
        figures = measured(lambda: str(stage_pack_frame(Path(work), frame)))
    elif item == "pack-stage":
        figures = measured(lambda: stage_pack(Path(work)).cached)
    elif item == "scores":
        figures = measured(lambda: str(stage_pack_scores(Path(work))))
    else:
        figures = measured(lambda: str(stage_impostor_views(Path(work), task)))
    # No heap trim here: the worker's next item reuses these pages (WORKER_MALLOC, start_pool).
    figures["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    figures["pid"], figures["process_cpu_s"] = os.getpid(), _cpu_seconds(resource.RUSAGE_SELF)
    figures["span"] = (item if frame is None and task is None else f"{item}:{(task or {}).get('id', frame)}", began, time.time())
    return figures


def _publish_beside_export(work: Path, out_root: Path, pool: ProcessPoolExecutor, meter: _Meter) -> Path:
    """The publish stage and the engine export in two workers at once: the export is built from work/bundle
    beside its home and put in place only once the bundle is published (a version conflict discards it)."""
    started = time.perf_counter()
    check_export_before_publishing(work, out_root)
    # The export holds the bundle's layers decoded and its zip's input at once: in a process of its own,
    # fresh from the fork server, its peak adds to no worker's rendering leftovers.
    exporter = one_shot_pool()
    results = {}
    try:
        export = exporter.submit(_worker_item, str(work), "export", out_root=str(out_root))
        publish = pool.submit(_worker_item, str(work), "publish-bundle", out_root=str(out_root))
        for name, future in (("publish", publish), ("export", export)):
            try:
                results[name] = future.result()
            except BaseException as error:
                results[name] = error
    finally:
        exporter.shutdown(wait=True, cancel_futures=True)
    staging = results["export"]["result"] if isinstance(results["export"], dict) else None
    for figures in results.values():
        if isinstance(figures, dict):
            meter.account_worker(figures)
            meter.figures("publish").add(dict(figures, wall_s=0.0))  # side by side: the stage's wall is both's, below
    meter.figures("publish").wall_s += time.perf_counter() - started
    for outcome in (results["publish"], results["export"]):
        if isinstance(outcome, BaseException):
            discard_export(Path(staging) if staging else None)
            raise outcome
    bundle = Path(results["publish"]["result"])
    if staging:
        manifest = read_json(bundle / "manifest.json")
        commit_export(Path(staging), export_home(out_root, manifest["name"], manifest["version"]))
    return bundle


def _publish(work: Path, out_root: Path) -> Path:
    """The publish stage and the engine export, which is part of publishing as in the worker's publish task
    (none when the bake's `export` parameter is false)."""
    check_export_before_publishing(work, out_root)
    published = stage_publish(work, out_root)
    stage_export(work, out_root)
    return published


def start_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of `workers` processes forked from the fork server, which starts now (in the background, while
    this process validates and searches the cycle) and imports the stages and pyrender once for them all,
    and jsonschema, which the pack stage, publishing and the export each verify a bundle with (45 ms
    of imports in each of those fresh processes at the bake's end, where nothing runs beside them)."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["crowdbake.stages.runner", "pyrender", "jsonschema"])
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


def submit_in_background(pool: ProcessPoolExecutor, *call: Any) -> Future:
    """pool.submit(*call) from a thread, and a future of its result. The pool's first item waits for its
    worker to fork, which waits for the fork server's imports (start_pool): this process need not."""
    outcome: Future = Future()

    def settle(done: Future) -> None:
        error = done.exception()
        if error is not None:
            outcome.set_exception(error)
        else:
            outcome.set_result(done.result())

    def submit() -> None:
        try:
            pool.submit(*call).add_done_callback(settle)
        except BaseException as error:  # noqa: BLE001 - the pool shut down first: handed to whoever waits
            outcome.set_exception(error)

    threading.Thread(target=submit, name="submit", daemon=True).start()
    return outcome


def one_shot_pool() -> ProcessPoolExecutor:
    """One process from the fork server (start_pool started it) that runs a single item and exits: for an item
    whose peak memory should not add to a worker's high-water mark."""
    return ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("forkserver"), max_tasks_per_child=1)


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


def task_order(tasks: list, workers: int) -> list:
    """The order the pool takes impostor tasks in. Fidelity-frame tasks (with their mesh references) take
    several times an ordinary one: they go first. The rest go frame by frame, so that each frame's atlases
    can be packed while later frames render, except the last `workers` frames, whose tasks alternate: those
    frames then finish together and their packs run side by side at the end instead of one after another
    on one core. tasks: ImpostorTasks (frame, id), in the plan's order."""
    plain = [task for task in tasks if not task.references]
    frames = list(dict.fromkeys(task.frame for task in plain))
    tail = set(frames[-workers:]) if workers > 1 else set()
    by_frame = [[task for task in plain if task.frame == frame] for frame in frames if frame in tail]
    interleaved = [task for ring in zip_longest(*by_frame) for task in ring if task is not None]
    return [task for task in tasks if task.references] + [task for task in plain if task.frame not in tail] + interleaved


def _poses_and_impostors(work: Path, pool: ProcessPoolExecutor | None, workers: int, meter: _Meter, progress: Progress | None,
                         textures: Future | None = None, after_plan: Callable[[], None] = lambda: None) -> None:
    """The impostor plan, the poses stage and every impostor task: in the pool (the plan here, while a
    worker starts on the poses), the longest items first, or all in order here. textures: the pool's
    stage_textures item, started before the cycle; the poses stage starts once it is done. after_plan:
    called once the first impostor tasks are handed out."""
    if pool is None:
        meter.run("impostors", lambda: stage_impostor_plan(work, progress))
        after_plan()
        tasks = impostor_tasks(work)
        meter.run("poses", lambda: stage_poses(work, progress))
        for done, task in enumerate(tasks):
            report(progress, "impostors", done, len(tasks))
            meter.run("impostors", lambda task=task: stage_impostor_views(work, task))
        report(progress, "impostors", len(tasks), len(tasks))
        return
    started = time.perf_counter()
    if textures is not None:
        figures = textures.result()  # the cycle search took longer: normally done already
        meter.account_worker(figures)
        meter.figures("poses").add(figures)
    pending: dict[Future, tuple[str, int | None]] = {pool.submit(_worker_item, str(work), "poses"): ("poses", None)}
    plan = measured(lambda: stage_impostor_plan(work, progress))
    meter.figures("impostors").add(dict(plan, wall_s=0.0))  # within the part's wall, below
    tasks = impostor_tasks(work)
    report(progress, "impostors", 0, len(tasks))
    ordered = task_order(tasks, workers)
    waiting: deque[tuple[str, dict | None, int | None]] = deque(("impostors", task.to_json(), task.frame) for task in ordered)
    # A frame's atlases are packed as soon as its last task is done, ahead of the tasks still waiting; the
    # pool is fed one item per free worker so that such an item does not queue behind them all.
    packable: deque[tuple[str, dict | None, int | None]] = deque()
    frame_tasks_left = {frame: sum(task.frame == frame for task in tasks) for frame in {task.frame for task in tasks}}
    done_tasks = 0
    # The pack stage's scoring (stage_pack_scores) starts once the poses, their mesh references and the
    # frames it reads are done, while later tasks still render, instead of after them all on one core.
    scoring_needs: set = {"poses", *(("frame", f) for f in score_frames(load_plan(work)))}
    scoring_queued = False

    def ready_to_score() -> None:
        nonlocal scoring_queued
        if not scoring_queued and not scoring_needs:
            scoring_queued = True
            packable.append(("scores", None, None))

    def feed() -> None:
        while len(pending) < workers and (packable or waiting):
            stage, task, frame = (packable or waiting).popleft()
            pending[submit(stage, task, frame)] = (stage, frame)

    # The scoring item holds the fidelity frame's references and decoded atlases (about 560 MB alone): it runs
    # in a process of its own, fresh from the fork server, not on top of a worker's rendering leftovers.
    # It counts as one of the `workers` busy processes.
    scorer = one_shot_pool()

    def submit(stage: str, task: dict | None, frame: int | None) -> Future:
        return (scorer if stage == "scores" else pool).submit(_worker_item, str(work), stage, task, frame)

    try:
        feed()
        after_plan()
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in finished:
                item, frame = pending.pop(future)
                stage = "pack" if item == "scores" else item
                figures = future.result()
                meter.account_worker(figures)
                if stage in ("impostors", "pack"):
                    figures = dict(figures, wall_s=0.0)  # the items overlap: the impostor stage's wall is the part's, below
                meter.figures(stage).add(figures)
                if stage == "impostors":
                    done_tasks += 1
                    report(progress, "impostors", done_tasks, len(tasks))
                    frame_tasks_left[frame] -= 1
                    if frame_tasks_left[frame] == 0:
                        packable.append(("pack", None, frame))
                elif stage == "poses":
                    report(progress, "poses", 1, 1)
                if item == "pack":
                    scoring_needs.discard(("frame", frame))
                elif item == "poses":
                    scoring_needs.discard("poses")
                ready_to_score()
            feed()
    finally:
        scorer.shutdown(wait=True, cancel_futures=True)
    meter.parallel_wall_s = time.perf_counter() - started
    # Side by side, the impostor stage lasts from its plan to its last task (poses keeps its own time).
    meter.figures("impostors").wall_s += meter.parallel_wall_s


@dataclass
class BakeSummary:
    """What run_bake did: where the bundle is, how big, how long each stage took, how faithful."""

    bundle: Path
    name: str
    version: str
    timings_s: dict[str, float]
    files: dict[str, int]
    meshes: list[dict[str, Any]]
    cycle: dict[str, Any]
    impostor: dict[str, Any]
    fidelity: dict[str, Any]
    compression: dict[str, Any]
    texture_memory: dict[str, Any]
    # Set when a texture variation is a JPEG (no alpha, so no colour-region codes): what that means.
    texture_note: str | None = None
    timings: dict[str, Any] = field(default_factory=dict)

    @property
    def total_bytes(self) -> int:
        return int(sum(self.files.values()))

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["bundle"] = str(self.bundle)
        data["total_bytes"] = self.total_bytes
        return data


def _mesh_summary(meshes: list[dict], poses: PosesRecord) -> list[dict]:
    """The manifest's meshes, low LODs with their target and meshoptimizer's error."""
    out = []
    for mesh in meshes:
        entry = {k: mesh[k] for k in ("part", "kind", "lod", "vertex_count", "triangle_count", "file")}
        if mesh["lod"] == 1:
            for part in poses.parts:
                if part.lod == 1 and part.part == mesh["part"]:
                    entry.update(target_triangles=part.target_triangles, relative_error=part.relative_error, locked_border=part.locked_border)
        out.append(entry)
    return out


def run_bake(inputs: BakeInputs, out_root: Path, work: Path | None = None, progress: Progress | None = None,
             workers: int | None = None) -> BakeSummary:
    """Run every stage and publish to out_root/<name>/<version>; returns a BakeSummary.

    work: the work directory (kept, so a rerun resumes); None = a temporary one, removed afterwards (the
    cycle report it would hold is written without its plots).
    workers: processes for the poses ∥ impostors part (None = default_workers(); 0 or 1 = this process).
    As with any multiprocessing start method but "fork", a script that calls this with workers must
    guard its top level with `if __name__ == "__main__":` (the workers import the main module).
    """
    temporary = work is None
    work = Path(tempfile.mkdtemp(prefix="crowdbake-work-")) if temporary else Path(work)
    work.mkdir(parents=True, exist_ok=True)
    workers = default_workers() if workers is None else int(workers)
    meter = _Meter()
    wall, cpu = time.perf_counter(), _cpu_seconds(resource.RUSAGE_SELF)
    pool = start_pool(workers) if workers > 1 else None
    server_cpu = _fork_server_cpu_seconds() if pool is not None else 0.0
    try:
        job = meter.run("validate", lambda: stage_validate(inputs, work)).record
        # The textures (part of the poses stage) need the job alone: a worker encodes them during the cycle search.
        textures = submit_in_background(pool, _worker_item, str(work), "textures") if pool is not None else None
        plots: list[Callable[[], None]] = []
        cycle = meter.run("cycle", lambda: stage_cycle(work, progress, plots=plots)).record
        # The cycle report's plots (a second or more of matplotlib) are drawn in a thread of this process,
        # which otherwise only waits for the workers; run_bake returns once they are written. The thread
        # starts once the impostor plan is made and its first tasks handed out: the plan, in this process
        # too, waits for the interpreter lock while matplotlib holds it, and every impostor task waits for
        # the plan. In a temporary work folder nobody will see the report: its plots are not drawn at all.
        plotter = _Background("cycle-plots", [] if temporary else plots, meter.figures("cycle"))
        try:
            _poses_and_impostors(work, pool, workers, meter, progress, textures, after_plan=plotter.start)
            if pool is not None:
                # The pack and publish stages too, in workers: their peak memory (the fidelity scoring holds
                # the fidelity frame's references and atlases; publishing reads the bundle twice and the
                # export decodes every atlas layer) then adds to no earlier stage's leftovers here.
                report(progress, "pack", 0, 1)
                figures = pool.submit(_worker_item, str(work), "pack-stage").result()
                meter.account_worker(figures)
                meter.figures("pack").add(figures)
                report(progress, "pack", 1, 1)
            plotter.result()
            poses = PosesRecord.from_json(read_json(work / "poses" / "record.json"))
            impostor = impostor_statistics(work)
            pack = meter.run("pack", lambda: stage_pack(work, progress)).record  # in this process, or the worker's record
            if pool is not None:
                bundle = _publish_beside_export(work, Path(out_root), pool, meter)
            else:
                bundle = meter.run("publish", lambda: _publish(work, Path(out_root)))
            report(progress, "publish", 1, 1)
        finally:
            if pool is not None:
                pool.shutdown(wait=True)
                pool = None
                server_cpu = _fork_server_cpu_seconds() - server_cpu  # its imports, on the first bake of a process
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        if temporary:
            shutil.rmtree(work, ignore_errors=True)
    timings = {
        "total_s": time.perf_counter() - wall,
        # This process, each worker (whole life: fresh from the fork server) and the fork server's imports.
        "cpu_s": _cpu_seconds(resource.RUSAGE_SELF) - cpu + sum(meter.worker_cpu_s.values()) + server_cpu,
        "render_s": sum(f.render_s for f in meter.stages.values()),
        "renders": sum(f.renders for f in meter.stages.values()),
        "workers": workers if workers > 1 else 1,
        "poses_with_impostors_s": meter.parallel_wall_s or None,
        "peak_rss_mib": {
            "process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "largest_worker": meter.worker_peak_rss_mib,
        },
        "stages": {stage: asdict(meter.figures(stage)) for stage in STAGES},
        "timeline": sorted(meter.timeline, key=lambda span: span["start_s"]),
    }
    manifest = read_json(bundle / "manifest.json")
    return BakeSummary(
        bundle=bundle,
        name=manifest["name"],
        version=manifest["version"],
        timings_s={stage: meter.figures(stage).wall_s for stage in STAGES},
        files={entry["path"]: entry["size"] for entry in manifest["files"]},
        meshes=_mesh_summary(manifest["meshes"], poses),
        cycle={k: getattr(cycle, k) for k in ("start_frame", "end_frame", "cycle_frames", "closing", "position_jump_ratio", "velocity_jump_ratio", "fps")},
        impostor=asdict(impostor),
        fidelity=dict(pack.fidelity, uv_precision=pack.uv_precision),
        compression=pack.compression,
        texture_memory=pack.texture_memory,
        texture_note=(job.textures or {}).get("note"),
        timings=timings,
    )
