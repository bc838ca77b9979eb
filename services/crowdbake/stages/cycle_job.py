"""The `crowdbake cycle` job: the loop of every clip the cloth cache plays and the transitions between
them (crowdbake.bake.clips, crowdbake.bake.transitions), written as the cycle stage's outputs.

    run_cycle_job(cloth_pc2, cloth_obj, out_dir, character=... | body_pc2=..., body_obj=..., timeline=...) -> CycleResult

A cache without a timeline plays one clip over every frame (crowdbake.stages.cycle_inputs): its one loop
is searched as a timeline's clips are, and there is no transition. cycle.json is the single-clip
document of the *primary* clip (the one `animation` names, else the timeline's first), the loop a
bundle carries, in cache frame numbers; with a timeline, plus
  timeline      fps, total_frames and the segments;
  clips         every clip's loop: the single-clip document's fields (candidates, closing, quality...)
                with clip, period, segment, clip_phase and searched_frames;
  transitions   every simulated change of clip: from/to clip and segment, the loop frames where it
                leaves and arrives, its frames, the cache frames it spans, and each join's candidates and
                quality figures.
and, with a timeline or without, out_of_bounds (every figure of a loop or join over its bound,
crowdbake.bake.bounds) and accept_out_of_bounds (whether the bake keeps them; else the job fails).
Files: looped.pc2 (the primary loop), report.html and its plots (crowdbake.stages.cycle_report); with a
timeline, clips/<clip>.pc2 (every loop), transitions/<k>_<from>_<to>.pc2 and, for several clips,
pose_frames.pc2 (every loop and transition end to end: the bundle's pose cache, format v2).
"""
from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path

import numpy as np

from crowdbake.bake.bounds import bounds_message, join_where, out_of_bounds
from crowdbake.bake.clips import ClipLoop, find_clip_loops
from crowdbake.bake.cycle import CycleParams, CycleResult, _float, _quality_dict
from crowdbake.bake.pose_ranges import first_frames
from crowdbake.bake.timeline import Timeline
from crowdbake.bake.transitions import SLOW_SWITCH_RATIO, Join, Transition, find_transitions, transition_jump_ratios
from crowdbake.errors import OutOfBoundsError
from crowdbake.formats.pc2 import write_pc2
from crowdbake.formats.ranges import Clip, Ranges
from crowdbake.formats.ranges import Transition as BundleTransition
from crowdbake.stages.clips_report import clip_figures
from crowdbake.stages.cycle_inputs import CycleInputs, check_one_motion, load_cycle_inputs
from crowdbake.stages.clips_report import clips_report
from crowdbake.stages.cycle_report import report_html, write_cycle_plots, write_edge_images
from crowdbake.stages.workdir import Progress

logger = logging.getLogger(__name__)


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
    plots: bool | list = True,
    timeline: str | os.PathLike | None = None,
    loops: list[ClipLoop] | None = None,
    check_fit: bool = False,
    accept_out_of_bounds: bool = False,
) -> CycleResult:
    """The whole `crowdbake cycle` job: files in, cycle.json + looped.pc2 + report.html out; returns the
    primary clip's result in cache frames.

    edge_pass: run pass 2 (rendering under OSMesa/EGL); False picks the best pass-1 candidate.
    plots: True draws the report's plots now; a list receives the drawing as callables to run later (the
        bake runner draws them beside the next stages); False draws none.
    timeline: a clip timeline file (crowdbake.ingest.timeline), or None for a cache of one clip.
    loops: every clip's loop searched already (crowdbake.stages.loops, in the timeline's order): only the
        transitions are searched here.
    check_fit: refuse a garment that does not follow the character (crowdbake.ingest.garment.check_garment_fit;
        a character and no timeline only).
    accept_out_of_bounds: keep loops and transitions that break a quality bound (crowdbake.bake.bounds);
        without it the job writes its outputs, then raises OutOfBoundsError naming the first.
    Raises ValueError on bad input (with a one-line reason).
    """
    report = progress or (lambda stage, done, total: None)
    report("load", 0, 1)
    inputs = load_cycle_inputs(cloth_pc2, cloth_obj, character, body_pc2, body_obj, cycle_frames, fps, up, units, animation, timeline,
                               check_fit=check_fit)
    if timeline is None:  # one clip over every frame: the cache must be one motion
        check_one_motion(inputs.cloth, inputs.cycle_frames, params.settle_frames, Path(cloth_pc2).name)
    report("load", 1, 1)
    plays = inputs.timeline
    if loops is None:
        render_views = None
        if edge_pass:
            from crowdbake.render.cloth_views import ClothViewRenderer

            render_views = ClothViewRenderer(inputs.cloth_faces, inputs.body_faces, params.views, params.image_size, params.elevation_deg)
        loops = find_clip_loops(inputs.cloth, inputs.cloth_faces, plays, params, render_views, inputs.body, inputs.body_faces,
                                inputs.body_normals, progress)
    elif [loop.clip for loop in loops] != plays.clips():
        raise ValueError(f"the loops searched are of {[loop.clip for loop in loops]}, the timeline plays {plays.clips()}")
    transitions = find_transitions(inputs.cloth, inputs.cloth_faces, plays, loops, params.max_candidates, params.velocity_weight,
                                   body=inputs.body)
    primary = next(loop for loop in loops if loop.clip == inputs.clip)
    result = primary.cache_result(plays.total_frames)
    report("report", 0, 1)
    breaks = out_of_bounds(loops, transitions)
    bounds = {"out_of_bounds": [item.to_dict() for item in breaks], "accept_out_of_bounds": accept_out_of_bounds}
    # Without a timeline there is nothing beyond the one loop to describe.
    sections = bounds if timeline is None else {**write_clip_files(out_dir, plays, primary, loops, transitions, inputs.sample_rate), **bounds}
    draw = [lambda: write_cycle_plots(result, out_dir)]
    if timeline is not None:  # every loop's and join's pictures, named in the sections before cycle.json is written
        figures = clip_figures(sections, loops, transitions, inputs.cloth)
        draw.append(lambda: figures.draw(out_dir))
    write_cycle_outputs(result, out_dir, inputs, plots=False, sections=sections)
    if isinstance(plots, list):
        plots.extend(draw)
    elif plots:
        for drawing in draw:
            drawing()
    report("report", 1, 1)
    if breaks and not accept_out_of_bounds:  # the outputs stay, for the report to show what broke
        raise OutOfBoundsError(bounds_message(breaks))
    for item in breaks:
        logger.warning("accepted out of bounds: %s", item.text())
    return result


def write_cycle_outputs(result: CycleResult, out_dir: str | os.PathLike, inputs: CycleInputs | None = None,
                        plots: bool = True, sections: dict | None = None) -> dict[str, Path]:
    """Write cycle.json, looped.pc2, the PNG plots, the edge images and report.html; returns the paths.

    plots: False skips the matplotlib plots (a second or more), for write_cycle_plots to draw later (the bake
    runner draws them beside the next stages); every other file, the report's links included, is written."""
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
    if sections is not None:  # a timeline's clips (write_clip_files): every loop and transition
        document.update(sections)
    paths["cycle_json"].write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    report = clips_report(document) if document.get("clips") else report_html(result, document)
    paths["report"].write_text(report, encoding="utf-8")
    logger.info("cycle outputs written to %s", out)
    return paths


def write_clip_files(out_dir: str | os.PathLike, timeline: Timeline, primary: ClipLoop, loops: list[ClipLoop],
                     transitions: list[Transition], sample_rate: float = 1.0) -> dict:
    """Every loop's and transition's PC2 file under out_dir (and, for several clips that play in place, the
    bundle's pose cache); returns cycle.json's sections of the timeline. sample_rate: the PC2 files' sample
    interval (the cache's)."""
    out = Path(out_dir)
    (out / "clips").mkdir(parents=True, exist_ok=True)
    (out / "transitions").mkdir(parents=True, exist_ok=True)
    clip_entries = []
    for loop in loops:
        name = f"clips/{file_stem(loop.clip)}.pc2"
        write_pc2(out / name, loop.looped, start_frame=0.0, sample_rate=sample_rate)
        clip_entries.append({**loop.to_dict(timeline.total_frames), "file": name})
    transition_entries = []
    for k, transition in enumerate(transitions):
        name = f"transitions/{k}_{file_stem(transition.from_clip)}_{file_stem(transition.to_clip)}.pc2"
        write_pc2(out / name, transition.frames, start_frame=0.0, sample_rate=sample_rate)
        transition_entries.append(transition_dict(transition, name))
        for leaving, join in ((True, transition.leave), (False, transition.arrive)):
            if join.switch_step_ratio > SLOW_SWITCH_RATIO:  # no slow candidate kept the bounds: a switch may read as a jump
                logger.warning("%s switches at a fast phase: %.2f x the clips' median step (slow: at most %.2f)",
                               join_where(transition.from_clip, transition.to_clip, leaving, join), join.switch_step_ratio,
                               SLOW_SWITCH_RATIO)
    sections = {"primary_clip": primary.clip, "clip_phase": primary.clip_phase, "timeline": timeline_dict(timeline),
                "clips": clip_entries, "transitions": transition_entries}
    travelling = [loop.clip for loop in loops if loop.result.root_offsets is not None]
    if len(loops) > 1 and travelling:
        # Its loop is in the root's frame, the transitions and the body are not: no bundle can hold both
        # (crowdbake.stages.cycle.stage_cycle refuses the bake; `crowdbake cycle` still writes the loops).
        sections["bundle_refused"] = (f"clip {travelling[0]!r} travels (its loop was searched in the root's frame): a bundle of "
                                      "several clips needs clips that play in place")
    elif len(loops) > 1:  # a bundle of several clips (format v2): every loop and transition in one pose cache
        ranges = bundle_ranges(loops, transitions)
        for entry, item in zip([*clip_entries, *transition_entries], ranges.all()):
            entry["pose_frames"] = [item.first_frame, item.first_frame + item.frames]
        write_pc2(out / POSE_FRAMES_FILE, np.concatenate([loop.looped for loop in loops] + [t.frames for t in transitions]),
                  start_frame=0.0, sample_rate=sample_rate)
        sections["bundle_ranges"] = {
            "pose_frames": ranges.pose_frames,
            "clips": [clip.to_manifest() for clip in ranges.clips],
            "transitions": [transition.to_manifest() for transition in ranges.transitions],
            # What the poses stage poses the body with: loop frame k of clip c shows clip frame (phase + k) mod period;
            # a transition's frames are the cache frames [source_start_frame, source_end_frame) of the timeline.
            "clip_phases": [loop.clip_phase for loop in loops],
            "file": POSE_FRAMES_FILE,
        }
    return sections


def file_stem(name: str) -> str:
    """A clip name as a file name: lower case, [a-z0-9_-] only (glTF names are free text)."""
    return re.sub(r"[^a-z0-9_-]+", "_", name.lower()).strip("_")[:48] or "clip"


def _join_dict(join: Join) -> dict:
    return {
        "cache_frame": join.cache_frame,
        "loop_frame": join.loop_frame,
        "distance": _float(join.distance),
        "crossfade_frames": join.half_width,
        "quality": _quality_dict(join.quality),
        "candidates": [{"cache_frame": f, "loop_frame": k, "distance": _float(d)} for f, k, d in join.candidates],
        "switch_step_ratio": _float(join.switch_step_ratio),
    }


def transition_dict(transition: Transition, file: str | None = None) -> dict:
    """One entry of cycle.json's `transitions`."""
    return {
        "from_clip": transition.from_clip,
        "to_clip": transition.to_clip,
        "from_segment": transition.from_segment,
        "to_segment": transition.to_segment,
        "leave_loop_frame": transition.leave_loop_frame,
        "arrive_loop_frame": transition.arrive_loop_frame,
        "frames": int(len(transition.frames)),
        "source_frames": list(transition.source_frames),
        "within_bounds": transition.within_bounds,
        "leave": _join_dict(transition.leave),
        "arrive": _join_dict(transition.arrive),
        **({"file": file} if file else {}),
    }


def timeline_dict(timeline: Timeline) -> dict:
    return {
        "fps": timeline.fps,
        "total_frames": timeline.total_frames,
        "segments": [
            {"clip": s.clip, "first_frame": s.first_frame, "last_frame": s.last_frame, "pure_first_frame": s.pure_first_frame,
             "pure_last_frame": s.pure_last_frame, "clip_frames": s.clip_frames, **({"new_simulation": True} if s.new_simulation else {})}
            for s in timeline.segments
        ],
    }


POSE_FRAMES_FILE = "pose_frames.pc2"


def bundle_ranges(loops: list[ClipLoop], transitions: list[Transition]) -> Ranges:
    """The bundle's clips and transitions (format v2) as pose-frame ranges: the loops in order, then the
    transitions, each after the one before. A transition's leave_frame is the loop frame played before it
    (its leave_loop_frame - 1), its arrive_frame the loop frame after it; its jump ratios the worse join's."""
    index = {loop.clip: k for k, loop in enumerate(loops)}
    counts = [len(loop.looped) for loop in loops] + [len(t.frames) for t in transitions]
    firsts = first_frames(counts)
    clips = []
    for loop, first in zip(loops, firsts):
        seam = loop.result.closing.seam_after
        clips.append(Clip(name=loop.clip, first_frame=first, frames=len(loop.looped), source_start_frame=loop.start_frame,
                          source_end_frame=loop.end_frame, closing=loop.result.closing.method,
                          position_jump_ratio=_seam_number(seam.position_jump_ratio), velocity_jump_ratio=_seam_number(seam.velocity_jump_ratio)))
    moves = []
    for transition, first in zip(transitions, firsts[len(loops):]):
        loop_a, loop_b = loops[index[transition.from_clip]].looped, loops[index[transition.to_clip]].looped
        position, velocity = transition_jump_ratios(transition, loop_a, loop_b)
        moves.append(BundleTransition(
            from_clip=index[transition.from_clip], to_clip=index[transition.to_clip],
            leave_frame=(transition.leave_loop_frame - 1) % len(loop_a), arrive_frame=transition.arrive_loop_frame,
            first_frame=first, frames=len(transition.frames), source_start_frame=transition.source_frames[0],
            source_end_frame=transition.source_frames[1], position_jump_ratio=_seam_number(position), velocity_jump_ratio=_seam_number(velocity)))
    return Ranges(sum(counts), tuple(clips), tuple(moves))


def _seam_number(value: float) -> float:
    """A seam ratio for the manifest: >= 0 and finite (an undefined ratio, for still cloth, is 0)."""
    return float(value) if np.isfinite(value) and value >= 0 else 0.0
