"""The impostor plan: the impostors' framing, baked frames and scene (work/impostor/scene.npz) from the
cycle's output, before any impostor task runs.

The poses stage records what this plan chose, so the pose caches, the impostor tasks and the pack agree.
For one clip the framing is crowdbake.stages.poses.impostor_framing's rule. For several clips with an
archetype budget (`impostor_archetype_mib`) the frames of every clip and transition come out of one
budget, split by measuring (crowdbake.bake.impostor_allocation, probes in crowdbake.stages.impostor_probe).
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from crowdbake.bake import compression, impostor_allocation, pose_ranges
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.bake.impostor_budget import bytes_per_texel, crop_for, frame_extents, map_formats
from crowdbake.formats.binary import QUANTIZED_POSE_CACHE_VERSION
from crowdbake.formats.gltf import load_character
from crowdbake.formats.skinned_cache import SKINNED_POSE_CACHE_MAGIC
from crowdbake.stages.impostor_probe import PROBE_AZIMUTHS, PROBE_GAPS, Prober
from crowdbake.stages.impostors import SCENE_FILE, Scene, scene_arrays
from crowdbake.stages.poses import diffuse_format, high_parts, impostor_framing, materials_of, part_materials
from crowdbake.stages.records import CycleRecord, ImpostorPlan
from crowdbake.stages.validate import load_job
from crowdbake.stages.workdir import Progress, StageOutcome, WorkDir, npz_bytes, report, stage_key, write_bytes_atomic

logger = logging.getLogger(__name__)
MIB = 1024 * 1024
# What chooses a several-clip bake's frames: part of the plan's key, so plans of another rule are redone.
ALLOCATION = f"measured-3-{PROBE_AZIMUTHS}x{PROBE_GAPS}-{impostor_allocation.TOLERANCE}-{len(impostor_allocation.LADDER)}"


class SceneFrames:
    """The high LOD at any pose frame, as the impostor tasks draw it (scene_arrays' stored frames), with
    the textures of `arrays` (diffuse_<m>, runtime_<m>, outfit_row): a Scene per frame, made once."""

    def __init__(self, high: dict, part_material: dict, arrays: dict[str, np.ndarray], material_count: int):
        self.high, self.part_material = high, part_material
        static = scene_arrays(high, part_material, [])
        self.faces, self.uvs, self.triangle_material = static["faces"], static["uvs"], static["triangle_material"]
        self.diffuse = [arrays[f"diffuse_{m}"] for m in range(material_count)]
        self.runtime = [arrays[f"runtime_{m}"] for m in range(material_count)]
        self.outfit_row = arrays["outfit_row"]
        self._scenes: dict[int, Scene] = {}

    def __call__(self, frame: int) -> Scene:
        if frame not in self._scenes:
            stored = scene_arrays(self.high, self.part_material, [frame])
            self._scenes[frame] = Scene(stored[f"positions_{frame}"].astype(np.float64), stored[f"normals_{frame}"].astype(np.float64),
                                        self.uvs.astype(np.float64), self.faces, self.triangle_material, self.diffuse, self.runtime,
                                        self.outfit_row)
        return self._scenes[frame]


def measured_framing(params, cycle: CycleRecord, high: dict, record: ImpostorPlan, scene_at, has_regions: list[bool],
                     budget: dict) -> tuple[AtlasLayout, list[int], dict]:
    """The layout, baked frames and budget account of a several-clip bake whose frames come out of one
    budget of params.impostor_archetype_mib (module docstring): the azimuths and rings of `record`'s layout,
    the frames `allocate` chooses from the probes' scores, the crop over them."""
    ranges = cycle.bundle_ranges()
    layout = AtlasLayout.from_manifest(record.layout)
    positions = np.concatenate([np.asarray(part.positions) for part in high.values()], axis=1)
    extents = frame_extents(positions, record.center, layout.elevations_deg)
    # Every pose frame's crop: what any allocation fits in (the probes draw in it; the budget counts it).
    widest = crop_for(extents, list(range(len(positions))), record.radius, params.tile_size)
    formats = map_formats(params.compress, params.uv_format, params.detail_map)
    views = len(layout.azimuths_deg) * len(layout.elevations_deg)
    frame_bytes = views * widest[2] * widest[3] * bytes_per_texel(formats)
    prober = Prober(ranges, replace(record, layout=replace(layout, crop=widest).to_manifest()), scene_at, formats, has_regions)
    scores = prober.table(params.impostor_frames)
    allocation = impostor_allocation.allocate(ranges, scores, frame_bytes, params.impostor_archetype_mib * MIB)
    frame_indices = allocation.frame_indices()
    if params.crop:
        layout = replace(layout, crop=crop_for(extents, frame_indices, record.radius, params.tile_size))
    account = impostor_allocation.allocation_document(ranges, scores, allocation, params.impostor_archetype_mib, frame_bytes)
    logger.info("impostor frames by measuring: %s (%.1f MiB of %.1f, probes %.1f s)",
                ", ".join(f"{r['name']} {r['baked_frames']}" for r in account["ranges"]), account["mib"],
                params.impostor_archetype_mib, prober.seconds)
    document = {**budget, "allocation": account, "ranges": pose_ranges.frames_per_range(ranges, frame_indices)}
    document["chosen"] = {**budget.get("chosen", {}), "frames": allocation.counts}
    document["fits"] = allocation.fits
    return layout, frame_indices, document


def stage_impostor_plan(work: Path, progress: Progress | None = None) -> StageOutcome[ImpostorPlan]:
    """The impostors' framing, baked frames and scene (work/impostor/scene.npz) from the cycle's output.

    The same high_parts as the poses stage's, without its LODs and texture compression: what the
    impostor tasks need; the poses stage takes its framing from this record."""
    started = time.perf_counter()
    folder = WorkDir(work)
    # Its scene is the caches' geometry: stale when their kind changes.
    key = stage_key("impostor-plan", folder.key_of("cycle"), QUANTIZED_POSE_CACHE_VERSION, SKINNED_POSE_CACHE_MAGIC.decode(), ALLOCATION)
    scene_path = folder.root / "impostor" / SCENE_FILE
    cached = folder.cached("impostor", key, ImpostorPlan, [scene_path])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)
    job = load_job(work)
    params = job.bake_params
    cycle = folder.load("cycle", CycleRecord)
    character = load_character(folder.inputs / job.inputs["character"], animation=params.animation)
    materials, outfits = materials_of(job, folder.inputs, character, first_layer_only=True)
    high, _, part_material = high_parts(job, cycle, folder, character)
    part_material = part_materials(part_material, materials)
    bounds, layout, frame_indices, budget = impostor_framing(params, cycle, high)
    textures: dict[str, np.ndarray] = {}
    has_regions = []
    for index, material in enumerate(materials):
        layers = material["layers"]
        pixel_format = diffuse_format(layers, params.compress)
        height, width = layers.shape[1:3]
        textures[f"diffuse_{index}"] = layers[0]
        # What a runtime samples: variation 0 through the bundle's block compression (as the poses stage encodes it).
        textures[f"runtime_{index}"] = compression.decode(compression.encode(layers[0], pixel_format), pixel_format, width, height)
        has_regions.append(pixel_format != "bc1")
    textures["outfit_row"] = outfits[0]
    record = ImpostorPlan(bounds=bounds, layout=layout.to_manifest(), frame_indices=frame_indices,
                          fidelity_frame=frame_indices[0], material_count=len(materials), ranges=cycle.ranges, budget=budget)
    if cycle.ranges is not None and params.impostor_archetype_mib is not None:
        report(progress, "impostor-plan", 0, 1)
        scene_at = SceneFrames(high, part_material, textures, len(materials))
        layout, frame_indices, budget = measured_framing(params, cycle, high, record, scene_at, has_regions, budget)
        record = replace(record, layout=layout.to_manifest(), frame_indices=frame_indices, fidelity_frame=frame_indices[0], budget=budget)
    arrays = {**scene_arrays(high, part_material, frame_indices), **textures}
    write_bytes_atomic(scene_path, npz_bytes(arrays))
    seconds = time.perf_counter() - started
    folder.save("impostor", key, record, seconds)
    report(progress, "impostor-plan", 1, 1)
    return StageOutcome(record, False, seconds)
