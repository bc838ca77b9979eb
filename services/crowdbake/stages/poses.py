"""Stage 3, poses (paper section 4): the body (linear blend skinning) and the cloth per cycle frame, at a
high and a low LOD, plus the materials' textures and the impostors' framing.

Reads the JobRecord and CycleRecord; writes work/poses/<part>_lod<k>.cbpc (a body posed by a skinned glTF:
<part>_lod<k>.cbsk, crowdbake.stages.body_skin), textures.npz (materials,
their encoded and decoded diffuse layers, the outfit map) and the PosesRecord. The textures need the job
alone, not the cycle (stage_textures): the bake runner encodes them in a worker while the cycle is searched.
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from PIL import Image

from crowdbake.bake import compression, lod, pose_ranges, poses
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.bake.impostor_budget import (
    budget_document, bytes_per_texel, crop_for, fit_budget, fit_budget_per_clip, frame_extents, frames_for_motion, map_formats,
)
from crowdbake.bake.texture_memory import MIB
from crowdbake.bake.cycle import estimate_root_offsets
from crowdbake.bake.body_skin import pose_body_cycle
from crowdbake.bake.skinning import pose_character
from crowdbake.errors import StageOrderError
from crowdbake.formats.binary import QUANTIZED_POSE_CACHE_VERSION, encode_quantized_pose_cache
from crowdbake.formats.skinned_cache import SKINNED_POSE_CACHE_MAGIC
from crowdbake.formats.gltf import load_character
from crowdbake.formats.images import read_texture_variation
from crowdbake.formats.obj import read_obj
from crowdbake.formats.pc2 import read_pc2
from crowdbake.formats.ranges import Ranges
from crowdbake.stages.body_skin import skinned_body, skinned_cache_bytes
from crowdbake.stages.records import CycleRecord, ImpostorPlan, JobRecord, MaterialInfo, PoseCachesRecord, PosePart, PosesRecord, TexturesRecord
from crowdbake.stages.validate import load_job, texture_files
from crowdbake.stages.workdir import (
    Progress, StageOutcome, WorkDir, npz_bytes, report, stage_key, write_bytes_atomic, write_json_atomic,
)

logger = logging.getLogger(__name__)

# Default outfits when the inputs bring no outfits.png: a fixed seed keeps the bake deterministic.
DEFAULT_OUTFIT_COUNT = 8
_DEFAULT_OUTFIT_SEED = 2006


def default_outfits(count: int = DEFAULT_OUTFIT_COUNT) -> np.ndarray:
    """(count, 16, 4) uint8 outfit map when the inputs bring none: region 0 white, others fixed colours."""
    rng = np.random.default_rng(_DEFAULT_OUTFIT_SEED)
    outfits = np.empty((count, 16, 4), dtype=np.uint8)
    outfits[..., :3] = rng.integers(64, 256, size=(count, 16, 3))
    outfits[..., 3] = 255
    outfits[:, 0, :3] = 255
    return outfits


def load_rgba_png(path: Path) -> np.ndarray:
    """(H, W, 4) uint8 from a PNG; an image without alpha gets alpha 0 (region 0: keep its colours)."""
    with Image.open(path) as image:
        has_alpha = "A" in image.getbands() or image.mode == "P" and "transparency" in image.info
        rgba = np.array(image.convert("RGBA"))
    if not has_alpha:
        rgba[..., 3] = 0
    return rgba


def materials_of(job: JobRecord, inputs: Path, character, first_layer_only: bool = False) -> tuple[list[dict], np.ndarray]:
    """Materials [{"name", "layers" (L, H, W, 4) uint8}] and the outfit map (O, 16, 4) uint8.

    character: the loaded character, read only when the job brings no textures (None will do then).
    first_layer_only: load variation 0 alone (L = 1), all the impostor bake draws with."""
    names = job.inputs
    if "textures" in names:
        diffuse, outfits_path = texture_files(inputs / names["textures"])
        # PNG or JPEG; a JPEG's alpha is 0 (region 0), since only a PNG carries region codes.
        layers = np.stack([read_texture_variation(path).rgba for path in (diffuse[:1] if first_layer_only else diffuse)])
        materials = [{"name": "character", "layers": layers}]
        if outfits_path is not None:
            outfits = load_rgba_png(outfits_path).reshape(-1, 16, 4)
            outfits[..., 3] = 255
        else:
            outfits = default_outfits()
        return materials, outfits
    if character.texture is not None:
        body = np.asarray(character.texture, dtype=np.uint8).copy()
        # A glTF alpha is opacity, not a region code: region 0 keeps the texture's own colours.
        body[..., 3] = 0
    else:
        body = np.full((4, 4, 4), 200, dtype=np.uint8)
        body[..., 3] = 0
    if "cloth" not in names:  # no garment (crowdbake.stages.body_only): no garment material
        return [{"name": "body", "layers": body[None]}], default_outfits()
    # The garment's UVs address no texture we were given: a plain white one in region 1 takes the outfit colour.
    garment = np.full((4, 4, 4), 255, dtype=np.uint8)
    garment[..., 3] = 17
    return [{"name": "body", "layers": body[None]}, {"name": "garment", "layers": garment[None]}], default_outfits()


def diffuse_format(layers: np.ndarray, compress: bool) -> str:
    """bc2 when compressing and the texture is whole 4x4 blocks, else rgba8."""
    height, width = layers.shape[1:3]
    return "bc2" if compress and height % 4 == 0 and width % 4 == 0 else "rgba8"


def high_parts(job: JobRecord, cycle: CycleRecord, work: WorkDir, character, skin_body: bool = True) -> tuple[dict, dict, dict]:
    """The high LOD of the body and the garment over the cycle: (parts, kinds, materials per part).

    The body as skinning where it can be (crowdbake.stages.body_skin.skinned_body; skin_body False: its
    vertex frames, always). The impostor plan (crowdbake.stages.impostors.stage_impostor_plan) draws the
    same arrays, so both stages run side by side from the cycle's output and agree to the bit."""
    inputs, names = work.inputs, job.inputs
    fps, start, frames = cycle.fps, cycle.start_frame, cycle.pose_frames
    looped_file = "looped.pc2" if cycle.ranges is None else cycle.ranges["file"]
    if cycle.ranges is not None:  # several clips: every loop, then every transition
        body_positions, body_normals = ranges_body(inputs / names["character"], inputs / names["timeline"], cycle)
    else:
        # With several clips the loop's first frame is at its clip frame, not at start_frame / fps.
        body_positions, body_normals = pose_body_cycle(character, fps, start if cycle.clip_phase is None else cycle.clip_phase, frames)
    if cycle.root_motion_removed and cycle.ranges is None:
        # The cycle search worked in the root's frame (the character travels): follow it for the body.
        everything, _ = pose_body_cycle(character, fps, 0, job.cache_frames)
        offsets = estimate_root_offsets(everything)[start : start + frames]
        body_positions = (body_positions - offsets[:, None, :]).astype(np.float32)

    body = poses.PartPoses(
        faces=np.asarray(character.faces, dtype=np.uint32),
        uvs=np.asarray(character.uvs, dtype=np.float32),
        positions=np.asarray(body_positions, dtype=np.float32),
        normals=poses.unit_normals(body_normals),
    )
    if skin_body:
        body = skinned_body(job, cycle, inputs, character, body)
    if "cloth" not in names:  # crowdbake.stages.body_only: the body is the whole character
        return {"body": body}, {"body": "body"}, {"body": 0}
    mesh = read_obj(inputs / names["cloth_mesh"])
    looped = read_pc2(work.root / "cycle" / looped_file)
    if looped.points.shape[0] != frames:
        raise StageOrderError(f"{looped_file} has {looped.points.shape[0]} frames, the cycle {frames}")
    garment_positions = poses.cloth_on_vertices(looped.points, mesh.source_index)
    garment_normals = poses.pose_normals(garment_positions, mesh.faces, weld=mesh.source_index)
    if mesh.uvs is None:
        logger.warning("%s has no texture coordinates: the garment's UV map will read (0, 0)", names["cloth_mesh"])
    garment_uvs = mesh.uvs if mesh.uvs is not None else np.zeros((mesh.vertex_count, 2), np.float32)
    garment = job.garment_part
    high = {
        "body": body,
        garment: poses.PartPoses(
            faces=np.asarray(mesh.faces, dtype=np.uint32),
            uvs=np.asarray(garment_uvs, dtype=np.float32),
            positions=garment_positions,
            normals=poses.unit_normals(garment_normals),
        ),
    }
    return high, {"body": "body", garment: "garment"}, {"body": 0, garment: 1}


def ranges_body(character_path: Path, timeline_path: Path, cycle: CycleRecord) -> tuple[np.ndarray, np.ndarray]:
    """The body over every pose frame of a several-clip bundle (cycle.ranges): each clip's loop posed by
    that clip's animation at its loop's clip frames, each transition at its cache frames as the timeline
    played them (blends included: crowdbake.bake.pose_ranges.body_at_cache_frames). (P, V, 3) each."""
    from crowdbake.ingest.timeline import read_timeline

    timeline = read_timeline(timeline_path)
    ranges = cycle.bundle_ranges()
    posed = {}
    for clip in timeline.clips():
        posed[clip] = pose_character(load_character(character_path, animation=clip), cycle.fps, timeline.period(clip))
    positions, normals = [], []
    for clip, phase in zip(ranges.clips, cycle.ranges["clip_phases"]):
        body = pose_ranges.clip_body(posed[clip.name], phase, clip.frames)
        positions.append(body[0])
        normals.append(body[1])
    for transition in ranges.transitions:
        body = pose_ranges.body_at_cache_frames(posed, timeline, np.arange(transition.source_start_frame, transition.source_end_frame))
        positions.append(body[0])
        normals.append(body[1])
    return np.concatenate(positions).astype(np.float32), np.concatenate(normals).astype(np.float32)


def part_materials(part_material: dict, materials: list) -> dict:
    """Material index per part: one given texture set serves every part."""
    return dict.fromkeys(part_material, 0) if len(materials) == 1 else part_material


def framing_bounds(high: dict) -> dict:
    """{"center": [x, y, z], "radius": r} of the sphere framing every part in every frame (metres): what
    every impostor view frames."""
    centre, radius = poses.common_bounds(*(part.positions for part in high.values()))
    return {"center": [float(c) for c in centre], "radius": float(radius)}


def impostor_framing(params, cycle: CycleRecord, high: dict) -> tuple[dict, AtlasLayout, list[int], dict]:
    """The impostors' framing: bounds {"center", "radius"} over every frame and part, the atlas layout
    (its crop, and the azimuth and frame counts within params.impostor_budget_mib: crowdbake.bake.
    impostor_budget), the baked cycle frames and the budget's account (texture_memory.json's `budget`).
    Shared by the poses stage and the impostor plan. Several clips: ranges_framing."""
    if cycle.ranges is not None:
        return ranges_framing(params, cycle.bundle_ranges(), high)
    bounds = framing_bounds(high)
    centre, radius = np.asarray(bounds["center"]), bounds["radius"]
    elevations = tuple(params.elevations_deg)
    positions = np.concatenate([np.asarray(part.positions) for part in high.values()], axis=1)
    extents = frame_extents(positions, centre, elevations)
    budget = None if params.impostor_budget_mib is None else params.impostor_budget_mib * MIB
    frames = frames_for_motion(positions, params.tile_size / (2.0 * radius), params.impostor_motion_texels, params.impostor_frames)
    choice = fit_budget(extents, radius, params.tile_size, params.azimuths, len(elevations), frames, cycle.cycle_frames,
                        bytes_per_texel(map_formats(params.compress, params.uv_format, params.detail_map)), budget)
    layout = AtlasLayout.rings(params.tile_size, choice.azimuths, elevations)
    if params.crop:
        layout = replace(layout, crop=choice.crop)
    frame_indices = poses.impostor_frame_indices(cycle.cycle_frames, choice.frames)
    return bounds, layout, frame_indices, budget_document(choice, params)


def ranges_framing(params, ranges: Ranges, high: dict) -> tuple[dict, AtlasLayout, list[int], dict]:
    """impostor_framing for several clips (crowdbake.bake.pose_ranges): the budget per clip, one azimuth
    count for all (fit_budget_per_clip), each transition's ends and frames between at its clips' spacing,
    the crop over every baked frame (one layout for all, so a clip's layers may be a little larger than
    the crop of its own frames the budget measured: texture_memory.json's `impostor.ranges` has the
    bytes as stored). The budget's account lists each clip's choice."""
    bounds = framing_bounds(high)
    centre, radius = np.asarray(bounds["center"]), bounds["radius"]
    elevations = tuple(params.elevations_deg)
    positions = np.concatenate([np.asarray(part.positions) for part in high.values()], axis=1)
    extents = frame_extents(positions, centre, elevations)
    budget = None if params.impostor_budget_mib is None else params.impostor_budget_mib * MIB
    frames = [frames_for_motion(positions[clip.first_frame:clip.first_frame + clip.frames], params.tile_size / (2.0 * radius),
                                params.impostor_motion_texels, params.impostor_frames) for clip in ranges.clips]
    choices = fit_budget_per_clip(extents, radius, params.tile_size, params.azimuths, len(elevations), frames,
                                  [(clip.first_frame, clip.frames) for clip in ranges.clips],
                                  bytes_per_texel(map_formats(params.compress, params.uv_format, params.detail_map)), budget)
    layout = AtlasLayout.rings(params.tile_size, choices[0].azimuths, elevations)
    frame_indices = pose_ranges.baked_frames(ranges, [choice.frames for choice in choices])
    if params.crop:
        layout = replace(layout, crop=crop_for(extents, frame_indices, radius, params.tile_size))
    document = {**budget_document(choices[0], params), "per_clip": {clip.name: budget_document(choice, params) for clip, choice in zip(ranges.clips, choices)},
                "ranges": pose_ranges.frames_per_range(ranges, frame_indices)}
    document["chosen"] = {"azimuths": choices[0].azimuths, "frames": [choice.frames for choice in choices]}
    document["fits"] = all(choice.fits for choice in choices)
    return bounds, layout, frame_indices, document


def _write_lods(high: dict, kinds: dict, part_material: dict, params, fps: float, out: Path) -> list[PosePart]:
    """The low LOD (the paper's ratio unless told otherwise; garments keep their borders) and both LODs'
    pose caches: a part with a skin (a skinned body, crowdbake.stages.body_skin) as CBSK, else quantized."""
    counts = [part.triangle_count for part in high.values()]
    if params.lod_triangles is not None:
        targets = lod.target_for_parts(counts, params.lod_triangles)
    else:
        ratio = params.lod_ratio if params.lod_ratio is not None else lod.PAPER_LOD_RATIO
        targets = [max(1, int(round(count * ratio))) for count in counts]
    parts: list[PosePart] = []
    for (name, part), target in zip(high.items(), targets):
        pose = part.positions[0] if part.simplify_pose is None else part.simplify_pose
        simplified = lod.simplify(pose, part.faces, target, uvs=part.uvs, lock_border=kinds[name] == "garment")
        low = poses.low_lod(part, simplified)
        for level, version in ((0, part), (1, low)):
            skinned = None if version.skin is None else skinned_cache_bytes(version, fps)
            path = out / f"{name}_lod{level}.{'cbsk' if skinned is not None else 'cbpc'}"
            (out / f"{name}_lod{level}.{'cbpc' if skinned is not None else 'cbsk'}").unlink(missing_ok=True)  # a rerun's other kind
            write_bytes_atomic(path, skinned if skinned is not None else
                               encode_quantized_pose_cache(version.faces, version.uvs, version.positions, version.normals, fps))
            parts.append(PosePart(part=name, kind=kinds[name], lod=level, file=path.name, material=part_material[name],
                                  vertex_count=version.vertex_count, triangle_count=version.triangle_count))
        parts[-1].target_triangles = int(target)
        parts[-1].relative_error = float(simplified.relative_error)
        parts[-1].locked_border = bool(simplified.locked_border)
    return parts


DIFFUSE_ERRORS = "diffuse_errors.json"
TEXTURES_FILE = "textures.npz"


def _write_textures(materials: list[dict], outfits: np.ndarray, compress: bool, out: Path) -> list[MaterialInfo]:
    """Encode the diffuse layers once; the impostor tasks and fidelity use what a runtime samples. The
    compression error of every block-compressed layer goes to DIFFUSE_ERRORS (for the pack stage's report,
    measured here where the layers are at hand, beside the impostor tasks rather than before the bundle)."""
    arrays: dict[str, np.ndarray] = {"outfits": outfits}
    errors: dict[str, list[dict]] = {}
    infos = []
    for index, material in enumerate(materials):
        layers = material["layers"]
        pixel_format = diffuse_format(layers, compress)
        height, width = layers.shape[1:3]
        encoded = [compression.encode(layer, pixel_format) for layer in layers]
        decoded = np.stack([compression.decode(data, pixel_format, width, height) for data in encoded])
        arrays[f"material_{index}"] = layers
        arrays[f"material_{index}_encoded"] = np.frombuffer(b"".join(encoded), dtype=np.uint8)
        arrays[f"material_{index}_decoded"] = decoded
        # Variation 0 on its own: the impostor tasks need only it, and np.load reads whole arrays.
        arrays[f"material_{index}_v0"] = layers[0]
        arrays[f"material_{index}_decoded_v0"] = decoded[0]
        if pixel_format != "rgba8":
            errors[material["name"]] = [compression.compression_error(layer, back) for layer, back in zip(layers, decoded)]
        infos.append(MaterialInfo(name=material["name"], variations=int(len(layers)), width=int(width), height=int(height), pixel_format=pixel_format))
    write_bytes_atomic(out / TEXTURES_FILE, npz_bytes(arrays))
    write_json_atomic(out / DIFFUSE_ERRORS, errors)
    return infos


def stage_textures(work: Path) -> TexturesRecord:
    """The materials' diffuse layers, encoded and decoded, and the outfit map → work/poses/TEXTURES_FILE
    and DIFFUSE_ERRORS (its record and stamp in work/textures/). Part of the poses stage, but it needs only
    the validated job: the bake runner runs it in a worker while this process searches the cycle.
    Idempotent: kept when written for the same job."""
    started = time.perf_counter()
    folder = WorkDir(work)
    out = folder.root / "poses"
    key = stage_key("textures", folder.key_of("validate"))
    cached = folder.cached("textures", key, TexturesRecord, [out / TEXTURES_FILE, out / DIFFUSE_ERRORS])
    if cached is not None:
        return cached
    job = load_job(work)
    # The character's own texture serves only when the job brings none (its glTF is parsed only then).
    character = None if "textures" in job.inputs else load_character(folder.inputs / job.inputs["character"], animation=job.bake_params.animation)
    materials, outfits = materials_of(job, folder.inputs, character)
    record = TexturesRecord(materials=_write_textures(materials, outfits, job.bake_params.compress, out), outfit_count=int(len(outfits)))
    folder.save("textures", key, record, time.perf_counter() - started)
    return record


POSE_CACHES = "pose-caches"  # the pose caches' stage folder (stamp and record; the caches are in work/poses)


def stage_pose_caches(work: Path, progress: Progress | None = None) -> StageOutcome[PoseCachesRecord]:
    """Bake the pose caches: body and cloth per cycle frame, high and low LOD, into work/poses; textures.
    Needs the cycle, not the impostor plan, so it runs beside the plan's probes."""
    started = time.perf_counter()
    folder = WorkDir(work)
    job = load_job(work)
    # A cache of another version is stale, and so is one from before skinned bodies.
    key = stage_key("pose-caches", folder.key_of("cycle"), QUANTIZED_POSE_CACHE_VERSION, SKINNED_POSE_CACHE_MAGIC.decode())
    out = folder.root / "poses"
    cached = folder.cached(POSE_CACHES, key, PoseCachesRecord, [out / TEXTURES_FILE, out / DIFFUSE_ERRORS])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)
    params = job.bake_params
    cycle = folder.load("cycle", CycleRecord)
    steps = 6
    report(progress, "poses", 0, steps)

    textures = stage_textures(work)
    character = load_character(folder.inputs / job.inputs["character"], animation=params.animation)
    high, kinds, part_material = high_parts(job, cycle, folder, character)
    part_material = part_materials(part_material, textures.materials)
    report(progress, "poses", 2, steps)
    parts = _write_lods(high, kinds, part_material, params, cycle.fps, out)
    record = PoseCachesRecord(frames_per_second=cycle.fps, cycle_frames=cycle.pose_frames, parts=parts, materials=textures.materials,
                              outfit_count=textures.outfit_count, ranges=cycle.ranges)
    report(progress, "poses", 5, steps)
    seconds = time.perf_counter() - started
    folder.save(POSE_CACHES, key, record, seconds)
    return StageOutcome(record, False, seconds)


def stage_poses(work: Path, progress: Progress | None = None) -> StageOutcome[PosesRecord]:
    """The poses record: the pose caches (stage_pose_caches) with the impostor framing the impostor plan
    chose (several clips: by measuring), so the caches, the impostor tasks and the pack agree."""
    started = time.perf_counter()
    folder = WorkDir(work)
    stage_pose_caches(work, progress)  # done already where the plan ran it (a node of its own): read back
    key = stage_key("poses", folder.key_of(POSE_CACHES), folder.key_of("impostor"))
    cached = folder.cached("poses", key, PosesRecord, [])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)
    caches = folder.load(POSE_CACHES, PoseCachesRecord)
    plan = folder.load("impostor", ImpostorPlan)
    record = PosesRecord(
        frames_per_second=caches.frames_per_second,
        cycle_frames=caches.cycle_frames,
        parts=caches.parts,
        materials=caches.materials,
        outfit_count=caches.outfit_count,
        bounds=plan.bounds,
        layout=plan.layout,
        frame_indices=plan.frame_indices,
        fidelity_frame=plan.fidelity_frame,
        budget=plan.budget,
        ranges=caches.ranges,
    )
    report(progress, "poses", 6, 6)
    seconds = time.perf_counter() - started
    folder.save("poses", key, record, seconds)
    return StageOutcome(record, False, seconds)
