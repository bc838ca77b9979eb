"""Stage 2, cycle: find and close the cloth's walk cycle (paper section 3), or take the given cycle.json.

Reads the JobRecord; writes work/cycle/cycle.json, work/cycle/looped.pc2 (exactly cycle_frames frames,
frame 0 = Fs), the report (crowdbake.stages.cycle_report) and the CycleRecord. The search is the
`crowdbake cycle` job (crowdbake.stages.cycle_job). A bake of several clips (a timeline) has each clip's
loop searched by the loops stage first (crowdbake.stages.loops, side by side); this stage then joins them
and finds the transitions.
"""
from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

from crowdbake.bake.cycle import CycleParams
from crowdbake.bake.loop_closing import close_cycle
from crowdbake.bake.bounds import OutOfBounds, bounds_message
from crowdbake.errors import InputError, OutOfBoundsError
from crowdbake.formats.obj import read_obj
from crowdbake.formats.pc2 import read_pc2, write_pc2
from crowdbake.params import BASE_FPS
from crowdbake.stages.body_only import animation_loop_cycle
from crowdbake.stages.cycle_job import run_cycle_job
from crowdbake.stages.loops import load_clip_loops
from crowdbake.stages.records import CycleRecord, JobRecord
from crowdbake.stages.validate import load_job
from crowdbake.stages.workdir import Progress, StageOutcome, WorkDir, read_json, report, stage_key, write_json_atomic

logger = logging.getLogger(__name__)


def bundle_cycle_document(document: dict) -> dict:
    """cycle.json as published: without timings and local paths, which differ between runs."""
    cleaned = json.loads(json.dumps(document))
    cleaned.pop("timings_s", None)
    cleaned.pop("files", None)
    if isinstance(cleaned.get("input"), dict):
        cleaned["input"].pop("sources", None)
    cleaned.pop("bundle_ranges", None)  # several clips: the manifest's clips and transitions say it
    for entry in [*cleaned.get("clips", []), *cleaned.get("transitions", [])]:  # several clips: work files, not the bundle's
        entry.pop("file", None)
        entry.pop("figures", None)
        entry.pop("timings_s", None)
    return cleaned


def _given_cycle(job: JobRecord, inputs: Path, cycle_json: Path, looped: Path, progress: Progress | None) -> dict:
    """A cycle chosen earlier: reuse its looped cache when it came along, else close it again."""
    names = job.inputs
    document = read_json(inputs / names["cycle"])
    start, frames = int(document["start_frame"]), int(document["cycle_frames"])
    method = (document.get("closing") or {}).get("method", "none")
    cache = read_pc2(inputs / names["cloth"])
    looped_points = None
    if "cycle_looped" in names:
        given = read_pc2(inputs / names["cycle_looped"])
        if given.points.shape == (frames, cache.point_count, 3):
            looped_points = given.points
        else:
            logger.warning("looped.pc2 beside cycle.json has shape %s, not (%d, %d, 3); closing again", given.points.shape, frames, cache.point_count)
    if looped_points is None:
        if start + frames + 1 > cache.sample_count and method != "none":
            raise InputError(f"closing the cycle needs frame {start + frames}, the cache ends at {cache.sample_count - 1}", "cycle")
        if method == "none":
            looped_points = cache.points[start : start + frames]
        else:
            faces = read_obj(inputs / names["cloth_mesh"]).faces if "cloth_mesh" in names else None
            looped_points = close_cycle(cache.points, start, frames, method, cloth_faces=faces).looped
    document.setdefault("end_frame", start + frames)
    document.setdefault("input", {})
    if document["input"].get("fps") is None:  # absent or null (crowdbake.ingest.cycle_document checked the rest)
        document["input"]["fps"] = job.fps if job.fps is not None else BASE_FPS / cache.sample_rate
    write_json_atomic(cycle_json, document)
    write_pc2(looped, looped_points, start_frame=0.0, sample_rate=cache.sample_rate)
    report(progress, "cycle", 1, 1)
    return document


def _check_given_bounds(document: dict, accept: bool) -> None:
    """OutOfBoundsError when a given cycle.json lists figures out of bounds (`crowdbake cycle
    --accept-out-of-bounds` wrote it) and this bake does not accept them too."""
    try:
        breaks = [OutOfBounds(str(item["where"]), (int(item["cache_frames"][0]), int(item["cache_frames"][1])), str(item["figure"]),
                              math.inf if item["value"] is None else float(item["value"]), float(item["bound"]))
                  for item in document.get("out_of_bounds") or []]
    except (KeyError, TypeError, ValueError, IndexError):
        raise InputError("cycle.json: /out_of_bounds must list objects with where, cache_frames, figure, value and bound", "cycle") from None
    if breaks and not accept:
        raise OutOfBoundsError(f"the given cycle: {bounds_message(breaks)}")


def _searched_cycle(job: JobRecord, work: Path, out: Path, progress: Progress | None, plots: list | None = None) -> dict:
    inputs = WorkDir(work).inputs
    params = job.bake_params
    names = job.inputs
    cycle_params = CycleParams(max_candidates=params.candidates, views=params.cycle_views, close=params.close)

    def forward(stage: str, done: int, total: int) -> None:
        report(progress, f"cycle:{stage}", done, total)

    try:
        run_cycle_job(
            inputs / names["cloth"],
            inputs / names["cloth_mesh"],
            out,
            character=inputs / names["character"],
            cycle_frames=params.cycle_frames,
            # The staged cache is in Y-up metres already (validate placed it); its rate is the job's.
            fps=job.fps,
            params=cycle_params,
            animation=params.animation,
            progress=forward,
            plots=True if plots is None else plots,
            timeline=inputs / names["timeline"] if "timeline" in names else None,
            # Every clip's loop, searched side by side by the loops stage: only the transitions are left.
            loops=load_clip_loops(work) if "timeline" in names else None,
            accept_out_of_bounds=params.accept_out_of_bounds,
        )
    except OutOfBoundsError:
        raise
    except ValueError as error:
        raise InputError(f"cycle search: {error}", "cloth") from None
    return read_json(out / "cycle.json")


def stage_cycle(work: Path, progress: Progress | None = None, plots: list | None = None) -> StageOutcome[CycleRecord]:
    """Find and close the cloth cycle (run_cycle_job), or take the given cycle.json; with a timeline, join
    the loops the loops stage searched (crowdbake.stages.loops) and find the transitions.

    plots: a list to append the report's plotting to (a callable) instead of drawing it here: nothing
    later reads the plots, so a caller may draw them beside the next stages."""
    started = time.perf_counter()
    folder = WorkDir(work)
    job = load_job(work)
    # A timeline's cycle stage also lays out the bundle's ranges (CycleRecord.ranges): stamps without them are stale.
    key = stage_key("cycle", folder.key_of("validate"), *(["bundle-ranges"] if "timeline" in job.inputs else []))
    out = folder.root / "cycle"
    cycle_json, looped = out / "cycle.json", out / "looped.pc2"
    body_only = "cloth" not in job.inputs  # crowdbake.stages.body_only: the animation's own loop, no looped cloth
    cached = folder.cached("cycle", key, CycleRecord, [cycle_json] if body_only else [cycle_json, looped])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)
    out.mkdir(parents=True, exist_ok=True)
    if body_only:
        document = animation_loop_cycle(job.cycle_frames, job.fps)
        write_json_atomic(cycle_json, document)
        report(progress, "cycle", 1, 1)
    elif "cycle" in job.inputs:
        document = _given_cycle(job, folder.inputs, cycle_json, looped, progress)
        _check_given_bounds(document, job.bake_params.accept_out_of_bounds)
    else:
        document = _searched_cycle(job, folder.root, out, progress, plots)

    if document.get("bundle_refused"):
        raise InputError(f"timeline: {document['bundle_refused']}", "timeline")
    seam = document.get("seam") or {}
    record = CycleRecord(
        start_frame=int(document["start_frame"]),
        end_frame=int(document.get("end_frame", document["start_frame"] + document["cycle_frames"])),
        cycle_frames=int(document["cycle_frames"]),
        closing=(document.get("closing") or {}).get("method", "none"),
        position_jump_ratio=seam.get("position_jump_ratio"),
        velocity_jump_ratio=seam.get("velocity_jump_ratio"),
        fps=float((document.get("input") or {}).get("fps") or BASE_FPS),
        root_motion_removed=bool((document.get("root_motion") or {}).get("removed", False)),
        source=document.get("source") or ("given" if "cycle" in job.inputs else "search"),
        clip_phase=document.get("clip_phase"),
        ranges=document.get("bundle_ranges"),
    )
    seconds = time.perf_counter() - started
    folder.save("cycle", key, record, seconds)
    return StageOutcome(record, False, seconds)
