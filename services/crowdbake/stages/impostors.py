"""Stage 4, impostors (paper sections 4, 5): normal, UV and detail maps per baked frame and view, fanned
out as independent tasks, one per (baked frame, elevation ring).

Reads the PosesRecord and the pose caches (one frame each, crowdbake.formats.binary.read_pose_frame);
writes work/impostor/parts/<id>.npz and its sidecar <id>.json (ImpostorPartRecord). Fidelity-frame
tasks also render the mesh references the pack stage scores the impostor against.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.bake import fidelity, impostor_maps
from crowdbake.formats.binary import read_pose_frame
from crowdbake.render.impostor import shared_renderer
from crowdbake.stages.records import ImpostorPartRecord, ImpostorStatistics, ImpostorTask, PosesRecord
from crowdbake.stages.workdir import Progress, WorkDir, npz_bytes, read_json, report, stage_key, write_bytes_atomic, write_json_atomic

# Samples per texel side of the fidelity stage's mesh reference (crowdbake.bake.fidelity).
FIDELITY_SUPERSAMPLE = 4
_TASK_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def load_poses(work: Path) -> PosesRecord:
    return WorkDir(work).load("poses", PosesRecord)


def impostor_tasks(work: Path) -> list[ImpostorTask]:
    """The impostor bake split into independent tasks: one per (baked frame, elevation ring).

    "references" marks the fidelity frame's tasks, which also render the mesh references. The order is
    deterministic (frame, then elevation).
    """
    poses = load_poses(work)
    azimuths, elevations = len(poses.layout["azimuths_deg"]), len(poses.layout["elevations_deg"])
    return [
        ImpostorTask(id=f"f{frame:04d}-e{elevation}", frame=int(frame), elevation=elevation,
                     views=[[azimuth, elevation] for azimuth in range(azimuths)], references=frame == poses.fidelity_frame)
        for frame in poses.frame_indices
        for elevation in range(elevations)
    ]


def as_task(task: ImpostorTask | dict) -> ImpostorTask:
    """A task from its record or from the JSON spec a Celery part carries."""
    return task if isinstance(task, ImpostorTask) else ImpostorTask.from_json(dict(task))


def part_path(work: Path, task: ImpostorTask | dict) -> Path:
    task_id = str(task.id if isinstance(task, ImpostorTask) else task.get("id", ""))
    if not _TASK_ID.match(task_id):
        raise ValueError(f"impostor task id {task_id!r} is not a plain name")
    return WorkDir(work).part_path(task_id)


@dataclass
class Scene:
    """The high LOD of every part at one frame, concatenated, with its materials' textures."""

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray
    triangle_material: np.ndarray
    diffuse: list[np.ndarray]  # variation 0 per material, as given (detail maps)
    diffuse_runtime: list[np.ndarray]  # variation 0 per material, as the runtime samples it (after compression)
    outfit_row: np.ndarray


def load_scene(work: Path, poses: PosesRecord, frame: int) -> Scene:
    work = Path(work)
    positions, normals, uvs, faces, materials = [], [], [], [], []
    offset = 0
    for part in poses.parts:
        if part.lod != 0:
            continue
        indices, part_uvs, part_positions, part_normals = read_pose_frame(work / "poses" / part.file, frame)
        positions.append(part_positions)
        normals.append(part_normals)
        uvs.append(part_uvs)
        faces.append(indices.astype(np.int64) + offset)
        materials.append(np.full(len(indices), part.material, dtype=np.int64))
        offset += len(part_uvs)
    with np.load(work / "poses" / "textures.npz") as textures:
        count = len(poses.materials)
        diffuse = [textures[f"material_{m}_v0"] for m in range(count)]
        runtime = [textures[f"material_{m}_decoded_v0"] for m in range(count)]
        outfit_row = textures["outfits"][0]
    return Scene(
        np.concatenate(positions).astype(np.float64),
        np.concatenate(normals).astype(np.float64),
        np.concatenate(uvs).astype(np.float64),
        np.concatenate(faces),
        np.concatenate(materials),
        diffuse,
        runtime,
        outfit_row,
    )


def midpoint_azimuths(azimuths: list[float]) -> list[float]:
    """The azimuth halfway to the next baked one, per baked azimuth (wrapping at 360°)."""
    if len(azimuths) == 1:
        return [(azimuths[0] + 180.0) % 360.0]
    following = azimuths[1:] + [azimuths[0] + 360.0]
    return [((a + b) / 2.0) % 360.0 for a, b in zip(azimuths, following)]


def _render_maps(scene: Scene, poses: PosesRecord, views: list[tuple[int, int]], timings: dict) -> tuple[dict, int]:
    layout = poses.layout
    tile = int(layout["tile_size"])
    normal, uv, detail, repaired = [], [], [], 0
    renderer = shared_renderer(tile)
    renderer.set_mesh(scene.positions, scene.faces)
    for a, e in views:
        view = impostor_maps.ortho_view(poses.center, poses.radius, layout["azimuths_deg"][a], layout["elevations_deg"][e], tile)
        clock = time.perf_counter()
        image = renderer.render(view)
        timings["render"] += time.perf_counter() - clock
        clock = time.perf_counter()
        coverage = impostor_maps.resolve_coverage(view, image.ids, scene.positions, scene.faces, image.depth)
        maps = impostor_maps.view_maps(
            view, coverage, scene.positions, scene.normals, scene.uvs, scene.faces, scene.triangle_material, scene.diffuse
        )
        timings["maps"] += time.perf_counter() - clock
        repaired += coverage.repaired
        normal.append(maps.normal)
        uv.append(maps.uv)
        detail.append(maps.detail)
    arrays = {
        "views": np.asarray(views, dtype=np.int64).reshape(-1, 2),
        "normal": np.stack(normal),
        "uv": np.stack(uv),
        "detail": np.stack(detail),
    }
    return arrays, repaired


def _render_references(scene: Scene, poses: PosesRecord, views: list[tuple[int, int]]) -> dict[str, np.ndarray]:
    """Per view, the mesh at the view's angle and at the angle halfway to the next azimuth, lit as the
    runtime lights the impostor (crowdbake.bake.fidelity.mesh_reference), FIDELITY_SUPERSAMPLE² samples a texel."""
    layout = poses.layout
    size = int(layout["tile_size"]) * FIDELITY_SUPERSAMPLE
    midpoints = midpoint_azimuths(list(layout["azimuths_deg"]))
    references, between = [], []
    renderer = shared_renderer(size)
    renderer.set_mesh(scene.positions, scene.faces)
    for a, e in views:
        for azimuth, store in ((layout["azimuths_deg"][a], references), (midpoints[a], between)):
            view = impostor_maps.ortho_view(poses.center, poses.radius, azimuth, layout["elevations_deg"][e], size)
            coverage = renderer.coverage(view, scene.positions, scene.faces)
            store.append(
                fidelity.mesh_reference(
                    view, coverage, FIDELITY_SUPERSAMPLE, scene.positions, scene.normals, scene.uvs, scene.faces,
                    scene.triangle_material, scene.diffuse_runtime, scene.outfit_row, fidelity.camera_light(view),
                ).astype(np.float32)
            )
    return {
        "reference": np.stack(references),
        "reference_between": np.stack(between),
        "between_azimuths": np.asarray([midpoints[a] for a, _ in views], dtype=np.float64),
    }


def stage_impostor_views(work: Path, task: ImpostorTask | dict) -> Path:
    """Render one task's views (normal, UV and detail maps) into work/impostor/parts/<id>.npz.

    Returns the .npz path. Idempotent: a part written for the same poses and task is kept.
    """
    work = Path(work)
    task = as_task(task)
    path = part_path(work, task)
    key = stage_key("impostor-part", WorkDir(work).key_of("poses"), task.to_json())
    stats_path = path.with_suffix(".json")
    if path.is_file() and stats_path.is_file():
        try:
            if read_json(stats_path).get("key") == key:
                return path
        except (OSError, ValueError):
            pass
    poses = load_poses(work)
    if task.frame not in poses.frame_indices:
        raise ValueError(f"impostor task frame {task.frame} is not one of the baked frames {poses.frame_indices}")
    scene = load_scene(work, poses, task.frame)
    views = [(int(a), int(e)) for a, e in task.views]
    timings = {"render": 0.0, "maps": 0.0, "references": 0.0}
    arrays, repaired = _render_maps(scene, poses, views, timings)
    if task.references:
        clock = time.perf_counter()
        arrays.update(_render_references(scene, poses, views))
        timings["references"] = time.perf_counter() - clock
    write_bytes_atomic(path, npz_bytes(arrays))
    write_json_atomic(stats_path, ImpostorPartRecord(key=key, views=len(views), repaired_texels=repaired, seconds=timings).to_json())
    return path


def stage_impostors(work: Path, progress: Progress | None = None) -> ImpostorStatistics:
    """Every impostor task in this process, in order (what the CLI does; the service fans them out)."""
    tasks = impostor_tasks(work)
    for done, task in enumerate(tasks):
        report(progress, "impostors", done, len(tasks))
        stage_impostor_views(work, task)
    report(progress, "impostors", len(tasks), len(tasks))
    return impostor_statistics(work)


def part_record(work: Path, task: ImpostorTask) -> ImpostorPartRecord | None:
    """The sidecar of a written part, or None."""
    stats_path = part_path(work, task).with_suffix(".json")
    return ImpostorPartRecord.from_json(read_json(stats_path)) if stats_path.is_file() else None


def impostor_statistics(work: Path) -> ImpostorStatistics:
    """Views, renders and seconds summed over the written impostor parts (from their sidecars)."""
    totals = ImpostorStatistics()
    for task in impostor_tasks(work):
        stats = part_record(work, task)
        if stats is None:
            continue
        totals.tasks += 1
        totals.views += int(stats.views)
        totals.repaired_texels += int(stats.repaired_texels)
        totals.render_seconds += float(stats.seconds["render"])
        totals.maps_seconds += float(stats.seconds["maps"])
        totals.reference_seconds += float(stats.seconds["references"])
    return totals
