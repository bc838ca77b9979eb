"""The cycle search's inputs: the cloth cache, the body (a character posed at the cache's frames, or a body
cache) and the clips the cache plays, read and cross-checked once.

    load_cycle_inputs(cloth_pc2, cloth_obj, character=... | body_pc2=..., body_obj=..., timeline=...) -> CycleInputs

A cache plays the clips of its timeline (crowdbake.ingest.timeline), or, without one, a single clip over
every frame (crowdbake.bake.timeline.one_clip_timeline): the cycle job (crowdbake.stages.cycle_job) and
the loops stage (crowdbake.stages.loops) search either the same way.

Frame rate (crowdbake.params.cache_fps): `fps` when the caller passes it, else the cache's own (MDD frame
times, Alembic time sampling), else BASE_FPS / sample_rate with BASE_FPS = 24 (the film rate the sample
content and most DCC scenes use): a PC2 file stores the interval between samples in frames, not a rate.
The cycle length, when not given, is the character's animation duration times that rate; with a timeline,
its primary clip's period.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.bake.timeline import Timeline, one_clip_timeline, primary_clip
from crowdbake.params import min_cloth_frames

# The animation's duration times the frame rate must be this close to a whole number of frames for the
# body to be tiled from one posed cycle; otherwise each frame is posed at its own wrapped time.
_WHOLE_FRAME_TOLERANCE = 1e-3


@dataclass
class CycleInputs:
    """Arrays for the search plus what the files said.

    cloth: (F, V, 3) float32 in PC2 point order; cloth_faces: (T, 3) int64 into those points.
    body: (F, Vb, 3) float32 or None; body_faces (Tb, 3) int64; body_normals (F, Vb, 3) or None (the search
    derives them from the faces).
    cycle_frames: l; fps: the cache's frame rate; sample_rate/start_frame: from the cloth PC2 header.
    timeline: the clips the cache plays (one clip over every frame when no timeline was given);
    clip: the primary clip, whose loop is the cycle a bundle carries.
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
    timeline: Timeline
    clip: str


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
    timeline: str | os.PathLike | None = None,
    clip: str | None = None,
    check_fit: bool = False,
) -> CycleInputs:
    """Read and cross-check the cycle search's input files. Raises ValueError with a one-line reason.

    cloth_pc2: any cloth cache crowdbake reads (.pc2 or .mdd with `cloth_obj`, .abc or an OBJ-sequence
    .zip alone; crowdbake.ingest.garment.read_cloth). fps: None takes the cache's own rate
    (crowdbake.params.cache_fps). The cloth's first frame is checked against the body's
    (crowdbake.ingest.garment.place_cloth) and converted to Y-up metres when up/units say so.
    timeline: a clip timeline file (crowdbake.ingest.timeline): its primary clip (`animation` or its first)
    gives the cycle length, it is checked against the cache and the character, and a character's body is
    posed per clip (pose_clips_body; only `clip`'s frames when given).
    check_fit: refuse (InputError "cloth") a garment that does not follow the character over the cache
    (crowdbake.ingest.garment.check_garment_fit, as the bake's validation does); a character and no timeline only."""
    from crowdbake.formats.obj import read_obj
    from crowdbake.formats.pc2 import read_pc2
    from crowdbake.ingest.garment import check_garment_fit, place_cloth, read_cloth
    from crowdbake.params import cache_fps

    plays = None
    if timeline is not None:
        from crowdbake.ingest.timeline import read_timeline

        plays = read_timeline(Path(timeline))
        animation = primary_clip(plays, animation)
        cycle_frames = plays.period(animation)
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
            from crowdbake.ingest.clip_choice import character_clip_evidence, character_clips, choose_clip

            clips = character_clips(character)
            animation = 0
            if len(clips) > 1 and cycle_frames is None:
                animation = choose_clip(clips, cache.frames, frame_rate, lambda indices: character_clip_evidence(
                    character, indices, cache.frames, frame_rate, up, units)).index
        loaded_character = load_character(character, animation=animation)
        # The garment must sit on the character before a minute of search is spent on it.
        from crowdbake.ingest.garment import body_at_rest

        cache = place_cloth(cache, body_at_rest(loaded_character), up, units)
        if plays is None:
            # The fit poses one clip over every frame: a timeline's cache is checked by its clips instead.
            if check_fit:
                check_garment_fit(loaded_character, cache, frame_rate)
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
    if plays is None:  # one clip over every frame, named after the cache
        plays = one_clip_timeline(Path(cloth_pc2).stem, frame_rate, frame_count, length)
        primary = plays.clips()[0]
    else:
        primary = animation
        _check_timeline(plays, Path(timeline), frame_count, frame_rate, character)
        if character is not None:
            body, body_faces = pose_clips_body(character, plays, only=clip)
        sources["timeline"] = str(timeline)
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
        timeline=plays,
        clip=primary,
    )


def _check_timeline(timeline: Timeline, timeline_path: Path, frame_count: int, fps: float, character) -> None:
    """The timeline against the cache and the character's clips (crowdbake.ingest.timeline.check_timeline_fits)."""
    from crowdbake.ingest.timeline import check_timeline_fits

    known = None
    if character is not None:
        from crowdbake.ingest.clip_choice import character_clips

        known = {clip.name: clip.seconds for clip in character_clips(character)}
    check_timeline_fits(timeline, frame_count, fps, known, timeline_path.name)


def pose_clips_body(character_path, timeline: Timeline, only: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The body at every pure frame of the timeline, posed at that frame's clip frame: ((F, Vb, 3) positions,
    (Tb, 3) faces); frames in blends stay zero (no search reads them). No normals: where the body is posed
    per clip, the search derives them from the faces.
    only: a clip's name to pose that clip's frames alone (the rest stay zero: one clip's search reads no other)."""
    from crowdbake.bake.skinning import pose_character
    from crowdbake.formats.gltf import load_character

    positions = faces = None
    for clip in timeline.clips() if only is None else [only]:
        character = load_character(character_path, animation=clip)
        period = timeline.period(clip)
        posed, _normals = pose_character(character, timeline.fps, period)
        if positions is None:
            positions = np.zeros((timeline.total_frames, *posed.shape[1:]), dtype=np.float32)
            faces = np.asarray(character.faces, dtype=np.int64)
        for s in timeline.segments:
            if s.clip == clip:
                rows = np.arange(s.pure_first_frame, s.pure_last_frame + 1)
                phase = timeline.clip_frame[rows] % period
                positions[rows] = posed[phase]
    return positions, faces


def check_one_motion(cloth: np.ndarray, cycle_frames: int, settle_frames: int | None, name: str) -> None:
    """Refuse (ValueError, one line) a cache searched as one clip whose cloth changes its motion along it
    (crowdbake.bake.motion_changes): it seems to play several clips, and a loop cut blind may come from
    another clip than the body plays. cloth: (F, V, 3); settle_frames: the search's (None: one cycle),
    before which nothing is compared; name: the cache's file name for the message."""
    from crowdbake.bake.motion_changes import CHANGE_FACTOR, motion_changes

    changes = motion_changes(cloth, cycle_frames, cycle_frames if settle_frames is None else settle_frames)
    if not changes:
        return
    listed = ", ".join(f"{change.factor:.1f}x at frame {change.frame}" for change in changes)
    raise ValueError(
        f"{name}: the cloth's motion changes along the cache, as if it played several clips: its speed over a "
        f"{cycle_frames}-frame cycle changes by more than {CHANGE_FACTOR:g}x from the cycle before ({listed}); give the "
        "clips' timeline (--timeline) to loop each clip on its own frames")
