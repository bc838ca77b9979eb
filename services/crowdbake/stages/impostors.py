"""Stage 4, impostors (paper sections 4, 5): normal, UV, detail and surface maps per baked frame and view,
fanned out as independent tasks, one per (baked frame, elevation ring).

One view from render to stored part reads in three files:

1. here, stage_impostor_views: the task's scene at its baked frame (task_scene), then render_task, whose
   draw_task makes the cameras and runs the GL passes;
2. crowdbake.render.impostor.BakeRenderer (shader_maps, shader_references): the GL context that runs
3. crowdbake.render.map_shader, whose shaders (GLSL in the same file) draw every view's maps,
   already encoded, in one pass, and the mesh's share of each texel in another;
then, back here, finish_task resolves the maps (extend_to_partial_texels, fill_background, the surface
map's alpha) into the arrays stage_impostor_views writes as work/impostor/parts/<id>.npz, with its sidecar
<id>.json (ImpostorPartRecord). The pack stage (crowdbake.stages.pack) lays the parts into atlases and
compresses them.

The impostor plan (crowdbake.stages.impostor_plan) runs on the cycle's output alone: the framing, the
baked frames and, in work/impostor/scene.npz, the high LOD at those frames and the textures the tasks
draw with (scene_arrays). The poses stage takes its framing from the plan and runs beside the tasks.
Fidelity-frame tasks also draw the mesh references the pack stage scores the impostor against, shaded
per sample by the map shader's reference pass.
"""
from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.bake import impostor_views, pose_ranges, surface_maps
from crowdbake.formats import pose_codec
from crowdbake.formats.skinned_cache import read_any_pose_frame
from crowdbake.render.impostor import shared_renderer
from crowdbake.render.map_shader import ShaderMaps
from crowdbake.stages.records import ImpostorPartRecord, ImpostorPlan, ImpostorStatistics, ImpostorTask, PosesRecord
from crowdbake.stages.workdir import (
    WorkDir, npz_bytes, read_json, stage_key, write_bytes_atomic, write_json_atomic,
)

# Samples per texel side of the fidelity stage's mesh reference (crowdbake.bake.fidelity): 3² = 9. 4²
# samples scored the sample's impostor within 0.003 SSIM of 3² (docs/bake.md, "Speed") for 16/9 the
# shading work.
FIDELITY_SUPERSAMPLE = 3
SCENE_FILE = "scene.npz"
# The maps a part holds; part of its key, so parts written before a map was added are rendered again.
PART_MAPS = ("normal", "uv", "detail", "surface")
# What draws the maps and the references, part of a part's key too: parts that numpy resolved from
# triangle-id renders, drawn before the surface map held coverage or before the normal map held each
# texel's footprint normal, are drawn again.
MAP_MAKER = "map_shader-3-footprints"
# Azimuth gaps the fidelity scores render the mesh in, halfway between two baked azimuths (each at every
# elevation): each is a render at FIDELITY_SUPERSAMPLE x the tile and its shading, so a bake with more
# azimuths scores this many gaps spread evenly round the ring (spread_gaps), 16 x 3 cameras of a 32-azimuth
# bake instead of 96. Part of a part's key, with the sampling it implies.
BETWEEN_AZIMUTHS = 16
# What the surface maps' motion is (crowdbake.bake.surface_maps.motion_positions), in the parts' key.
SURFACE_MOTION = "central-velocity"
# Coverage below this share of a texel stores as alpha 0 (SPEC.md: 4-bit alpha rounds it away).
MIN_COVERAGE = 1.0 / 30.0
_TASK_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def load_poses(work: Path) -> PosesRecord:
    return WorkDir(work).load("poses", PosesRecord)


def load_plan(work: Path) -> ImpostorPlan:
    return WorkDir(work).load("impostor", ImpostorPlan)


def scene_arrays(high: dict, part_material: dict[str, int], frame_indices: list[int]) -> dict[str, np.ndarray]:
    """The high LOD of every part concatenated (as load_scene reads it): faces (T, 3) int64, uvs (V, 2)
    float32, triangle_material (T,) int64, and per baked frame f positions_f, normals_f (V, 3) float32, as
    the pose caches store them (quantized, or a skinned body's skinned frames: the impostors show what the
    meshes show)."""
    faces, uvs, materials, offset = [], [], [], 0
    for name, part in high.items():
        faces.append(np.asarray(part.faces, dtype=np.int64) + offset)
        uvs.append(np.asarray(part.uvs, dtype=np.float32))
        materials.append(np.full(len(part.faces), part_material[name], dtype=np.int64))
        offset += len(part.uvs)
    arrays = {"faces": np.concatenate(faces), "uvs": np.concatenate(uvs), "triangle_material": np.concatenate(materials)}
    for frame in frame_indices:
        # A skinned body's frames are stored as matrices, skinned exactly so by the caches' readers.
        stored = [(part.positions[frame:frame + 1], part.normals[frame:frame + 1]) if part.skin is not None else
                  pose_codec.stored_frames(part.positions[frame:frame + 1], part.normals[frame:frame + 1]) for part in high.values()]
        arrays[f"positions_{frame}"] = np.concatenate([positions[0] for positions, _ in stored])
        arrays[f"normals_{frame}"] = np.concatenate([normals[0] for _, normals in stored])
    return arrays


def previous_baked_frame(record: ImpostorPlan | PosesRecord, frame: int) -> int:
    """The baked frame before `frame`, as next_baked_frame the other way (crowdbake.bake.surface_maps)."""
    ranges = record.bundle_ranges()
    if ranges is None:
        return surface_maps.previous_baked_frame(frame, record.frame_indices)
    return surface_maps.previous_baked_frame_in_range(ranges, frame, record.frame_indices)


def next_baked_frame(record: ImpostorPlan | PosesRecord, frame: int) -> int:
    """The baked frame the surface map's motion at `frame` leads to: the next around the cycle, or with
    several clips the next in the same range (crowdbake.bake.pose_ranges.next_baked_frame: a transition's
    last leads to itself, zero motion)."""
    ranges = record.bundle_ranges()
    if ranges is None:
        return surface_maps.next_baked_frame(frame, record.frame_indices)
    return pose_ranges.next_baked_frame(ranges, frame, record.frame_indices)


def impostor_tasks(work: Path) -> list[ImpostorTask]:
    """The impostor bake split into independent tasks: one per (baked frame, elevation ring).

    "references" marks the fidelity frame's tasks, which also render the mesh references. The order is
    deterministic (frame, then elevation). Needs the impostor plan only.
    """
    plan = load_plan(work)
    azimuths, elevations = len(plan.layout["azimuths_deg"]), len(plan.layout["elevations_deg"])
    return [
        ImpostorTask(id=f"f{frame:04d}-e{elevation}", frame=int(frame), elevation=elevation,
                     views=[[azimuth, elevation] for azimuth in range(azimuths)], references=frame == plan.fidelity_frame)
        for frame in plan.frame_indices
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
    diffuse_runtime: list[np.ndarray]  # variation 0 per material, as the runtime samples it (after compression); [] unless asked
    outfit_row: np.ndarray


def load_scene(work: Path, plan: ImpostorPlan, frame: int, runtime_textures: bool = True) -> Scene:
    """One baked frame of the plan's scene (float64 geometry); runtime_textures: also the decoded diffuse."""
    with np.load(Path(work) / "impostor" / SCENE_FILE) as data:
        count = plan.material_count
        return Scene(
            data[f"positions_{frame}"].astype(np.float64),
            data[f"normals_{frame}"].astype(np.float64),
            data["uvs"].astype(np.float64),
            data["faces"],
            data["triangle_material"],
            [data[f"diffuse_{m}"] for m in range(count)],
            [data[f"runtime_{m}"] for m in range(count)] if runtime_textures else [],
            data["outfit_row"],
        )


def load_pose_scene(work: Path, poses: PosesRecord, frame: int) -> Scene:
    """The scene at any cycle frame from the poses stage's caches (the plan holds the baked frames only)."""
    work = Path(work)
    positions, normals, uvs, faces, materials = [], [], [], [], []
    offset = 0
    for part in poses.parts:
        if part.lod != 0:
            continue
        indices, part_uvs, part_positions, part_normals = read_any_pose_frame(work / "poses" / part.file, frame)
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
        np.concatenate(positions).astype(np.float64), np.concatenate(normals).astype(np.float64),
        np.concatenate(uvs).astype(np.float64), np.concatenate(faces), np.concatenate(materials), diffuse, runtime, outfit_row,
    )


def stage_impostor_views(work: Path, task: ImpostorTask | dict) -> Path:
    """Render one task's views (normal, UV, detail and surface maps) into work/impostor/parts/<id>.npz.

    Returns the .npz path. Idempotent: a part written for the same plan and task is kept. Needs the
    impostor plan, not the poses stage.
    """
    work = Path(work)
    task = as_task(task)
    path = part_path(work, task)
    key = stage_key("impostor-part", PART_MAPS, MAP_MAKER, SURFACE_MOTION, BETWEEN_AZIMUTHS, WorkDir(work).key_of("impostor"), task.to_json())
    stats_path = path.with_suffix(".json")
    if path.is_file() and stats_path.is_file():
        try:
            if read_json(stats_path).get("key") == key:
                return path
        except (OSError, ValueError):
            pass
    plan = load_plan(work)
    if task.frame not in plan.frame_indices:
        raise ValueError(f"impostor task frame {task.frame} is not one of the baked frames {plan.frame_indices}")
    scene, next_positions = task_scene(work, plan, task)
    timings = {"render": 0.0, "maps": 0.0, "references": 0.0}
    arrays = render_task(scene, plan, task, timings, next_positions)
    write_bytes_atomic(path, npz_bytes(arrays))
    gl = shared_renderer(int(plan.layout["tile_size"])).gl.to_json()
    write_json_atomic(stats_path, ImpostorPartRecord(key=key, views=len(task.views), seconds=timings, gl=gl).to_json())
    return path


def task_scene(work: Path, plan: ImpostorPlan, task: ImpostorTask) -> tuple[Scene, np.ndarray]:
    """What render_task draws for `task`: the scene at its frame and its vertices moved by their velocity
    there (crowdbake.bake.surface_maps.motion_positions), from work/impostor alone."""
    scene = load_scene(work, plan, task.frame, runtime_textures=task.references)
    with np.load(Path(work) / "impostor" / SCENE_FILE) as data:
        sides = surface_maps.motion_sides(task.frame, previous_baked_frame(plan, task.frame), next_baked_frame(plan, task.frame))
        previous, following = (None if side is None else data[f"positions_{side}"].astype(np.float64) for side in sides)
        return scene, surface_maps.motion_positions(data[f"positions_{task.frame}"], previous, following)


def render_task(scene: Scene, plan: ImpostorPlan, task: ImpostorTask, timings: dict[str, float],
                next_positions: np.ndarray | None = None, footprints: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """A task's maps (and, for the fidelity frame, references): the arrays of its part. draw_task's GL
    passes, then finish_task's texels on the CPU; next_positions, footprints and timings as draw_task."""
    return finish_task(draw_task(scene, plan, task, timings, next_positions, footprints), timings)


@dataclass
class DrawnTask:
    """What a task's GL passes drew (draw_task), before finish_task: views (V, 2) (azimuth, elevation)
    indices; maps as the shader wrote them; footprints (V, S, S, 4) float32 (mesh_footprints: the mean
    shading normal over each texel's samples, the mesh's share of it in alpha); references (V + B, S, S, 3)
    float32 for the fidelity frame (the baked views, then the B cameras between them), else None;
    between: those cameras (_between_cameras)."""

    views: list[tuple[int, int]]
    maps: ShaderMaps
    footprints: np.ndarray
    references: np.ndarray | None
    between: dict[str, np.ndarray] | None


def draw_task(scene: Scene, plan: ImpostorPlan, task: ImpostorTask, timings: dict[str, float],
              next_positions: np.ndarray | None = None, footprints: np.ndarray | None = None) -> DrawnTask:
    """A task's GL passes in the shared renderer.

    next_positions: (V, 3) the scene's vertices moved by their velocity at this baked frame, for the
    surface maps' motion (crowdbake.bake.surface_maps.motion_positions); None: no motion.
    footprints: (V, S, S, 4) the task's views' mesh_footprints, where the caller drew them already (the
    impostor probes draw a frame's once for every count that bakes it); None: drawn here.

    The maps of every view are drawn, encoded, in one pass of crowdbake.render.map_shader at each texel's
    centre; each texel's footprint (its mean shading normal and the mesh's share of it, the surface map's
    alpha) as the references sample it, FIDELITY_SUPERSAMPLE² samples a texel. With references, the mesh
    is also drawn shaded at FIDELITY_SUPERSAMPLE x the tile from
    every baked view and halfway to the next azimuth (_between_cameras), box-filtered on the GPU, in one
    pass. timings: adds "render" (the maps' pass) and "references" seconds.
    """
    layout = plan.layout
    tile = int(layout["tile_size"])
    views = [(int(a), int(e)) for a, e in task.views]
    angles = [(layout["azimuths_deg"][a], layout["elevations_deg"][e]) for a, e in views]
    map_views = [impostor_views.ortho_view(plan.center, plan.radius, azimuth, elevation, tile) for azimuth, elevation in angles]
    renderer = shared_renderer(tile)
    clock = time.perf_counter()
    maps = renderer.shader_maps(map_views, scene.positions, scene.normals, scene.uvs,
                                scene.positions if next_positions is None else next_positions,
                                scene.faces, scene.triangle_material, scene.diffuse)
    timings["render"] += time.perf_counter() - clock
    references, between = None, None
    clock = time.perf_counter()
    if task.references:
        between = _between_cameras(plan, views)
        # One pass for the baked views and the cameras between them: the mesh and textures go up once.
        references = mesh_references(scene, plan, angles + [(azimuth, plan.layout["elevations_deg"][e])
                                                           for (_, e), azimuth in zip(between["between_views"].tolist(), between["between_azimuths"])])
        timings["references"] += time.perf_counter() - clock
    if footprints is None:
        # Sampled as the references are: the share is the surface map's alpha, the normal the normal map's.
        clock = time.perf_counter()
        footprints = mesh_footprints(scene, plan, angles)
        timings["render"] += time.perf_counter() - clock
    return DrawnTask(views, maps, footprints, references, between)


def finish_task(drawn: DrawnTask, timings: dict[str, float]) -> dict[str, np.ndarray]:
    """The part's arrays from what draw_task drew (its maps are changed in place): texels the mesh
    covers only in part take their nearest covered texel's values (extend_to_partial_texels), every
    covered texel the normal of its footprint (footprint_normals), backgrounds are filled for the whole
    ring at once (fill_background), the surface map's alpha is the coverage. timings: adds "maps" seconds."""
    maps, coverage = drawn.maps, drawn.footprints[..., 3]
    clock = time.perf_counter()
    mask = extend_to_partial_texels(maps.mask, coverage, [maps.normal, maps.uv, maps.detail, maps.surface])
    maps.normal[..., :3] = footprint_normals(drawn.footprints[..., :3], maps.normal[..., :3], mask)
    # The surface map's background is filled as the others' but keeps its blocks as filled: its values
    # beside the silhouette are read back by the runtime's reprojection.
    fill_background(mask, [maps.normal, maps.detail], unflattened=[maps.surface])
    maps.surface[..., 3] = np.where(mask, np.rint(np.clip(coverage, 0.0, 1.0) * 255.0), 0).astype(np.uint8)
    timings["maps"] += time.perf_counter() - clock
    arrays = {"views": np.asarray(drawn.views, dtype=np.int64).reshape(-1, 2), "normal": maps.normal, "uv": maps.uv,
              "detail": maps.detail, "surface": maps.surface}
    if drawn.references is not None:
        count = len(drawn.views)
        arrays.update(reference=drawn.references[:count], reference_between=drawn.references[count:], **drawn.between)
    return arrays


def mesh_footprints(scene: Scene, plan: ImpostorPlan, angles: list[tuple[float, float]]) -> np.ndarray:
    """Each texel's footprint from each (azimuth, elevation) in degrees, sampled as mesh_references samples
    it (FIDELITY_SUPERSAMPLE² samples a texel): (V, S, S, 4) float32, RGB the mean shading normal over the
    samples (0 where the mesh misses one), alpha the share the mesh covers (mesh_references' alpha
    with_coverage, to the bit)."""
    size = int(plan.layout["tile_size"]) * FIDELITY_SUPERSAMPLE
    views = [impostor_views.ortho_view(plan.center, plan.radius, azimuth, elevation, size) for azimuth, elevation in angles]
    if not views:
        return np.zeros((0, size // FIDELITY_SUPERSAMPLE, size // FIDELITY_SUPERSAMPLE, 4), np.float32)
    return shared_renderer(int(plan.layout["tile_size"])).shader_footprints(
        views, scene.positions, scene.normals, scene.faces, scene.triangle_material, len(scene.diffuse_runtime or scene.diffuse),
        FIDELITY_SUPERSAMPLE)


def footprint_normals(sums: np.ndarray, codes: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The normal map's RGB codes with every texel of `mask` holding its footprint's normal: the direction
    of `sums` (..., 3), the shading normals summed (or averaged) over the texel's samples, coded as the map
    shader codes a normal (SPEC.md "Impostor maps": (n + 1) / 2, rounded to nearest). codes: (..., 3) uint8
    the map shader's normal at each texel's centre, kept where the sum has no direction (the samples'
    normals cancel) and outside `mask`.

    A texel the mesh covers in part or across a crease is seen by a picture's pixel as the mean of what it
    covers (the references' anti-aliasing); its centre's normal alone shades it as one of its faces."""
    sums = np.asarray(sums, dtype=np.float64)
    length = np.linalg.norm(sums, axis=-1, keepdims=True)
    directed = mask[..., None] & (length > 1e-6)
    unit = sums / np.maximum(length, 1e-12)
    coded = np.floor(np.clip((unit + 1.0) * 127.5, 0.0, 255.0) + 0.5).astype(np.uint8)
    return np.where(directed, coded, codes)


def mesh_references(scene: Scene, plan: ImpostorPlan, angles: list[tuple[float, float]], with_coverage: bool = False) -> np.ndarray:
    """The mesh from each (azimuth, elevation) in degrees, lit as the runtime lights the impostor, at
    FIDELITY_SUPERSAMPLE² samples a texel (crowdbake.render.map_shader.draw_references, which
    crowdbake.reference.mesh_reference is the float64 reference of): (V, S, S, 3) float32."""
    size = int(plan.layout["tile_size"]) * FIDELITY_SUPERSAMPLE
    views = [impostor_views.ortho_view(plan.center, plan.radius, azimuth, elevation, size) for azimuth, elevation in angles]
    if not views:
        return np.zeros((0, size // FIDELITY_SUPERSAMPLE, size // FIDELITY_SUPERSAMPLE, 4 if with_coverage else 3), np.float32)
    return shared_renderer(int(plan.layout["tile_size"])).shader_references(
        views, scene.positions, scene.normals, scene.uvs, scene.faces, scene.triangle_material,
        scene.diffuse_runtime or scene.diffuse,  # (without runtime textures only the coverage is wanted)
        scene.outfit_row, FIDELITY_SUPERSAMPLE, with_coverage)


def extend_to_partial_texels(mask: np.ndarray, coverage: np.ndarray, maps: list[np.ndarray]) -> np.ndarray:
    """Give the texels the mesh covers only in part (their centre outside `mask`) the values of their
    view's nearest covered texel, in place, and return the extended mask.

    mask: (V, S, S) bool, texel centres the mesh covers; coverage: (V, S, S) float 0..1, the share of each
    texel the mesh covers (supersampled); maps: (V, S, S, C) images of those views. A soft silhouette is
    drawn from these texels too (SPEC.md "Impostor maps", the surface map's alpha): they need a surface
    point to colour, light and reproject, and the nearest covered one is the surface beside them."""
    partial = (np.asarray(coverage) >= MIN_COVERAGE) & ~mask
    if not partial.any():
        return mask
    nearest = nearest_inside_views(mask).reshape(-1)
    chosen = partial.reshape(-1)
    for image in maps:
        flat = image.reshape(-1, image.shape[-1])
        flat[chosen] = flat[nearest[chosen]]
    return mask | partial


def fill_background(mask: np.ndarray, maps: list[np.ndarray], unflattened: list[np.ndarray] = ()) -> np.ndarray:
    """Give the texels outside `mask` the RGB of their view's nearest covered texel, in place.

    mask: (V, S, S) bool; maps, unflattened: (V, S, S, C >= 3) images of those views (alpha left alone).
    The 4 x 4 blocks of `maps` holding no covered texel are then made flat (flatten_empty_blocks); those
    of `unflattened` keep the filled values. Returns the flat index (V·S·S,) of every texel's nearest
    covered texel (nearest_inside_views).

    Block compression fits each block's endpoints to all 16 texels: filling the background with the
    silhouette's own values keeps it from spending precision on texels nobody sees, and a flat block
    costs the encoder nothing. The exact maps of crowdbake.reference.impostor_maps end here too."""
    shape = mask.shape
    nearest = nearest_inside_views(mask).reshape(-1)
    for image in maps:
        image[..., :3] = flatten_empty_blocks(image[..., :3].reshape(-1, 3)[nearest].reshape(shape + (3,)), mask)
    for image in unflattened:
        image[..., :3] = image[..., :3].reshape(-1, 3)[nearest].reshape(shape + (3,))
    return nearest


def nearest_inside_views(masks: np.ndarray) -> np.ndarray:
    """(V, H, W) int64 flat index into a (V * H * W) stack of the nearest texel inside each view's mask
    (nearest_inside per view, whose distance transform stays 2D); a view whose mask is empty or full
    points at itself."""
    count, height, width = masks.shape
    index = np.arange(count * height * width, dtype=np.int64).reshape(count, height, width)
    for k in range(count):
        nearest = nearest_inside(masks[k])
        if nearest is not None:
            index[k] = k * height * width + nearest[0] * width + nearest[1]
    return index


def nearest_inside(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(rows, columns) (H, W) of the nearest texel inside `mask` for every texel; None if mask is empty or full."""
    from scipy import ndimage  # a third of a second to import; only the background fill needs it

    if not mask.any() or mask.all():
        return None
    _, (rows, columns) = ndimage.distance_transform_edt(~mask, return_indices=True)
    return rows, columns


def flatten_empty_blocks(image: np.ndarray, mask: np.ndarray, block: int = 4) -> np.ndarray:
    """Copy of (..., H, W, C) `image` whose block x block tiles holding no texel of the (..., H, W) `mask`
    are one flat colour (their top-left texel's). A flat block compresses exactly and needs no encoder
    effort; only blocks on the silhouette need the dilated values. Leading axes are independent images
    (views). Sizes that are not multiples of `block` are left unchanged."""
    height, width = mask.shape[-2:]
    out = image.copy()
    if height % block or width % block:
        return out
    lead = mask.shape[:-2]
    rows, columns = height // block, width // block
    empty = ~mask.reshape(lead + (rows, block, columns, block)).any(axis=(-3, -1))  # (..., rows, columns)
    tiles = out.reshape(lead + (rows, block, columns, block, -1))
    corner = tiles[..., :1, :, :1, :]  # (..., rows, 1, columns, 1, C)
    tiles[:] = np.where(empty[..., :, None, :, None, None], corner, tiles)
    return out


def _between_cameras(plan: ImpostorPlan, views: list[tuple[int, int]]) -> dict[str, np.ndarray]:
    """The cameras halfway to the next azimuth (no baked view shares their references), for the views whose
    azimuth gap is scored (spread_gaps): "between_views" (B, 2) their (azimuth, elevation) indices and
    "between_azimuths" (B,) degrees."""
    midpoints = midpoint_azimuths(list(plan.layout["azimuths_deg"]))
    scored = set(spread_gaps(len(midpoints)))
    chosen = [(a, e) for a, e in views if a in scored]
    return {
        "between_views": np.asarray(chosen, dtype=np.int64).reshape(-1, 2),
        "between_azimuths": np.asarray([midpoints[a] for a, _ in chosen], dtype=np.float64),
    }


def spread_gaps(count: int, limit: int = BETWEEN_AZIMUTHS) -> list[int]:
    """The gaps scored of `count` azimuth gaps (gap i: from baked azimuth i to the next), at most `limit`
    of them spread evenly round the ring: all when count <= limit, else every (count / limit)-th."""
    if count <= limit:
        return list(range(count))
    return [int(i) for i in np.linspace(0, count, limit, endpoint=False).astype(int)]


def midpoint_azimuths(azimuths: list[float]) -> list[float]:
    """The azimuth halfway to the next baked one, per baked azimuth (wrapping at 360°)."""
    if len(azimuths) == 1:
        return [(azimuths[0] + 180.0) % 360.0]
    following = azimuths[1:] + [azimuths[0] + 360.0]
    return [((a + b) / 2.0) % 360.0 for a, b in zip(azimuths, following)]


def part_record(work: Path, task: ImpostorTask) -> ImpostorPartRecord | None:
    """The sidecar of a written part, or None."""
    stats_path = part_path(work, task).with_suffix(".json")
    return ImpostorPartRecord.from_json(read_json(stats_path)) if stats_path.is_file() else None


def gl_renderers(work: Path) -> list[dict]:
    """Each GL context that drew the written impostor parts (their sidecars' `gl`), in task order, with
    `impostor_tasks`: how many parts it drew. One entry, unless workers of several kinds shared the bake."""
    counts: dict[str, int] = {}  # by the context's JSON text: dicts keep their first-seen order
    for task in impostor_tasks(work):
        stats = part_record(work, task)
        if stats is not None and stats.gl is not None:
            text = json.dumps(stats.gl, sort_keys=True)
            counts[text] = counts.get(text, 0) + 1
    return [{**json.loads(text), "impostor_tasks": count} for text, count in counts.items()]


def impostor_statistics(work: Path) -> ImpostorStatistics:
    """Views, renders and seconds summed over the written impostor parts (from their sidecars)."""
    totals = ImpostorStatistics()
    for task in impostor_tasks(work):
        stats = part_record(work, task)
        if stats is None:
            continue
        totals.tasks += 1
        totals.views += int(stats.views)
        totals.render_seconds += float(stats.seconds["render"])
        totals.maps_seconds += float(stats.seconds["maps"])
        totals.reference_seconds += float(stats.seconds["references"])
    return totals
