"""The impostor plan: the impostors' framing, baked frames and scene (work/impostor/scene.npz) from the
cycle's output, before any impostor task runs.

The poses stage records what this plan chose, so the pose caches, the impostor tasks and the pack agree.
By default (`impostor_choice` measured) the tile, the azimuth count and the frames of every clip and
transition come out of one budget by measuring (crowdbake.bake.impostor_layout and impostor_allocation,
probes in crowdbake.stages.impostor_probe): `impostor_budget_mib` for one clip, `impostor_archetype_mib`
for several. `impostor_choice` rule (or several clips without an archetype budget) keeps
crowdbake.stages.poses.impostor_framing's rule.

Four steps, four plan nodes: stage_impostor_scene (the high LOD at every pose frame, in
work/impostor-probes), stage_impostor_probe per probe item (the layout's tile, azimuth and ring probes;
each range's frame ladder), stage_impostor_check per option one clip shortlists (measured end to end),
both of which the local runner draws side by side, and stage_impostor_plan, the choice.
"""
from __future__ import annotations

import json
import logging
import re
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from crowdbake.bake import compression, impostor_allocation, impostor_layout, pose_ranges
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.bake.impostor_budget import FrameExtents, bytes_per_texel, crop_for, frame_extents, map_formats
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
from crowdbake.stages.workdir import (
    Progress, StageOutcome, WorkDir, npz_bytes, read_json, report, stage_key, write_bytes_atomic, write_json_atomic,
)

logger = logging.getLogger(__name__)
MIB = 1024 * 1024
# work/impostor-probes: the probe scene (every pose frame) and one file of scores per probe item.
PROBES = "impostor-probes"
# One clip: how many of the best predicted (tile, azimuths) pairs are measured end to end.
SHORTLIST = 3
# What chooses a several-clip bake's frames: part of the plan's key, so plans of another rule are redone.
ALLOCATION = (f"measured-5-{PROBE_AZIMUTHS}x{PROBE_GAPS}-{impostor_allocation.TOLERANCE}-{len(impostor_allocation.LADDER)}"
              f"-{impostor_layout.TILE_STEPS}-{impostor_layout.AT_VIEWS_TARGET}-{impostor_layout.BETWEEN_TARGET}")


class StoredFrames:
    """The high LOD at any pose frame, as the impostor tasks draw it, read from the probe scene
    (work/impostor-probes/scene.npz, stage_impostor_scene): a Scene per frame, made once."""

    def __init__(self, path: Path):
        self._data = np.load(path)
        self.material_count = int(self._data["material_count"])
        self.faces, self.uvs = self._data["faces"], self._data["uvs"].astype(np.float64)
        self.triangle_material = self._data["triangle_material"]
        self.diffuse = [self._data[f"diffuse_{m}"] for m in range(self.material_count)]
        self.runtime = [self._data[f"runtime_{m}"] for m in range(self.material_count)]
        self.outfit_row = self._data["outfit_row"]
        self.has_regions = [bool(v) for v in self._data["has_regions"]]
        self.extents = FrameExtents(self._data["extent_reach"], self._data["extent_low"], self._data["extent_high"])
        self._scenes: dict[int, Scene] = {}

    def __call__(self, frame: int) -> Scene:
        if frame not in self._scenes:
            self._scenes[frame] = Scene(self._data[f"positions_{frame}"].astype(np.float64), self._data[f"normals_{frame}"].astype(np.float64),
                                        self.uvs, self.faces, self.triangle_material, self.diffuse, self.runtime, self.outfit_row)
        return self._scenes[frame]

    def plan_arrays(self, frame_indices: list[int]) -> dict[str, np.ndarray]:
        """What work/impostor/scene.npz holds for the plan's baked frames (scene_arrays' and the textures)."""
        names = ["faces", "uvs", "triangle_material", "outfit_row", *(f"diffuse_{m}" for m in range(self.material_count)),
                 *(f"runtime_{m}" for m in range(self.material_count))]
        names += [f"{kind}_{frame}" for frame in frame_indices for kind in ("positions", "normals")]
        return {name: self._data[name] for name in names}

    def close(self) -> None:
        self._data.close()


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


def measures(params, cycle: CycleRecord) -> bool:
    """Whether the plan chooses by measuring (module docstring): one clip measured, or several clips
    measured within an archetype budget."""
    return params.impostor_choice == "measured" and (cycle.ranges is None or params.impostor_archetype_mib is not None)


@dataclass
class ProbeSetting:
    """What every probe of one bake and the choice share: the ranges (one clip as one range), the layout
    asked for (its crop the widest), the probe scene's frames and a Prober drawing them."""

    params: Any
    several: bool
    ranges: Ranges
    elevations: tuple[float, ...]
    asked: AtlasLayout
    scene_at: StoredFrames
    prober: Prober
    record: ImpostorPlan

    def widest(self, tile: int):
        return widest_crop(self.params, self.scene_at.extents, self.record.radius, tile)

    def frame_bytes(self, tile: int, azimuths: int) -> float:
        box = AtlasLayout(tile, (0.0,), (0.0,), self.widest(tile)).crop_box
        formats = map_formats(self.params.compress, self.params.uv_format, self.params.detail_map)
        return azimuths * len(self.elevations) * box[2] * box[3] * bytes_per_texel(formats)


def widest_crop(params, extents: FrameExtents, radius: float, tile: int):
    """Every pose frame's crop at `tile`: what any choice fits in (the probes draw in it; the budget counts
    it); None where the bake does not crop."""
    return crop_for(extents, list(range(len(extents.reach))), radius, tile) if params.crop else None


def probe_setting(work: Path) -> ProbeSetting:
    """The probes' setting of the bake at `work`, from its job, cycle and probe scene (stage_impostor_scene)."""
    folder = WorkDir(work)
    params = load_job(work).bake_params
    cycle = folder.load("cycle", CycleRecord)
    record = folder.load(PROBES, ImpostorPlan)
    ranges = cycle.bundle_ranges() if cycle.ranges is not None else one_clip_ranges(cycle)
    elevations = tuple(params.elevations_deg)
    scene_at = StoredFrames(folder.root / PROBES / SCENE_FILE)
    asked = replace(AtlasLayout.rings(params.tile_size, params.azimuths, elevations),
                    crop=widest_crop(params, scene_at.extents, record.radius, params.tile_size))
    formats = map_formats(params.compress, params.uv_format, params.detail_map)
    prober = Prober(ranges, replace(record, layout=asked.to_manifest()), scene_at, formats, scene_at.has_regions)
    return ProbeSetting(params, cycle.ranges is not None, ranges, elevations, asked, scene_at, prober, record)


def layout_probes(setting: ProbeSetting) -> dict[str, Any]:
    """The tile, azimuth and ring probes (module docstring) at one pose frame: {"at_views": {tile: SSIM},
    "azimuths": {count: SSIM}, "elevation_loss": SSIM lost halfway between rings}."""
    params, asked, prober = setting.params, setting.asked, setting.prober
    probe_frame = setting.ranges.clips[0].first_frame
    at_views = {}
    for tile in impostor_layout.tile_ladder(params.tile_size, largest_tile(params, len(setting.elevations))):
        probe, cameras = at_views_probe(replace(asked, tile_size=tile, crop=setting.widest(tile)))
        at_views[tile] = prober.views_score(probe, probe_frame, cameras)
    ring = asked.elevations_deg[len(setting.elevations) // 2]
    azimuths = {}
    for count in impostor_layout.probed_azimuths(params.azimuths):
        probe, cameras = azimuth_gap_probe(params.tile_size, count, ring, asked.crop)
        azimuths[count] = prober.views_score(probe, probe_frame, cameras)
    elevation = elevation_gap_probe(asked)
    loss = 0.0 if elevation is None else at_views[params.tile_size] - prober.views_score(elevation[0], probe_frame, elevation[1])
    return {"at_views": at_views, "azimuths": azimuths, "elevation_loss": loss}


def range_probes(setting: ProbeSetting, index: int) -> dict[int, float]:
    """{count: SSIM} of range `index` (ranges.all() order) over its ladder, as Prober.range_table probes it."""
    counts = impostor_allocation.ladders(setting.ranges, setting.params.impostor_frames)[index]
    return setting.prober.range_table(index, counts)


def budget_of(setting: ProbeSetting) -> float | None:
    """The impostor budget in MiB: params.impostor_archetype_mib for several clips, params.impostor_budget_mib
    for one (None: no budget)."""
    return setting.params.impostor_archetype_mib if setting.several else setting.params.impostor_budget_mib


def layout_candidates(setting: ProbeSetting, probed: dict[str, Any], probed_tables: list[dict[int, float]]) -> list[impostor_layout.LayoutOption]:
    """Every (tile, azimuths) pair with its frames within the budget and its predicted scores
    (crowdbake.bake.impostor_layout.options), from the probes (layout_probes, range_probes per range)."""
    params, ranges = setting.params, setting.ranges
    budget_mib = budget_of(setting)
    frame_tables = [impostor_allocation.interpolated(table, counts)
                    for table, counts in zip(probed_tables, impostor_allocation.ladders(ranges, params.impostor_frames))]
    azimuth_scores = impostor_allocation.interpolated(probed["azimuths"], impostor_layout.azimuth_ladder(params.azimuths))
    return impostor_layout.options(ranges, frame_tables, probed["at_views"], azimuth_scores, probed["elevation_loss"], params.tile_size,
                                   setting.frame_bytes, None if budget_mib is None else budget_mib * MIB)


def one_clip_shortlist(setting: ProbeSetting, candidates: list[impostor_layout.LayoutOption],
                       at_views: dict[int, float]) -> list[impostor_layout.LayoutOption]:
    """One clip: the SHORTLIST best predicted pairs and the rule's own choice (the probe scene's framing),
    which the plan measures end to end (the losses do not add exactly), so that the choice is never worse
    than the rule's by the probes."""
    record, asked_tile = setting.record, setting.params.tile_size
    budget_mib = budget_of(setting)
    rule_frames = list(record.frame_indices)
    rule_azimuths = len(AtlasLayout.from_manifest(record.layout).azimuths_deg)
    rule_bytes = int(round(len(rule_frames) * setting.frame_bytes(asked_tile, rule_azimuths)))
    rule = impostor_layout.LayoutOption(asked_tile, rule_azimuths, impostor_allocation.Allocation(
        [len(rule_frames)], [rule_frames], rule_bytes, budget_mib is None or rule_bytes <= budget_mib * MIB, [float("nan")]),
        at_views[asked_tile], [float("nan")], float("nan"))
    shortlist = impostor_layout.shortlist(candidates, SHORTLIST)
    if all((o.tile, o.azimuths, o.allocation.frames) != (rule.tile, rule.azimuths, rule.allocation.frames) for o in shortlist):
        shortlist.append(rule)
    return shortlist


def check_score(setting: ProbeSetting, tile: int, azimuths: int, frames: list[int]) -> float:
    """The end-to-end score of a one-clip option of `tile`² tiles, `azimuths` a ring and baked `frames`
    (Prober.between_score, in the widest crop at that tile)."""
    return setting.prober.between_score(0, list(frames), tile, azimuths, setting.elevations, setting.widest(tile))


def measured_framing(setting: ProbeSetting, probed: dict[str, Any], probed_tables: list[dict[int, float]],
                     between: Callable[[int, impostor_layout.LayoutOption], float] | None = None) -> tuple[AtlasLayout, list[int], dict]:
    """The layout, baked frames and budget account chosen by measuring (module docstring) from the probes
    (layout_probes, range_probes per range): the tile and azimuth count (crowdbake.bake.impostor_layout)
    and every range's frames (impostor_allocation) within the budget (budget_of). between(k, option): for
    one clip, the end-to-end score of the shortlist's k-th option (the plan reads stage_impostor_check's);
    None: check_score here."""
    params, ranges, elevations, record = setting.params, setting.ranges, setting.elevations, setting.record
    several = setting.several
    budget_mib = budget_of(setting)
    asked_tile = params.tile_size
    at_views, probed_azimuths, elevation_loss = probed["at_views"], probed["azimuths"], probed["elevation_loss"]
    candidates = layout_candidates(setting, probed, probed_tables)
    checked = None
    if several:
        chosen = impostor_layout.choose_layout(candidates)
    else:
        shortlist = one_clip_shortlist(setting, candidates, at_views)
        if between is None:
            def between(_k: int, o: impostor_layout.LayoutOption) -> float:
                return check_score(setting, o.tile, o.azimuths, o.allocation.frames[0])
        checked = [impostor_layout.measured(option, between(k, option)) for k, option in enumerate(shortlist)]
        chosen = impostor_layout.choose_layout(checked)
    allocation = chosen.allocation
    frame_indices = allocation.frame_indices()
    layout = AtlasLayout.rings(chosen.tile, chosen.azimuths, elevations)
    if params.crop:
        layout = replace(layout, crop=crop_for(setting.scene_at.extents, frame_indices, record.radius, chosen.tile))
    frame_mib = setting.frame_bytes(chosen.tile, chosen.azimuths)
    account = impostor_allocation.allocation_document(ranges, probed_tables, allocation, budget_mib, frame_mib)
    logger.info("impostor by measuring: tile %d, %d azimuths, frames %s (%.1f MiB of %s)", chosen.tile, chosen.azimuths,
                ", ".join(f"{r['name']} {r['baked_frames']}" for r in account["ranges"]), account["mib"],
                "no budget" if budget_mib is None else f"{budget_mib:g}")
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


def stage_impostor_scene(work: Path, progress: Progress | None = None) -> StageOutcome[ImpostorPlan]:
    """What the probes and the plan start from, in work/impostor-probes: the framing by the rule (several
    clips chosen by measuring: the bounds alone, the asked layout and a first frame standing until the
    plan replaces them) and, in scene.npz, the high LOD at every pose frame with the textures the tasks
    draw with and each frame's extents (FrameExtents). The same high_parts as the poses stage's, without
    its LODs and texture compression."""
    started = time.perf_counter()
    folder = WorkDir(work)
    # Its scene is the caches' geometry: stale when their kind changes.
    key = stage_key("impostor-scene", folder.key_of("cycle"), QUANTIZED_POSE_CACHE_VERSION, SKINNED_POSE_CACHE_MAGIC.decode(), ALLOCATION)
    scene_path = folder.root / PROBES / SCENE_FILE
    cached = folder.cached(PROBES, key, ImpostorPlan, [scene_path])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)
    job = load_job(work)
    params = job.bake_params
    cycle = folder.load("cycle", CycleRecord)
    character = load_character(folder.inputs / job.inputs["character"], animation=params.animation)
    materials, outfits = materials_of(job, folder.inputs, character, first_layer_only=True)
    high, _, part_material = high_parts(job, cycle, folder, character)
    part_material = part_materials(part_material, materials)
    if measures(params, cycle) and cycle.ranges is not None:
        # The per-clip rule's framing is no candidate for several clips: only its bounds are needed.
        bounds, budget = framing_bounds(high), None
        layout, frame_indices = AtlasLayout.rings(params.tile_size, params.azimuths, tuple(params.elevations_deg)), [0]
    else:
        bounds, layout, frame_indices, budget = impostor_framing(params, cycle, high)
    arrays: dict[str, np.ndarray] = {}
    has_regions = []
    for index, material in enumerate(materials):
        layers = material["layers"]
        pixel_format = diffuse_format(layers, params.compress)
        height, width = layers.shape[1:3]
        arrays[f"diffuse_{index}"] = layers[0]
        # What a runtime samples: variation 0 through the bundle's block compression (as the poses stage encodes it).
        arrays[f"runtime_{index}"] = compression.decode(compression.encode(layers[0], pixel_format), pixel_format, width, height)
        has_regions.append(pixel_format != "bc1")
    positions = np.concatenate([np.asarray(part.positions) for part in high.values()], axis=1)
    extents = frame_extents(positions, bounds["center"], tuple(params.elevations_deg))
    arrays.update(scene_arrays(high, part_material, list(range(len(positions)))), outfit_row=outfits[0], has_regions=np.array(has_regions),
                  material_count=np.array(len(materials)), extent_reach=extents.reach, extent_low=extents.low, extent_high=extents.high)
    write_bytes_atomic(scene_path, npz_bytes(arrays))
    record = ImpostorPlan(bounds=bounds, layout=layout.to_manifest(), frame_indices=frame_indices, fidelity_frame=frame_indices[0],
                          material_count=len(materials), ranges=cycle.ranges, budget=budget)
    seconds = time.perf_counter() - started
    folder.save(PROBES, key, record, seconds)
    return StageOutcome(record, False, seconds)


def probe_items(work: Path) -> list[dict[str, Any]]:
    """The plan's probes, each a unit of work of its own (the local runner runs them side by side): the
    layout's (tiles, azimuths, rings) and one per clip and transition; none where the plan does not measure."""
    folder = WorkDir(work)
    params = load_job(work).bake_params
    cycle = folder.load("cycle", CycleRecord)
    if not measures(params, cycle):
        return []
    ranges = cycle.bundle_ranges() if cycle.ranges is not None else one_clip_ranges(cycle)
    return [{"id": "layout"}] + [{"id": f"range-{index}", "range": index} for index in range(len(ranges.all()))]


def probe_path(work: Path, item: dict[str, Any]) -> Path:
    if not re.fullmatch(r"layout|range-\d+|check-\d+", str(item.get("id", ""))):
        raise ValueError(f"impostor probe id {item.get('id')!r} is not a probe's")
    return Path(work) / PROBES / f"{item['id']}.json"


def _kept_or_made(work: Path, item: dict[str, Any], key: str, make: Callable[[ProbeSetting], dict[str, Any]]) -> dict[str, Any]:
    """work/impostor-probes/<id>.json of a probe or check item where it holds `key`; else make(setting) written
    there with its key and seconds (JSON: counts and tiles as text). Returns the document."""
    started = time.perf_counter()
    path = probe_path(work, item)
    try:
        stored = read_json(path)
        if stored.get("key") == key:
            return stored
    except (OSError, ValueError):
        pass
    setting = probe_setting(work)
    try:
        made = make(setting)
    finally:
        setting.scene_at.close()
    document = json.loads(json.dumps({"key": key, **made, "seconds": round(time.perf_counter() - started, 3)}))
    write_json_atomic(path, document)
    return document


def stage_impostor_probe(work: Path, item: dict[str, Any]) -> dict[str, Any]:
    """One probe item's scores (layout_probes, or range_probes of item["range"]), kept for the same probe
    scene (_kept_or_made)."""
    def make(setting: ProbeSetting) -> dict[str, Any]:
        return layout_probes(setting) if item["id"] == "layout" else {"table": range_probes(setting, int(item["range"]))}

    return _kept_or_made(work, item, stage_key("impostor-probe", WorkDir(work).key_of(PROBES), item["id"]), make)


def _probed(work: Path, items: list[dict[str, Any]]) -> tuple[dict[str, Any], list[dict[int, float]]]:
    """The probes' scores (stage_impostor_probe of each item, read back where they were drawn already) as
    measured_framing takes them: the layout's and one {count: SSIM} table per range."""
    probes = {item["id"]: stage_impostor_probe(work, item) for item in items}
    layout_scores = probes["layout"]
    probed = {"at_views": _counted(layout_scores["at_views"]), "azimuths": _counted(layout_scores["azimuths"]),
              "elevation_loss": float(layout_scores["elevation_loss"])}
    return probed, [_counted(probes[item["id"]]["table"]) for item in items[1:]]


def check_items(work: Path) -> list[dict[str, Any]]:
    """One clip measured: the shortlisted options (one_clip_shortlist), each measured end to end as a unit
    of work of its own (the local runner runs them side by side); none otherwise. Needs the probes done."""
    items = probe_items(work)
    if not items:
        return []
    setting = probe_setting(work)
    try:
        if setting.several:
            return []
        probed, tables = _probed(work, items)
        shortlist = one_clip_shortlist(setting, layout_candidates(setting, probed, tables), probed["at_views"])
    finally:
        setting.scene_at.close()
    return [check_item(k, option) for k, option in enumerate(shortlist)]


def check_item(k: int, option: impostor_layout.LayoutOption) -> dict[str, Any]:
    """The k-th shortlisted option of one clip as a check item."""
    return {"id": f"check-{k}", "tile": option.tile, "azimuths": option.azimuths, "frames": list(option.allocation.frames[0])}


def stage_impostor_check(work: Path, item: dict[str, Any]) -> dict[str, Any]:
    """One shortlisted option's end-to-end score (check_score), kept for the same probe scene and option
    (_kept_or_made): {"key", "ssim", "seconds"}."""
    def make(setting: ProbeSetting) -> dict[str, Any]:
        return {"ssim": float(check_score(setting, int(item["tile"]), int(item["azimuths"]), [int(f) for f in item["frames"]]))}

    key = stage_key("impostor-check", WorkDir(work).key_of(PROBES), item["id"], item["tile"], item["azimuths"], *item["frames"])
    return _kept_or_made(work, item, key, make)


def _counted(scores: dict[str, float]) -> dict[int, float]:
    """A probe file's {count or tile as text: SSIM} as {int: float}."""
    return {int(count): float(score) for count, score in scores.items()}


def stage_impostor_plan(work: Path, progress: Progress | None = None) -> StageOutcome[ImpostorPlan]:
    """The impostors' framing, baked frames and scene (work/impostor/scene.npz): the probe scene's rule
    framing (stage_impostor_scene), or chosen from its probes (stage_impostor_probe; each done already
    where the runner ran it as an item of its own, else here)."""
    started = time.perf_counter()
    folder = WorkDir(work)
    scene = stage_impostor_scene(work, progress)
    key = stage_key("impostor-plan", folder.key_of(PROBES))
    scene_path = folder.root / "impostor" / SCENE_FILE
    cached = folder.cached("impostor", key, ImpostorPlan, [scene_path])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)
    report(progress, "impostor-plan", 0, 1)
    record = scene.record
    items = probe_items(work)
    frames = StoredFrames(folder.root / PROBES / SCENE_FILE)
    try:
        if items:
            probed, tables = _probed(work, items)
            setting = probe_setting(work)
            try:
                # One clip's checks as their items left them (or measured now, where no runner ran them).
                layout, frame_indices, budget = measured_framing(
                    setting, probed, tables, lambda k, option: float(stage_impostor_check(work, check_item(k, option))["ssim"]))
            finally:
                setting.scene_at.close()
            record = replace(record, layout=layout.to_manifest(), frame_indices=frame_indices, fidelity_frame=frame_indices[0], budget=budget)
        write_bytes_atomic(scene_path, npz_bytes(frames.plan_arrays(record.frame_indices)))
    finally:
        frames.close()
    seconds = time.perf_counter() - started
    folder.save("impostor", key, record, seconds)
    report(progress, "impostor-plan", 1, 1)
    return StageOutcome(record, False, seconds)
