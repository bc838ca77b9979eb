"""A whole bake on one machine (`crowdbake bake`, the tests, the benchmarks): the bake plan
(crowdbake.stages.plan) run by this process and a pool of worker processes.

Every node starts as soon as what it needs is done: the textures are encoded in a worker while the
clips' loops are searched in the others (for one clip, while this process searches the cycle); the poses
stage and the impostor tasks run side by side; a frame's atlases are packed as soon as that frame's tasks
are done, and the scores as soon as their frames are; the bundle is published while its engine export is
built. Where fewer than two cores are usable every node
runs here, in plan order. How the workers start and behave is crowdbake.stages.worker_pool's business.

Timings (BakeSummary.timings): wall, CPU (this process and its workers) and seconds inside OpenGL, per
stage and in all, and the timeline of every item (crowdbake.stages.timings).
"""
from __future__ import annotations

import itertools
import resource
import shutil
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from crowdbake.stages import STAGES
from crowdbake.stages.plan import ALONE, BAKE_PLAN, HERE, NODES, Call, Node, Trace
from crowdbake.stages.timings import Background, Meter, measured
from crowdbake.stages.worker_pool import (
    cpu_seconds, default_workers, fork_server_cpu_seconds, one_shot_pool, start_pool, submit_in_background, trim_heap,
)
from crowdbake.stages.publish import LocalDestination
from crowdbake.stages.workdir import Progress, read_json, report

def run_node(name: str, work: str, item: Any, destination: LocalDestination) -> dict[str, Any]:
    """One node (or one item of a fan-out node) in a worker process: its result and figures (measured)."""
    return measured(lambda: NODES[name].run(Call(Path(work), item, destination=destination)))


@dataclass
class _Item:
    node: Node
    item: Any
    key: str | None
    needs: list[tuple[str, str | None]]


class _Schedule:
    """Which items of the plan are listed, waiting, running and done."""

    def __init__(self, work: Path, workers: int):
        self.work, self.workers = work, workers
        self.listed: dict[str, list[_Item]] = {}
        self.done: set[tuple[str, str | None]] = set()
        self.started: set[tuple[str, str | None]] = set()

    def node_done(self, name: str) -> bool:
        return name in self.listed and all((name, it.key) in self.done for it in self.listed[name])

    def _listable(self, node: Node) -> bool:
        if node.item_needs is not None:  # items list their own needs: the nodes need only be listed
            return all(need in self.listed for need in node.needs)
        return all(self.node_done(need) for need in node.needs)

    def refresh(self) -> list[_Item]:
        """List what became listable; the items that can start now, not yet started, in plan order."""
        for node in BAKE_PLAN:
            if node.name not in self.listed and self._listable(node):
                values = node.items(self.work) if node.fans_out else [None]
                if node.order is not None:
                    values = node.order(values, self.workers)
                self.listed[node.name] = [
                    _Item(node, value, None if not node.fans_out else node.item_key(value),
                          node.item_needs(self.work, value) if node.item_needs else [(need, None) for need in node.needs])
                    for value in values]
        ready = []
        for items in self.listed.values():
            for it in items:
                if (it.node.name, it.key) not in self.started and all(
                        (name, key) in self.done if key is not None else self.node_done(name) for name, key in it.needs):
                    ready.append(it)
        return ready

    def all_done(self) -> bool:
        return all(self.node_done(node.name) for node in BAKE_PLAN)


def _execute(work: Path, inputs, destination: LocalDestination, pool: ProcessPoolExecutor | None, workers: int, meter: Meter,
             trace: Trace, progress: Progress | None, plots: list, plotter: Background) -> dict[str, Any]:
    """Run every node of the plan; the results of the nodes that do not fan out, by name."""
    schedule, results = _Schedule(work, workers), {}
    pending: dict[Future, tuple[_Item, ProcessPoolExecutor | None]] = {}
    # Items that can start, best first: urgent nodes (they unblock later ones), then plan order, then the
    # order their node listed them in (Node.order).
    ready: list[tuple[tuple, _Item]] = []
    position, listed = {node.name: k for k, node in enumerate(BAKE_PLAN)}, itertools.count()
    units_done = {stage: 0 for stage in STAGES}

    def finished(it: _Item, figures: dict[str, Any], in_worker: bool) -> None:
        schedule.done.add((it.node.name, it.key))
        meter.account(it.node.unit, it.node.name if it.key is None else f"{it.node.name}:{it.key}", figures, in_worker)
        trace.add(it.node, work, it.item)
        if it.key is None:
            results[it.node.name] = figures["result"]
        units_done[it.node.unit] += 1
        # A node not listed yet counts as one item, so a unit is not reported done while a later node of it waits
        # (the poses stage's textures finish long before its pose caches start).
        total = sum(len(schedule.listed[node.name]) if node.name in schedule.listed else 1 for node in BAKE_PLAN if node.unit == it.node.unit)
        report(progress, it.node.unit, units_done[it.node.unit], total)

    def collect(futures) -> None:
        for future in futures:
            it, own = pending.pop(future)
            if own is not None:
                own.shutdown(wait=True)  # its one process has exited: wait, or its manager thread races the shutdown
            finished(it, future.result(), in_worker=True)

    try:
        while not schedule.all_done():
            collect([future for future in pending if future.done()])  # done while this process ran a node
            for it in schedule.refresh():
                schedule.started.add((it.node.name, it.key))
                ready.append(((not it.node.urgent, position[it.node.name], next(listed)), it))
            ready.sort(key=lambda entry: entry[0])
            # Pool items first, so that workers are busy while this process runs a node of its own.
            for entry in [entry for entry in ready if pool is not None and entry[1].node.placement != HERE]:
                if len(pending) >= workers:
                    break
                ready.remove(entry)
                it = entry[1]
                own = one_shot_pool() if it.node.placement == ALONE else None
                pending[submit_in_background(own or pool, run_node, it.node.name, str(work), it.item, destination)] = (it, own)
                if it.node.fans_out and schedule.node_done("cycle"):
                    plotter.start()  # the report's plots wait for the first fan-out after them: its plan took the GIL first
            here = next((entry for entry in ready if pool is None or entry[1].node.placement == HERE), None)
            if here is not None:
                ready.remove(here)
                it, call = here[1], Call(work, here[1].item, progress, inputs, destination, plots)
                figures = measured(lambda: it.node.run(call))
                trim_heap()
                finished(it, figures, in_worker=False)
                continue
            if not pending:
                raise RuntimeError(f"the bake plan is stuck: {sorted(node.name for node in BAKE_PLAN if not schedule.node_done(node.name))} cannot start")
            collect(wait(pending, return_when=FIRST_COMPLETED)[0])
    except BaseException:
        for future, (_it, own) in pending.items():
            future.cancel()
            if own is not None:
                own.shutdown(wait=True, cancel_futures=True)
        raise
    return results


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
    # The GL contexts that drew the impostor maps (PackRecord.gl_renderers).
    gl_renderers: list[dict[str, Any]] = field(default_factory=list)
    # Set when a texture variation is a JPEG (no alpha, so no colour-region codes): what that means.
    texture_note: str | None = None
    # Set when the bake picked the animation itself (JobRecord.animation_choice): which and why.
    animation_choice: dict[str, Any] | None = None
    timings: dict[str, Any] = field(default_factory=dict)
    # The plan's nodes as they ran, with their keys (crowdbake.stages.plan.Trace).
    nodes: list[dict[str, Any]] = field(default_factory=list)

    @property
    def total_bytes(self) -> int:
        return int(sum(self.files.values()))

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["bundle"] = str(self.bundle)
        data["total_bytes"] = self.total_bytes
        return data


def _mesh_summary(meshes: list[dict], poses) -> list[dict]:
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


def run_bake(inputs, out_root: Path, work: Path | None = None, progress: Progress | None = None,
             workers: int | None = None) -> BakeSummary:
    """Run the bake plan on `inputs` (crowdbake.stages.validate.BakeInputs) and publish to
    out_root/<name>/<version>; returns a BakeSummary.

    work: the work directory (kept, so a rerun resumes); None = a temporary one, removed afterwards (the
    cycle report it would hold is written without its plots).
    workers: worker processes (None = worker_pool.default_workers(); 0 or 1 = every node here). As with
    any multiprocessing start method but "fork", a script that calls this with workers must guard its
    top level with `if __name__ == "__main__":` (the workers import the main module).
    """
    from crowdbake.stages.impostors import impostor_statistics
    from crowdbake.stages.records import CycleRecord, JobRecord, PackRecord, PosesRecord
    from crowdbake.stages.workdir import WorkDir

    temporary = work is None
    work = Path(tempfile.mkdtemp(prefix="crowdbake-work-")) if temporary else Path(work)
    work.mkdir(parents=True, exist_ok=True)
    workers = default_workers() if workers is None else int(workers)
    meter, trace, destination = Meter(), Trace(), LocalDestination(Path(out_root))
    wall, cpu = time.perf_counter(), cpu_seconds()
    pool = start_pool(workers) if workers > 1 else None
    server_cpu = fork_server_cpu_seconds() if pool is not None else 0.0
    # The cycle report's plots (a second or more of matplotlib) are drawn in a thread of this process,
    # which otherwise mostly waits for the workers. In a temporary work folder nobody will see them.
    plots: list = []
    plotter = Background("cycle-plots", plots if not temporary else [], meter.stages["cycle"])
    try:
        try:
            results = _execute(work, inputs, destination, pool, workers if pool else 0, meter, trace, progress, plots, plotter)
            plotter.result()
        except BaseException:
            destination.abort(work)
            raise
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
                server_cpu = fork_server_cpu_seconds() - server_cpu  # its imports, on the first bake of a process
        folder = WorkDir(work)
        job, cycle = folder.load("validate", JobRecord), folder.load("cycle", CycleRecord)
        poses, pack = folder.load("poses", PosesRecord), folder.load("pack", PackRecord)
        impostor = impostor_statistics(work)
    finally:
        if temporary:
            shutil.rmtree(work, ignore_errors=True)
    bundle = Path(results["publish"]["path"])
    timings = {
        "total_s": time.perf_counter() - wall,
        # This process, each worker (whole life: fresh from the fork server) and the fork server's imports.
        "cpu_s": cpu_seconds() - cpu + sum(meter.worker_cpu_s.values()) + server_cpu,
        "render_s": sum(f.render_s for f in meter.stages.values()),
        "renders": sum(f.renders for f in meter.stages.values()),
        "workers": workers if workers > 1 else 1,
        "poses_with_impostors_s": meter.covered("poses", "impostors") if pool is not None else None,
        "peak_rss_mib": {"process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "largest_worker": meter.worker_peak_rss_mib},
        "stages": {stage: asdict(meter.stages[stage]) for stage in STAGES},
        "timeline": sorted(meter.timeline, key=lambda span: span["start_s"]),
    }
    manifest = read_json(bundle / "manifest.json")
    return BakeSummary(
        bundle=bundle,
        name=manifest["name"],
        version=manifest["version"],
        timings_s={stage: meter.stages[stage].wall_s for stage in STAGES},
        files={entry["path"]: entry["size"] for entry in manifest["files"]},
        meshes=_mesh_summary(manifest["meshes"], poses),
        cycle={k: getattr(cycle, k) for k in ("start_frame", "end_frame", "cycle_frames", "closing", "position_jump_ratio", "velocity_jump_ratio", "fps")},
        impostor=asdict(impostor),
        fidelity=dict(pack.fidelity, uv_precision=pack.uv_precision),
        compression=pack.compression,
        texture_memory=pack.texture_memory,
        gl_renderers=pack.gl_renderers,
        texture_note=(job.textures or {}).get("note"),
        animation_choice=job.animation_choice,
        timings=timings,
        nodes=trace.entries,
    )
