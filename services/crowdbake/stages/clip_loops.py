"""The cycle stage for a cache simulated across several clips (a timeline): a loop per clip and the
transitions between them (crowdbake.bake.clips, crowdbake.bake.transitions), written beside the usual
cycle outputs.

    run_clips_job(inputs, timeline, out_dir, params, animation, render_views, plots) -> CycleResult

cycle.json is the single-clip document of the *primary* clip (the one `animation` names, else the
timeline's first), the loop a bundle carries, in cache frame numbers, plus
  timeline      fps, total_frames and the segments;
  clips         every clip's loop: the single-clip document's fields (candidates, closing, quality...)
                with clip, period, segment, clip_phase and searched_frames;
  transitions   every simulated change of clip: from/to clip and segment, the loop frames where it
                leaves and arrives, its frames, the cache frames it spans, and each join's candidates and
                quality figures.
Files: looped.pc2 (the primary loop), clips/<clip>.pc2 (every loop), transitions/<k>_<from>_<to>.pc2.
"""
from __future__ import annotations

import html
import logging
import re
from pathlib import Path

import numpy as np

from crowdbake.bake.clips import ClipLoop, find_clip_loops
from crowdbake.bake.timeline import Timeline
from crowdbake.bake.cycle import CycleParams, CycleResult, _float, _quality_dict
from crowdbake.bake.pose_ranges import first_frames
from crowdbake.bake.transitions import SLOW_SWITCH_RATIO, Join, Transition, find_transitions, transition_jump_ratios
from crowdbake.formats.ranges import Clip, Ranges
from crowdbake.formats.ranges import Transition as BundleTransition

logger = logging.getLogger(__name__)


def file_stem(name: str) -> str:
    """A clip name as a file name: lower case, [a-z0-9_-] only (glTF names are free text)."""
    return re.sub(r"[^a-z0-9_-]+", "_", name.lower()).strip("_")[:48] or "clip"


def primary_clip(timeline: Timeline, animation: int | str | None) -> str:
    """The clip a bundle carries: `animation` when it names a clip of the timeline, else the first clip.
    ValueError when `animation` names a clip the timeline does not play."""
    clips = timeline.clips()
    if animation is None:
        return clips[0]
    if isinstance(animation, str) and animation in clips:
        return animation
    raise ValueError(f"animation {animation!r} is not a clip of the timeline (it plays {', '.join(clips)}): name one of them")


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


def pose_clips_body(character_path, timeline: Timeline, only: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body at every pure frame of the timeline, posed at that frame's clip frame: ((F, Vb, 3)
    positions, (F, Vb, 3) normals, (Tb, 3) faces); frames in blends stay zero (no search reads them).
    only: a clip's name to pose that clip's frames alone (the rest stay zero: one clip's search reads no other)."""
    from crowdbake.bake.skinning import pose_character
    from crowdbake.formats.gltf import load_character

    positions = normals = faces = None
    for clip in timeline.clips() if only is None else [only]:
        character = load_character(character_path, animation=clip)
        period = timeline.period(clip)
        posed, posed_normals = pose_character(character, timeline.fps, period)
        if positions is None:
            positions = np.zeros((timeline.total_frames, *posed.shape[1:]), dtype=np.float32)
            normals = np.zeros_like(positions)
            faces = np.asarray(character.faces, dtype=np.int64)
        for s in timeline.segments:
            if s.clip == clip:
                rows = np.arange(s.pure_first_frame, s.pure_last_frame + 1)
                phase = timeline.clip_frame[rows] % period
                positions[rows], normals[rows] = posed[phase], posed_normals[phase]
    return positions, normals, faces


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


def run_clips_job(cloth: np.ndarray, cloth_faces: np.ndarray, timeline: Timeline, out_dir: Path,
                  params: CycleParams = CycleParams(), animation: int | str | None = None, render_views=None,
                  body: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, progress=None, sample_rate: float = 1.0,
                  loops: list[ClipLoop] | None = None) -> tuple[CycleResult, list[ClipLoop], list[Transition], dict]:
    """Every clip's loop and every transition, their files under out_dir; returns (the primary clip's
    result in cache frames, the loops, the transitions, cycle.json's multi-clip sections).
    body: pose_clips_body's output or None (then no penetration figures); sample_rate: the PC2 files'
    sample interval (the cache's); loops: every clip's loop, in the timeline's order, searched already
    (crowdbake.stages.loops), or None to search them here. ValueError on a clip without
    a loop or a segment too short for a join."""
    from crowdbake.formats.pc2 import write_pc2

    primary = primary_clip(timeline, animation)
    positions, faces = (None, None) if body is None else (body[0], body[2])
    if loops is None:
        loops = find_clip_loops(cloth, cloth_faces, timeline, params, render_views, positions, faces, progress)
    elif [loop.clip for loop in loops] != timeline.clips():
        raise ValueError(f"the loops searched are of {[loop.clip for loop in loops]}, the timeline plays {timeline.clips()}")
    transitions = find_transitions(cloth, cloth_faces, timeline, loops, params.max_candidates, params.velocity_weight, body=positions)
    out = Path(out_dir)
    (out / "clips").mkdir(parents=True, exist_ok=True)
    (out / "transitions").mkdir(parents=True, exist_ok=True)
    clip_entries = []
    for loop in loops:
        name = f"clips/{file_stem(loop.clip)}.pc2"
        write_pc2(out / name, loop.looped, start_frame=0.0, sample_rate=sample_rate)
        clip_entries.append({**loop.to_dict(timeline.total_frames), "file": name})
        quality = loop.result.closing.quality
        if quality is not None and quality.exceeded:
            logger.warning("the loop of clip %r breaks its quality bounds: %s", loop.clip, ", ".join(quality.exceeded))
    transition_entries = []
    for k, transition in enumerate(transitions):
        name = f"transitions/{k}_{file_stem(transition.from_clip)}_{file_stem(transition.to_clip)}.pc2"
        write_pc2(out / name, transition.frames, start_frame=0.0, sample_rate=sample_rate)
        transition_entries.append(transition_dict(transition, name))
        if not transition.within_bounds:
            logger.warning("the transition %s -> %s breaks its quality bounds", transition.from_clip, transition.to_clip)
        for end, join in (("leaves", transition.leave), ("arrives", transition.arrive)):
            if join.switch_step_ratio > SLOW_SWITCH_RATIO:  # no slow candidate kept the bounds: a switch may read as a jump
                logger.warning("the transition %s -> %s %s at a fast phase: %.2f x the clips' median step (slow: at most %.2f)",
                               transition.from_clip, transition.to_clip, end, join.switch_step_ratio, SLOW_SWITCH_RATIO)
    main = next(loop for loop in loops if loop.clip == primary)
    sections = {"primary_clip": primary, "clip_phase": main.clip_phase, "timeline": timeline_dict(timeline),
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
    return main.cache_result(timeline.total_frames), loops, transitions, sections


def clips_report_html(document: dict) -> str:
    """The report's section on every clip loop and transition, with their quality figures (empty for one clip)."""
    if not document.get("clips"):
        return ""

    def figures(quality: dict | None) -> str:
        if quality is None:
            return "<td>–</td><td>–</td><td>–</td><td>–</td>"
        cells = "".join(f"<td>{_shown(quality.get(name))}</td>" for name in ("stretch_ratio", "deviation_ratio", "seam_acceleration_ratio"))
        verdict = "ok" if quality["within_bounds"] else "OVER: " + ", ".join(quality["exceeded"])
        return cells + f"<td>{html.escape(verdict)}</td>"

    head = "<th>stretch</th><th>deviation</th><th>seam acc.</th><th>bounds</th>"

    def pose_frames(entry: dict) -> str:  # the bundle's pose frames [first, end) of a range (several clips only)
        span = entry.get("pose_frames")
        return "<td>–</td>" if span is None else f"<td>{span[0]}–{span[1] - 1}</td>"

    loops = "".join(
        f"<tr><td>{html.escape(c['clip'])}</td><td>{c['period']}</td><td>{c['start_frame']}–{c['end_frame']}</td>"
        f"{pose_frames(c)}<td>{c['segment']}</td>{figures(c['closing'].get('quality'))}</tr>"
        for c in document["clips"]
    )
    moves = "".join(
        f"<tr><td>{html.escape(t['from_clip'])} → {html.escape(t['to_clip'])}</td><td>{t['leave_loop_frame']}</td>"
        f"<td>{t['arrive_loop_frame']}</td><td>{t['frames']}</td><td>{t['source_frames'][0]}–{t['source_frames'][1]}</td>"
        f"{pose_frames(t)}<td>leave</td>{figures(t['leave']['quality'])}</tr>"
        f"<tr><td></td><td></td><td></td><td></td><td></td><td></td><td>arrive</td>{figures(t['arrive']['quality'])}</tr>"
        for t in document["transitions"]
    )
    bounds = document["clips"][0]["closing"].get("quality") or {}
    if "bundle_ranges" in document:
        carried = (f"The bundle carries every loop and transition: {document['bundle_ranges']['pose_frames']} pose frames, "
                   "each range's shown below (format v2).")
    else:
        carried = f"The bundle carries {html.escape(document.get('primary_clip', ''))}."
    if not document["transitions"] and any(s.get("new_simulation") for s in document.get("timeline", {}).get("segments", [])):
        carried += " The clips were simulated apart (one cache per clip): no transitions, as no simulation joined them."
    limits = ", ".join(f"{name.replace('_', ' ')} ≤ {value:g}" for name, value in (bounds.get("bounds") or {}).items())
    return (
        f"<h2>Clips: a loop each</h2><p>{carried} Bounds: {html.escape(limits)}.</p>"
        f"<table><thead><tr><th>clip</th><th>period</th><th>cache frames</th><th>pose frames</th><th>segment</th>{head}</tr></thead><tbody>{loops}</tbody></table>"
        "<h2>Transitions taken from the simulation</h2><p>Playback leaves loop A before its frame <i>leave</i>, plays the "
        "transition's frames, and goes on with loop B's frame <i>arrive</i>; each join is crossfaded like a loop's seam.</p>"
        f"<table><thead><tr><th>change</th><th>leave</th><th>arrive</th><th>frames</th><th>cache frames</th><th>pose frames</th><th>join</th>{head}</tr></thead>"
        f"<tbody>{moves}</tbody></table>"
    )


def _shown(value) -> str:
    return "–" if value is None else f"{value:.3g}"


def check_timeline(inputs, timeline: Timeline, timeline_path: Path, character) -> None:
    """The timeline against the loaded inputs (crowdbake.stages.cycle.CycleInputs) and the character's
    clips (crowdbake.ingest.timeline.check_timeline_fits)."""
    from crowdbake.ingest.timeline import check_timeline_fits

    known = None
    if character is not None:
        from crowdbake.ingest.clip_choice import character_clips

        known = {clip.name: clip.seconds for clip in character_clips(character)}
    check_timeline_fits(timeline, inputs.cloth.shape[0], inputs.fps, known, timeline_path.name)


def run_timeline(inputs, timeline: Timeline, timeline_path: Path, character, out_dir, params: CycleParams,
                 animation: str, render_views, progress, loops: list[ClipLoop] | None = None) -> tuple[CycleResult, dict]:
    """run_cycle_job's several-clip path: the timeline checked, the body posed per clip, then run_clips_job
    (loops: searched already, see run_clips_job). The body is posed even then: the transitions' search
    reads it (crowdbake.bake.transitions.switch_is_slow), as the one over every clip does."""
    check_timeline(inputs, timeline, timeline_path, character)
    body = None
    if character is not None:
        body = pose_clips_body(character, timeline)
    elif inputs.body is not None:
        body = (inputs.body, inputs.body_normals, inputs.body_faces)
    result, _, _, sections = run_clips_job(inputs.cloth, inputs.cloth_faces, timeline, out_dir, params, animation,
                                           render_views, body, progress, inputs.sample_rate, loops)
    sections["sources"] = {"timeline": str(timeline_path)}
    return result, sections
