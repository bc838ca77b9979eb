"""The bake as one plan: its nodes (stage functions), what each needs and writes, and its fan-outs.

    validate ─┬─ textures ──────────────────────────────────┐
              └─ clip_loop × clips ─ cycle ─┬─ pose_caches ─┴───────────────────────────────────────────────────────────────────────┬─ poses ─ references ─────────── scores ─┬─ pack ─┬─ publish ─┬─ commit_export
                                            └─ impostor_scene ─ impostor_probe × probes ─ impostor_check × options ─ impostor_plan ─┤                                         │        └─ export ──┘
                                                                                                                                    └─ impostor_views × tasks ─ pack_frame × frames ─┘

Two executors run this plan and neither writes an order of its own:
- crowdbake.stages.runner (`crowdbake bake`, one machine) starts every node as soon as what it needs is
  done, in this process or in a pool of worker processes (Node.placement), a fan-out item as soon as the
  items it needs are done (Node.item_needs);
- crowdbake.jobs.tasks (the service) runs each `unit` as a Celery task, its nodes in plan order, and a
  fan-out node's items as parallel tasks; what travels between machines is what the nodes write.

Every node is idempotent: it keeps outputs written from the same inputs (a key in its stamp or sidecar),
so a rerun or a redelivered task returns at once. Node.key reads that key: two executors that ran the
same nodes with the same keys made the same records.

This module stays light (the stage modules are imported when a node runs): the service's task module and
the API read it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

from crowdbake.stage_names import FAN_OUT_STAGES, STAGES

# Where the local runner runs a node: in the runner's own process (short, or it must: the validate
# stage reads the caller's inputs), in a worker of the pool, or in a fresh process of its own (an item
# whose peak memory should add to no worker's leftovers).
HERE, POOL, ALONE = "here", "pool", "alone"


class Destination(Protocol):
    """Where a bake publishes: a bundles folder (the runner) or the service's stores (the tasks)."""

    def publish(self, work: Path) -> dict[str, Any]:
        """Publish work/bundle once; what was published (name, version, path or digest)."""

    def export(self, work: Path) -> Any:
        """Build, or publish, the engine export of work/bundle (nothing when the bake makes none)."""

    def commit_export(self, work: Path) -> Any:
        """Put a built export in place once the bundle is published (nothing where export published it)."""


@dataclass
class Call:
    """What a node gets: the bake's work folder, its item (a fan-out node's, as JSON), and what only an
    executor can bring: the progress callback, the validate node's inputs, the publish nodes'
    destination, and a list the cycle node leaves its report's plotting in (None: it draws them itself)."""

    work: Path
    item: Any = None
    progress: Callable[[str, int, int], None] | None = None
    inputs: Any = None
    destination: Destination | None = None
    plots: list | None = None


@dataclass(frozen=True)
class Node:
    """One step of the bake. needs: the nodes whose every item must be done first; reads: earlier nodes
    whose records it reads besides (no order of their own: they come before what it needs). unit: the stage it
    belongs to (STAGES: its progress, its timings, the service task that runs it). writes: the paths
    under the work folder it writes (a fan-out node: per item, see item_writes). items: a fan-out node's
    items (JSON values) from the work folder; item_key names one. item_needs: the (node, item key or
    None for every item) one item needs, where finer than `needs`. urgent: the local runner starts it
    ahead of the items already waiting (it unblocks later nodes)."""

    name: str
    unit: str
    run: Callable[[Call], Any]
    key: Callable[[Path, Any], str | None]
    needs: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()
    items: Callable[[Path], list] | None = None
    item_key: Callable[[Any], str] = str
    item_needs: Callable[[Path, Any], list[tuple[str, str | None]]] | None = None
    item_writes: Callable[[Any], tuple[str, ...]] | None = None
    order: Callable[[list, int], list] | None = None
    placement: str = POOL
    urgent: bool = False

    @property
    def fans_out(self) -> bool:
        return self.items is not None


# ------------------------------------------------------------------------------------------- keys


def _stamp_key(folder: str) -> Callable[[Path, Any], str | None]:
    """The key in work/<folder>/stage.json (crowdbake.stages.workdir.WorkDir.save)."""

    def key(work: Path, _item: Any) -> str | None:
        return _json_key(Path(work) / folder / "stage.json")

    return key


def _json_key(path: Path) -> str | None:
    from crowdbake.stages.workdir import read_json

    try:
        return read_json(path).get("key")
    except (OSError, ValueError, AttributeError):
        return None


def _file_digest(relative: str) -> Callable[[Path, Any], str | None]:
    def key(work: Path, _item: Any) -> str | None:
        from crowdbake.files import sha256_file

        path = Path(work) / relative
        return sha256_file(path) if path.is_file() else None

    return key


def _references_key(work: Path, _item: Any) -> str | None:
    import numpy as np

    from crowdbake.stages.runtime_fidelity import REFERENCES_FILE

    path = Path(work) / "pack" / REFERENCES_FILE
    if not path.is_file():
        return None
    with np.load(path) as data:
        return str(data["key"])


def _part_key(work: Path, item: dict) -> str | None:
    return _json_key(Path(work) / "impostor" / "parts" / f"{item['id']}.json")


def _frame_key(work: Path, frame: int) -> str | None:
    from crowdbake.stages.pack import frame_path

    return _json_key(frame_path(work, frame).with_suffix(".json"))


def _scores_key(work: Path, _item: Any) -> str | None:
    return _json_key(Path(work) / "pack" / "scores.json")


def _no_key(_work: Path, _item: Any) -> None:
    return None


# ------------------------------------------------------------------------------------------- nodes


def _validate(call: Call) -> dict:
    from crowdbake.stages.validate import stage_validate

    if call.inputs is None:
        raise ValueError("the validate node needs the bake's inputs (Call.inputs)")
    return stage_validate(call.inputs, call.work).to_json()


def _textures(call: Call) -> dict:
    from crowdbake.stages.poses import stage_textures

    return stage_textures(call.work).to_json()


def _clip_loop(call: Call) -> str:
    from crowdbake.stages.loops import stage_clip_loop

    return str(stage_clip_loop(call.work, call.item))


def _loop_items(work: Path) -> list[dict]:
    from crowdbake.stages.loops import loop_items

    return loop_items(work)


def _loop_key(work: Path, item: dict) -> str | None:
    from crowdbake.stages.loops import item_files

    return _json_key(Path(work) / item_files(item)[1])


def _loop_writes(item: dict) -> tuple[str, ...]:
    from crowdbake.stages.loops import item_files

    return item_files(item)


def _cycle(call: Call) -> dict:
    from crowdbake.stages.cycle import stage_cycle

    return stage_cycle(call.work, call.progress, plots=call.plots).to_json()


def _impostor_scene(call: Call) -> dict:
    from crowdbake.stages.impostor_plan import stage_impostor_scene

    return stage_impostor_scene(call.work, call.progress).to_json()


def _impostor_probe(call: Call) -> str:
    from crowdbake.stages.impostor_plan import stage_impostor_probe

    return str(stage_impostor_probe(call.work, call.item)["key"])


def _probe_writes(item: dict) -> tuple[str, ...]:
    from crowdbake.stages.impostor_plan import probe_path

    return (probe_path(Path(), item).as_posix(),)


def _probe_items(work: Path) -> list[dict]:
    from crowdbake.stages.impostor_plan import probe_items

    return probe_items(work)


def _probe_key(work: Path, item: dict) -> str | None:
    from crowdbake.stages.impostor_plan import probe_path

    return _json_key(probe_path(work, item))


def _impostor_check(call: Call) -> float:
    from crowdbake.stages.impostor_plan import stage_impostor_check

    return float(stage_impostor_check(call.work, call.item)["ssim"])


def _check_items(work: Path) -> list[dict]:
    from crowdbake.stages.impostor_plan import check_items

    return check_items(work)


def _impostor_plan(call: Call) -> dict:
    from crowdbake.stages.impostor_plan import stage_impostor_plan

    return stage_impostor_plan(call.work, call.progress).to_json()


def _pose_caches(call: Call) -> dict:
    from crowdbake.stages.poses import stage_pose_caches

    return stage_pose_caches(call.work, call.progress).to_json()


def _poses(call: Call) -> dict:
    from crowdbake.stages.poses import stage_poses

    return stage_poses(call.work, call.progress).to_json()


def _references(call: Call) -> int:
    from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, load_poses
    from crowdbake.stages.runtime_fidelity import between_references

    return len(between_references(call.work, load_poses(call.work), FIDELITY_SUPERSAMPLE))


def _impostor_views(call: Call) -> str:
    from crowdbake.stages.impostors import stage_impostor_views

    return str(stage_impostor_views(call.work, call.item))


def _impostor_items(work: Path) -> list[dict]:
    from crowdbake.stages.impostors import impostor_tasks

    return [task.to_json() for task in impostor_tasks(work)]


def task_order(tasks: list, workers: int) -> list:
    """The order the local runner hands out impostor tasks (ImpostorTask or their JSON) in. Fidelity-frame
    tasks (with their mesh references) take several times an ordinary one: they go first. The rest go
    frame by frame, so that each frame's atlases can be packed while later frames render, except the last
    `workers` frames, whose tasks alternate: those frames then finish together and their packs run side
    by side at the end instead of one after another on one core."""
    from itertools import zip_longest

    def field_of(task, name):
        return task[name] if isinstance(task, dict) else getattr(task, name)

    plain = [task for task in tasks if not field_of(task, "references")]
    frames = list(dict.fromkeys(field_of(task, "frame") for task in plain))
    tail = set(frames[-workers:]) if workers > 1 else set()
    by_frame = [[task for task in plain if field_of(task, "frame") == frame] for frame in frames if frame in tail]
    interleaved = [task for ring in zip_longest(*by_frame) for task in ring if task is not None]
    return ([task for task in tasks if field_of(task, "references")]
            + [task for task in plain if field_of(task, "frame") not in tail] + interleaved)


def _pack_frame(call: Call) -> str:
    from crowdbake.stages.pack import stage_pack_frame

    return str(stage_pack_frame(call.work, int(call.item)))


def _frames(work: Path) -> list[int]:
    from crowdbake.stages.impostors import load_plan

    return [int(frame) for frame in load_plan(work).frame_indices]


def _frame_needs(work: Path, frame: int) -> list[tuple[str, str | None]]:
    """A frame's atlases need that frame's impostor tasks only."""
    return [("impostor_views", task["id"]) for task in _impostor_items(work) if task["frame"] == int(frame)]


def _scores(call: Call) -> str:
    from crowdbake.stages.pack import stage_pack_scores

    return str(stage_pack_scores(call.work))


def _scores_needs(work: Path, _item: Any) -> list[tuple[str, str | None]]:
    """The scores read the mesh references and the two frames they score (pack.score_frames)."""
    from crowdbake.stages.impostors import load_plan
    from crowdbake.stages.pack import score_frames

    return [("references", None)] + [("pack_frame", str(frame)) for frame in score_frames(load_plan(work))]


def _pack(call: Call) -> dict:
    from crowdbake.stages.pack import stage_pack

    return stage_pack(call.work, call.progress).to_json()


def _publish(call: Call) -> dict:
    return call.destination.publish(call.work)


def _export(call: Call) -> Any:
    return call.destination.export(call.work)


def _commit_export(call: Call) -> Any:
    return call.destination.commit_export(call.work)


IMPOSTOR_SCENE_FILES = ("impostor-probes/record.json", "impostor-probes/stage.json", "impostor-probes/scene.npz")
IMPOSTOR_PLAN_FILES = ("impostor/record.json", "impostor/stage.json", "impostor/scene.npz")

BAKE_PLAN: tuple[Node, ...] = (
    Node("validate", "validate", _validate, _stamp_key("validate"), writes=("validate", "inputs"), placement=HERE),
    # A loop per clip of a timeline, side by side (none for one clip: the cycle node searches it); the
    # cycle node joins them (the transitions need both loops of a change) and writes the report.
    Node("clip_loop", "loops", _clip_loop, _loop_key, needs=("validate",), items=_loop_items, item_key=lambda item: str(item["id"]),
         item_writes=_loop_writes),
    Node("cycle", "cycle", _cycle, _stamp_key("cycle"), needs=("validate", "clip_loop"), writes=("cycle",), placement=HERE),
    # The impostor plan in four, beside the pose caches (the poses record joins them): its scene (every
    # pose frame's high LOD), its probes drawn side by side (the layout's and one per clip and transition;
    # none by the rule: the probes stage is then skipped), one clip's end-to-end checks, the choice.
    Node("impostor_scene", "cycle", _impostor_scene, _stamp_key("impostor-probes"), needs=("cycle",), writes=IMPOSTOR_SCENE_FILES),
    Node("impostor_probe", "probes", _impostor_probe, _probe_key, needs=("impostor_scene",), reads=("validate",), items=_probe_items,
         item_key=lambda item: str(item["id"]), item_writes=_probe_writes, urgent=True),
    Node("textures", "poses", _textures, _stamp_key("textures"), needs=("validate",), writes=("textures", "poses")),
    # One clip: the options the probes shortlist, each measured end to end, side by side (none otherwise).
    Node("impostor_check", "poses", _impostor_check, _probe_key, needs=("impostor_probe",), reads=("validate", "impostor_scene"),
         items=_check_items, item_key=lambda item: str(item["id"]), item_writes=_probe_writes, urgent=True),
    Node("impostor_plan", "poses", _impostor_plan, _stamp_key("impostor"), needs=("impostor_probe", "impostor_check"),
         reads=("impostor_scene",), writes=IMPOSTOR_PLAN_FILES),
    Node("pose_caches", "poses", _pose_caches, _stamp_key("pose-caches"), needs=("cycle", "textures"), writes=("poses", "pose-caches")),
    Node("poses", "poses", _poses, _stamp_key("poses"), needs=("pose_caches", "impostor_plan"), writes=("poses",), placement=HERE),
    Node("impostor_views", "impostors", _impostor_views, _part_key, needs=("impostor_plan",), items=_impostor_items,
         item_key=lambda task: str(task["id"]), order=task_order,
         item_writes=lambda task: (f"impostor/parts/{task['id']}.npz", f"impostor/parts/{task['id']}.json")),
    Node("references", "pack", _references, _references_key, needs=("poses",), writes=("pack",), urgent=True),
    Node("pack_frame", "pack", _pack_frame, _frame_key, needs=("impostor_views",), reads=("validate",), writes=("pack",),
         items=_frames, item_needs=_frame_needs, urgent=True),
    # The scores hold the fidelity frame's references and decoded atlases: in a process of their own.
    Node("scores", "pack", _scores, _scores_key, needs=("references", "pack_frame"), reads=("validate",), writes=("pack",),
         item_needs=_scores_needs, placement=ALONE, urgent=True),
    Node("pack", "pack", _pack, _stamp_key("pack"), needs=("poses", "pack_frame", "scores"), reads=("validate", "cycle"),
         writes=("pack", "bundle")),
    Node("publish", "publish", _publish, _file_digest("bundle/manifest.json"), needs=("pack",)),
    # The export holds the bundle's layers decoded and its zip's input at once: in a process of its own.
    Node("export", "publish", _export, _no_key, needs=("pack",), placement=ALONE),
    Node("commit_export", "publish", _commit_export, _no_key, needs=("publish", "export"), placement=HERE),
)

NODES: dict[str, Node] = {node.name: node for node in BAKE_PLAN}

# The modules the nodes run (imported when a node first runs, so that this module stays light): what a
# process that runs nodes may import ahead (crowdbake.stages.worker_pool preloads them in its fork server).
STAGE_MODULES = (
    "crowdbake.stages.validate", "crowdbake.stages.loops", "crowdbake.stages.cycle", "crowdbake.stages.poses", "crowdbake.stages.impostors",
    "crowdbake.stages.impostor_plan",
    "crowdbake.stages.runtime_fidelity", "crowdbake.stages.pack", "crowdbake.stages.publish", "crowdbake.storage.exports",
)


def nodes_of(unit: str) -> list[Node]:
    """The nodes a unit (a STAGES entry: a service task) runs, in plan order."""
    return [node for node in BAKE_PLAN if node.unit == unit]


def fan_out_of(unit: str) -> Node | None:
    """The unit's fan-out node, if it is one (the service runs its items as parallel tasks)."""
    return next((node for node in nodes_of(unit) if node.fans_out), None)


def unit_writes(unit: str) -> tuple[str, ...]:
    """What a unit's nodes write under the work folder, without repeats (a fan-out's items: item_writes)."""
    return tuple(dict.fromkeys(path for node in nodes_of(unit) for path in node.writes))


def unit_reads(unit: str) -> tuple[str, ...]:
    """The earlier units whose outputs a unit's nodes need or read (what a machine fetches before running
    it), in STAGES order."""
    wanted = {NODES[other].unit for node in nodes_of(unit) for other in (*node.needs, *node.reads)} - {unit}
    return tuple(stage for stage in STAGES if stage in wanted)


def runs_in_parallel(unit: str) -> bool:
    """True for a unit that is one fan-out node alone: the service runs its items as parallel tasks. A
    fan-out that shares its unit with other nodes runs its items one after another in that unit's task."""
    nodes = nodes_of(unit)
    return len(nodes) == 1 and nodes[0].fans_out


def plan_problems(plan: tuple[Node, ...] = BAKE_PLAN) -> list[str]:
    """What makes a plan unrunnable by both executors: a need or read that is not an earlier node (the
    service runs units and their nodes in plan order), an item need on an unknown node, a unit out of
    STAGES or out of order, or fan-out units other than crowdbake.stage_names.FAN_OUT_STAGES (which the
    database layer reads). Empty for a good plan."""
    problems, seen = [], set()
    position = {stage: k for k, stage in enumerate(STAGES)}
    for node in plan:
        if node.unit not in position:
            problems.append(f"{node.name}: unit {node.unit!r} is not a stage")
        for need in (*node.needs, *node.reads):
            if need not in seen:
                problems.append(f"{node.name} needs {need!r}, which is not an earlier node")
        seen.add(node.name)
    units = [position[node.unit] for node in plan if node.unit in position]
    if units != sorted(units):
        problems.append("the nodes' units are not in STAGES order")
    alone = tuple(stage for stage in STAGES if [node.fans_out for node in plan if node.unit == stage] == [True])
    if alone != FAN_OUT_STAGES:
        problems.append(f"the units that are one fan-out node alone are {alone}, FAN_OUT_STAGES says {FAN_OUT_STAGES}")
    return problems


@dataclass
class Trace:
    """The nodes an executor ran, with each one's key (Node.key): two executors of one bake that ran the
    same nodes with the same keys made the same records."""

    entries: list[dict[str, Any]] = field(default_factory=list)

    def add(self, node: Node, work: Path, item: Any = None) -> dict[str, Any]:
        entry = {"node": node.name, "item": None if item is None else node.item_key(item), "key": node.key(Path(work), item)}
        self.entries.append(entry)
        return entry
