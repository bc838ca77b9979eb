"""The impostor plan: the impostors' framing, baked frames and scene (work/impostor/scene.npz) from the
cycle's output, before any impostor task runs.

The poses stage records what this plan chose, so the pose caches, the impostor tasks and the pack agree.
By default (`impostor_choice` measured) the tile, the azimuth count and the frames of every clip and
transition come out of one budget by measuring (crowdbake.bake.impostor_layout and impostor_allocation,
probes in crowdbake.stages.impostor_probe): `impostor_budget_mib` for one clip, `impostor_archetype_mib`
for several. `impostor_choice` rule (or several clips without an archetype budget) keeps
crowdbake.stages.poses.impostor_framing's rule.
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from crowdbake.bake import compression, impostor_allocation, impostor_layout, pose_ranges
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.bake.impostor_budget import bytes_per_texel, crop_for, frame_extents, map_formats
from crowdbake.formats.binary import QUANTIZED_POSE_CACHE_VERSION
from crowdbake.formats.gltf import load_character
from crowdbake.formats.skinned_cache import SKINNED_POSE_CACHE_MAGIC
from crowdbake.formats.ranges import Clip, Ranges
from crowdbake.params import MAX_IMPOSTOR_TEXELS, MAX_TILE_SIZE
from crowdbake.stages.impostor_probe import PROBE_AZIMUTHS, PROBE_GAPS, Prober, at_views_probe, azimuth_gap_probe, elevation_gap_probe
from crowdbake.stages.impostors import SCENE_FILE, Scene, scene_arrays
from crowdbake.stages.poses import diffuse_format, framing_bounds, high_parts, impostor_framing, materials_of, part_materials
from crowdbake.stages.records import CycleRecord, ImpostorPlan
from crowdbake.stages.validate import load_job
from crowdbake.stages.workdir import Progress, StageOutcome, WorkDir, npz_bytes, report, stage_key, write_bytes_atomic

logger = logging.getLogger(__name__)
MIB = 1024 * 1024
# One clip: how many of the best predicted (tile, azimuths) pairs are measured end to end.
SHORTLIST = 3
# What chooses a several-clip bake's frames: part of the plan's key, so plans of another rule are redone.
ALLOCATION = (f"measured-5-{PROBE_AZIMUTHS}x{PROBE_GAPS}-{impostor_allocation.TOLERANCE}-{len(impostor_allocation.LADDER)}"
              f"-{impostor_layout.TILE_STEPS}-{impostor_layout.AT_VIEWS_TARGET}-{impostor_layout.BETWEEN_TARGET}")


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


def one_clip_ranges(cycle: CycleRecord) -> Ranges:
    """A one-clip cycle as a bundle of one looping range (pose frames 0 .. cycle_frames - 1): its baked
    frames at any count are poses.impostor_frame_indices', so the measured choice serves both."""
    clip = Clip(name="cycle", first_frame=0, frames=cycle.cycle_frames, source_start_frame=0, source_end_frame=cycle.cycle_frames,
                closing="", position_jump_ratio=0.0, velocity_jump_ratio=0.0)
    return Ranges(pose_frames=cycle.cycle_frames, clips=(clip,), transitions=())


def largest_tile(params, rings: int) -> int:
    """The largest tile the choice may try: MAX_TILE_SIZE, and within MAX_IMPOSTOR_TEXELS at the frames and
    azimuths asked (a worker's memory, whatever the budget)."""
    most = int(np.sqrt(MAX_IMPOSTOR_TEXELS / max(1, params.impostor_frames * params.azimuths * rings)))
    return max(4, min(MAX_TILE_SIZE, most - most % 4))


def measured_framing(params, cycle: CycleRecord, high: dict, record: ImpostorPlan, scene_at,
                     has_regions: list[bool]) -> tuple[AtlasLayout, list[int], dict]:
    """The layout, baked frames and budget account chosen by measuring (module docstring): the tile and
    azimuth count (crowdbake.bake.impostor_layout) and every range's frames (impostor_allocation) within
    the budget: params.impostor_archetype_mib for several clips, params.impostor_budget_mib for one."""
    several = cycle.ranges is not None
    ranges = cycle.bundle_ranges() if several else one_clip_ranges(cycle)
    budget_mib = params.impostor_archetype_mib if several else params.impostor_budget_mib
    budget_bytes = None if budget_mib is None else budget_mib * MIB
    elevations = tuple(params.elevations_deg)
    positions = np.concatenate([np.asarray(part.positions) for part in high.values()], axis=1)
    extents = frame_extents(positions, record.center, elevations)
    every_frame = list(range(len(positions)))

    def widest(tile: int):
        """Every pose frame's crop at `tile`: what any choice fits in (the probes draw in it; the budget counts it)."""
        return crop_for(extents, every_frame, record.radius, tile) if params.crop else None

    formats = map_formats(params.compress, params.uv_format, params.detail_map)

    def frame_bytes(tile: int, azimuths: int) -> float:
        box = AtlasLayout(tile, (0.0,), (0.0,), widest(tile)).crop_box
        return azimuths * len(elevations) * box[2] * box[3] * bytes_per_texel(formats)

    asked_tile = params.tile_size
    asked = replace(AtlasLayout.rings(asked_tile, params.azimuths, elevations), crop=widest(asked_tile))
    prober = Prober(ranges, replace(record, layout=asked.to_manifest()), scene_at, formats, has_regions)
    probed_tables = prober.table(params.impostor_frames)
    frame_tables = [impostor_allocation.interpolated(table, counts)
                    for table, counts in zip(probed_tables, impostor_allocation.ladders(ranges, params.impostor_frames))]
    probe_frame = ranges.clips[0].first_frame
    at_views = {}
    for tile in impostor_layout.tile_ladder(asked_tile, largest_tile(params, len(elevations))):
        probe, cameras = at_views_probe(replace(asked, tile_size=tile, crop=widest(tile)))
        at_views[tile] = prober.views_score(probe, probe_frame, cameras)
    ring = asked.elevations_deg[len(elevations) // 2]
    probed_azimuths = {}
    azimuth_ladder = impostor_layout.azimuth_ladder(params.azimuths)
    for count in impostor_allocation.probed_counts(azimuth_ladder):
        probe, cameras = azimuth_gap_probe(asked_tile, count, ring, asked.crop)
        probed_azimuths[count] = prober.views_score(probe, probe_frame, cameras)
    azimuth_scores = impostor_allocation.interpolated(probed_azimuths, azimuth_ladder)
    elevation = elevation_gap_probe(asked)
    elevation_loss = 0.0 if elevation is None else at_views[asked_tile] - prober.views_score(elevation[0], probe_frame, elevation[1])
    candidates = impostor_layout.options(ranges, frame_tables, at_views, azimuth_scores, elevation_loss, asked_tile, frame_bytes, budget_bytes)
    checked = None
    if several:
        chosen = impostor_layout.choose_layout(candidates)
    else:
        # One clip: the best predicted pairs and the rule's own choice measured end to end (the losses do
        # not add exactly), so the choice is never worse than the rule's by the probes.
        rule_frames = list(record.frame_indices)
        rule_azimuths = len(AtlasLayout.from_manifest(record.layout).azimuths_deg)
        rule_bytes = int(round(len(rule_frames) * frame_bytes(asked_tile, rule_azimuths)))
        rule = impostor_layout.LayoutOption(asked_tile, rule_azimuths, impostor_allocation.Allocation(
            [len(rule_frames)], [rule_frames], rule_bytes, budget_bytes is None or rule_bytes <= budget_bytes, [float("nan")]),
            at_views[asked_tile], [float("nan")], float("nan"))
        shortlist = impostor_layout.shortlist(candidates, SHORTLIST)
        if all((o.tile, o.azimuths, o.allocation.frames) != (rule.tile, rule.azimuths, rule.allocation.frames) for o in shortlist):
            shortlist.append(rule)
        checked = [impostor_layout.measured(option, prober.between_score(0, option.allocation.frames[0], option.tile, option.azimuths,
                                                                         elevations, widest(option.tile)))
                   for option in shortlist]
        chosen = impostor_layout.choose_layout(checked)
    allocation = chosen.allocation
    frame_indices = allocation.frame_indices()
    layout = AtlasLayout.rings(chosen.tile, chosen.azimuths, elevations)
    if params.crop:
        layout = replace(layout, crop=crop_for(extents, frame_indices, record.radius, chosen.tile))
    frame_mib = frame_bytes(chosen.tile, chosen.azimuths)
    account = impostor_allocation.allocation_document(ranges, probed_tables, allocation, budget_mib, frame_mib)
    logger.info("impostor by measuring: tile %d, %d azimuths, frames %s (%.1f MiB of %s, probes %.1f s)", chosen.tile, chosen.azimuths,
                ", ".join(f"{r['name']} {r['baked_frames']}" for r in account["ranges"]), account["mib"],
                "no budget" if budget_mib is None else f"{budget_mib:g}", prober.seconds)
    document = {
        "budget_mib": budget_mib,
        "asked": {"tile": asked_tile, "azimuths": params.azimuths, "frames": params.impostor_frames},
        "chosen": {"tile": chosen.tile, "azimuths": chosen.azimuths, "frames": allocation.counts if several else allocation.counts[0]},
        "fits": allocation.fits,
        "rule": "measured",
        "layout": impostor_layout.layout_document(candidates, chosen, at_views, probed_azimuths, elevation_loss, checked),
        "allocation": account,
    }
    if several:
        document["ranges"] = pose_ranges.frames_per_range(ranges, frame_indices)
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
    measured = params.impostor_choice == "measured" and (cycle.ranges is None or params.impostor_archetype_mib is not None)
    if measured and cycle.ranges is not None:
        # The per-clip rule's framing is no candidate for several clips: only its bounds are needed (the
        # asked layout and a first frame stand until measured_framing replaces them).
        bounds, budget = framing_bounds(high), None
        layout, frame_indices = AtlasLayout.rings(params.tile_size, params.azimuths, tuple(params.elevations_deg)), [0]
    else:
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
    if measured:
        report(progress, "impostor-plan", 0, 1)
        scene_at = SceneFrames(high, part_material, textures, len(materials))
        layout, frame_indices, budget = measured_framing(params, cycle, high, record, scene_at, has_regions)
        record = replace(record, layout=layout.to_manifest(), frame_indices=frame_indices, fidelity_frame=frame_indices[0], budget=budget)
    arrays = {**scene_arrays(high, part_material, frame_indices), **textures}
    write_bytes_atomic(scene_path, npz_bytes(arrays))
    seconds = time.perf_counter() - started
    folder.save("impostor", key, record, seconds)
    report(progress, "impostor-plan", 1, 1)
    return StageOutcome(record, False, seconds)
