"""Stage 2, cycle: find and close the cloth's walk cycle (paper section 3), or take the given cycle.json.

Reads the JobRecord; writes work/cycle/cycle.json, work/cycle/looped.pc2 (exactly cycle_frames frames,
frame 0 = Fs), the report (crowdbake.stages.cycle_report) and the CycleRecord. The cloth cache is read once.
A bake of several clips (a timeline) has each clip's loop searched by the loops stage first
(crowdbake.stages.loops, side by side); this stage then joins them and finds the transitions.
`crowdbake cycle` runs the same search outside a bake:

    run_cycle_job(cloth_pc2, cloth_obj, out_dir, character=... | body_pc2=..., body_obj=...) -> CycleResult

Frame rate (crowdbake.params.cache_fps): `fps` when the caller passes it, else the cache's own (MDD frame
times, Alembic time sampling), else BASE_FPS / sample_rate with BASE_FPS = 24 (the film rate the sample
content and most DCC scenes use): a PC2 file stores the interval between samples in frames, not a rate.
The cycle length, when not given, is the character's animation duration times that rate.
"""
from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.bake.cycle import CycleParams, CycleResult, find_cycle
from crowdbake.bake.loop_closing import close_cycle
from crowdbake.errors import InputError
from crowdbake.formats.obj import read_obj
from crowdbake.formats.pc2 import read_pc2, write_pc2
from crowdbake.params import BASE_FPS, min_cloth_frames
from crowdbake.stages.body_only import animation_loop_cycle
from crowdbake.stages.cycle_report import report_html, write_cycle_plots, write_edge_images
from crowdbake.stages.records import CycleRecord, JobRecord
from crowdbake.stages.validate import load_job
from crowdbake.stages.workdir import Progress, StageOutcome, WorkDir, read_json, report, stage_key, write_json_atomic

logger = logging.getLogger(__name__)

# The animation's duration times the frame rate must be this close to a whole number of frames for the
# body to be tiled from one posed cycle; otherwise each frame is posed at its own wrapped time.
_WHOLE_FRAME_TOLERANCE = 1e-3


@dataclass
class CycleInputs:
    """Arrays for find_cycle plus what the files said.

    cloth: (F, V, 3) float32 in PC2 point order; cloth_faces: (T, 3) int64 into those points.
    body: (F, Vb, 3) float32 or None; body_faces (Tb, 3) int64; body_normals (F, Vb, 3) or None.
    cycle_frames: l; fps: the cache's frame rate; sample_rate/start_frame: from the cloth PC2 header.
    """

    cloth: np.ndarray
    cloth_faces: np.ndarray
    body: np.ndarray | None
    body_faces: np.ndarray | None
    body_normals: np.ndarray | None
    cycle_frames: int
    fps: float
    sample_rate: float
    start_frame: float
    cycle_frames_source: str
    sources: dict


def _pose_body(character, fps: float, frame_count: int) -> tuple[np.ndarray, np.ndarray]:
    """The character's looping animation at the cache's frames: frame f at time (f / fps) mod duration."""
    from crowdbake.bake.skinning import pose_character

    duration = float(character.animation_duration)
    if duration <= 0:
        raise ValueError("the character has no animation to pose the body with")
    frames_per_loop = duration * fps
    whole = round(frames_per_loop)
    if whole >= 1 and abs(frames_per_loop - whole) < _WHOLE_FRAME_TOLERANCE:
        positions, normals = pose_character(character, fps, min(whole, frame_count))
        index = np.arange(frame_count) % whole
        return positions[index], normals[index]
    posed = [pose_character(character, fps, 1, start_time=(f / fps) % duration) for f in range(frame_count)]
    return np.concatenate([p for p, _ in posed]), np.concatenate([n for _, n in posed])


def _check_two_cycles(frame_count: int, cycle_frames: int, path) -> None:
    if cycle_frames < 2:
        raise ValueError(f"the cycle length must be at least 2 frames, got {cycle_frames}")
    if frame_count < min_cloth_frames(cycle_frames):
        raise ValueError(
            f"too few frames for two cycles: {path} has {frame_count} frames, two cycles of {cycle_frames} need {min_cloth_frames(cycle_frames)}"
        )


def _pc2_start_frame(path: str | os.PathLike) -> float:
    """A PC2 header's startFrame (recorded in cycle.json); 0 for the other caches, which start at their first sample."""
    import struct

    if Path(path).suffix.lower() != ".pc2":
        return 0.0
    with open(path, "rb") as handle:
        return float(struct.unpack("<f", handle.read(24)[20:24])[0])


def load_cycle_inputs(
    cloth_pc2: str | os.PathLike,
    cloth_obj: str | os.PathLike | None = None,
    character: str | os.PathLike | None = None,
    body_pc2: str | os.PathLike | None = None,
    body_obj: str | os.PathLike | None = None,
    cycle_frames: int | None = None,
    fps: float | None = None,
    up: str | None = None,
    units: str | None = None,
    animation: int | str | None = None,
    pose_body: bool = True,
) -> CycleInputs:
    """Read and cross-check the cycle search's input files. Raises ValueError with a one-line reason.

    cloth_pc2: any cloth cache crowdbake reads (.pc2 or .mdd with `cloth_obj`, .abc or an OBJ-sequence
    .zip alone; crowdbake.ingest.garment.read_cloth). fps: None takes the cache's own rate
    (crowdbake.params.cache_fps). The cloth's first frame is checked against the body's
    (crowdbake.ingest.garment.place_cloth) and converted to Y-up metres when up/units say so.
    pose_body: False leaves a character's body unposed (body None, its faces set): a timeline's search
    poses it per clip (crowdbake.stages.clip_loops.pose_clips_body)."""
    from crowdbake.formats.obj import read_obj
    from crowdbake.formats.pc2 import read_pc2
    from crowdbake.ingest.garment import place_cloth, read_cloth
    from crowdbake.params import cache_fps

    if character is not None and (body_pc2 is not None or body_obj is not None):
        raise ValueError("give the body either as a character (.glb) or as a body cache and mesh, not both")
    if (body_pc2 is None) != (body_obj is None):
        raise ValueError("a body cache needs its mesh: give both --body and --body-mesh")
    cache = read_cloth(cloth_pc2, cloth_obj)
    cloth_faces = cache.mesh.source_index[cache.faces.astype(np.int64)]
    frame_rate = cache_fps(fps, cache.fps, cache.frame_step)
    if not frame_rate > 0:
        raise ValueError(f"fps must be positive, got {frame_rate}")
    frame_count = cache.frame_count
    sources = {"cloth_cache": str(cloth_pc2)}
    if cloth_obj is not None:
        sources["cloth_mesh"] = str(cloth_obj)
    if cycle_frames is not None:
        _check_two_cycles(frame_count, int(cycle_frames), cloth_pc2)

    body = body_faces = body_normals = None
    loaded_character = None
    if character is not None:
        from crowdbake.formats.gltf import load_character

        if animation is None:  # not told: the clip the cloth repeats after (crowdbake.ingest.clip_choice)
            from crowdbake.ingest.clip_choice import character_clips, choose_clip

            clips = character_clips(character)
            animation = choose_clip(clips, cache.frames, frame_rate).index if len(clips) > 1 and cycle_frames is None else 0
        loaded_character = load_character(character, animation=animation)
        # The garment must sit on the character before a minute of search is spent on it.
        from crowdbake.ingest.garment import body_at_rest

        cache = place_cloth(cache, body_at_rest(loaded_character), up, units)
        if pose_body:
            body, body_normals = _pose_body(loaded_character, frame_rate, frame_count)
        body_faces = np.asarray(loaded_character.faces, dtype=np.int64)
        sources["character"] = str(character)
    elif body_pc2 is not None:
        body_cache = read_pc2(body_pc2)
        body_mesh = read_obj(body_obj)
        if body_mesh.position_count != body_cache.point_count:
            raise ValueError(
                f"vertex counts do not match: {body_obj} has {body_mesh.position_count} positions, {body_pc2} has {body_cache.point_count} points"
            )
        if body_cache.sample_count != frame_count:
            raise ValueError(f"frame counts do not match: {body_pc2} has {body_cache.sample_count} frames, {cloth_pc2} has {frame_count}")
        if len(body_mesh.faces) == 0:
            raise ValueError(f"{body_obj} has no faces")
        body = body_cache.points
        # The body cache is taken as Y-up metres, like a character; up/units convert the cloth only.
        cache = place_cloth(cache, body[0], up, units)
        body_faces = body_mesh.source_index[body_mesh.faces.astype(np.int64)]
        sources.update(body_cache=str(body_pc2), body_mesh=str(body_obj))

    if cycle_frames is not None:
        length, origin = int(cycle_frames), "given"
    elif loaded_character is not None:
        length, origin = int(round(loaded_character.animation_duration * frame_rate)), "character animation"
    else:
        raise ValueError("the cycle length is unknown: give --cycle-frames (a body cache carries no animation length)")
    _check_two_cycles(frame_count, length, cloth_pc2)
    return CycleInputs(
        cloth=cache.frames,
        cloth_faces=cloth_faces,
        body=body,
        body_faces=body_faces,
        body_normals=body_normals,
        cycle_frames=length,
        fps=frame_rate,
        sample_rate=cache.frame_step,
        start_frame=_pc2_start_frame(cloth_pc2),
        cycle_frames_source=origin,
        sources=sources,
    )


def run_cycle_job(
    cloth_pc2: str | os.PathLike,
    cloth_obj: str | os.PathLike,
    out_dir: str | os.PathLike,
    character: str | os.PathLike | None = None,
    body_pc2: str | os.PathLike | None = None,
    body_obj: str | os.PathLike | None = None,
    cycle_frames: int | None = None,
    fps: float | None = None,
    params: CycleParams = CycleParams(),
    up: str | None = None,
    units: str | None = None,
    animation: int | str | None = None,
    progress: Progress | None = None,
    edge_pass: bool = True,
    plots: bool = True,
    timeline: str | os.PathLike | None = None,
    loops: list | None = None,
) -> CycleResult:
    """The whole `crowdbake cycle` job: files in, cycle.json + looped.pc2 + report.html out.

    edge_pass: run pass 2 (rendering under OSMesa/EGL); False picks the best pass-1 candidate.
    plots: draw the report's plots now; False leaves them to write_cycle_plots(result, out_dir).
    timeline: a clip timeline (crowdbake.ingest.timeline): a loop per clip and the transitions between
        them (crowdbake.stages.clip_loops); the primary clip's loop is the one written as looped.pc2.
    loops: with a timeline, every clip's loop searched already (crowdbake.stages.loops, in the timeline's
        order): only the transitions are searched here.
    Raises ValueError on bad input (with a one-line reason).
    """
    report = progress or (lambda stage, done, total: None)
    report("load", 0, 1)
    clips = None
    if timeline is not None:
        from crowdbake.ingest.timeline import read_timeline
        from crowdbake.stages.clip_loops import primary_clip

        clips = read_timeline(Path(timeline))
        animation = primary_clip(clips, animation)
        cycle_frames = clips.period(animation)
    # A timeline with a character poses the body per clip (clip_loops.pose_clips_body), not with one clip's animation.
    inputs = load_cycle_inputs(cloth_pc2, cloth_obj, character, body_pc2, body_obj, cycle_frames, fps, up, units, animation,
                               pose_body=clips is None or character is None)
    report("load", 1, 1)
    render_views = None
    if edge_pass and loops is None:
        from crowdbake.render.cloth_views import ClothViewRenderer

        render_views = ClothViewRenderer(
            inputs.cloth_faces, inputs.body_faces, params.views, params.image_size, params.elevation_deg
        )
    sections = None
    if clips is not None:
        from crowdbake.stages.clip_loops import run_timeline

        result, sections = run_timeline(inputs, clips, Path(timeline), character, out_dir, params, animation, render_views, progress,
                                        loops)
    else:
        result = find_cycle(
            inputs.cloth, inputs.cloth_faces, inputs.body, inputs.body_faces, inputs.cycle_frames,
            params, render_views, body_normals=inputs.body_normals, progress=progress,
        )
    report("report", 0, 1)
    write_cycle_outputs(result, out_dir, inputs, plots=plots, sections=sections)
    report("report", 1, 1)
    return result


def write_cycle_outputs(result: CycleResult, out_dir: str | os.PathLike, inputs: CycleInputs | None = None,
                        plots: bool = True, sections: dict | None = None) -> dict[str, Path]:
    """Write cycle.json, looped.pc2, the PNG plots, the edge images and report.html; returns the paths.

    plots: False skips the matplotlib plots (a second or more), for write_cycle_plots to draw later (the bake
    runner draws them beside the next stages); every other file, the report's links included, is written."""
    from crowdbake.formats.pc2 import write_pc2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "cycle_json": out / "cycle.json",
        "looped_cache": out / "looped.pc2",
        "report": out / "report.html",
        "pass1_plot": out / "pass1.png",
        "seam_plot": out / "seam.png",
        "candidates_plot": out / "candidates.png",
    }
    sample_rate = inputs.sample_rate if inputs is not None else 1.0
    write_pc2(paths["looped_cache"], result.looped, start_frame=0.0, sample_rate=sample_rate)

    if result.winner_images is not None and result.winner_edges is not None:
        paths["edges_plot"] = out / "edges.png"
        paths.update(write_edge_images(result, out / "edges"))
    if plots:
        write_cycle_plots(result, out)

    document = result.to_dict()
    document["files"] = {name: path.relative_to(out).as_posix() for name, path in paths.items() if name != "cycle_json"}
    if inputs is not None:
        document["input"].update(
            fps=inputs.fps,
            sample_rate=inputs.sample_rate,
            pc2_start_frame=inputs.start_frame,
            cycle_frames_source=inputs.cycle_frames_source,
            sources=inputs.sources,
        )
    if sections is not None:  # several clips (crowdbake.stages.clip_loops): every loop and transition
        sources = sections.pop("sources", {})
        document.update(sections)
        if inputs is not None:
            document["input"]["sources"].update(sources)
    paths["cycle_json"].write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    paths["report"].write_text(report_html(result, document), encoding="utf-8")
    logger.info("cycle outputs written to %s", out)
    return paths



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


def _searched_cycle(job: JobRecord, work: Path, out: Path, progress: Progress | None, plots: list | None = None) -> dict:
    from crowdbake.stages.loops import load_clip_loops

    inputs = WorkDir(work).inputs
    params = job.bake_params
    names = job.inputs
    cycle_params = CycleParams(max_candidates=params.candidates, views=params.cycle_views, close=params.close)

    def forward(stage: str, done: int, total: int) -> None:
        report(progress, f"cycle:{stage}", done, total)

    try:
        result = run_cycle_job(
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
            plots=plots is None,
            timeline=inputs / names["timeline"] if "timeline" in names else None,
            # Every clip's loop, searched side by side by the loops stage: only the transitions are left.
            loops=load_clip_loops(work) if "timeline" in names else None,
        )
    except ValueError as error:
        raise InputError(f"cycle search: {error}", "cloth") from None
    if plots is not None:
        plots.append(lambda: write_cycle_plots(result, out))
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
