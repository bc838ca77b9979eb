"""Which of a character's animations drove the cloth, when the bake was not told (`animation` not given).

A character exported with several clips (Idle, Walk, Run...) and a cloth simulated on one of them: the
first clip is not necessarily the walk. The rule, in three steps:

1. A clip *fits* when its length in cache frames, round(duration x fps), is at least MIN_CYCLE_FRAMES and
   the cache holds two repetitions of it (the cycle search compares frames one cycle apart:
   crowdbake.params.min_cloth_frames).
2. Among the clips that fit, the one the cloth repeats best after: the cloth's shape (each frame's
   vertices minus their mean, so that walking forward does not count) is compared with itself one clip
   length later, `repeat_gap`; the smallest RMS gap wins, the shorter clip on a tie. A cloth driven by a
   24-frame walk comes back after 24 frames; after a 12-frame clip it is half a stride off. A clip that
   loops (every channel ends where it starts, or one key's step short of it: a walk, not a fall) goes
   before one that does not, since the bake tiles the body's clip.
3. The physical evidence (crowdbake.bake.clip_evidence), the body posed by each clip that fits: the cloth
   collided with the body that drove it, so under that clip it stays outside the body and moves with it.
   A clip the cloth clearly does not follow, or sits inside more than under the others, goes after the
   clips that pass; among clips whose repeat gaps tie or nearly tie (GAP_NEAR_TIE) the one the cloth
   follows best wins (a 23-frame walk and a 23-frame run repeat alike). The reason names each clip's gap,
   share of cloth inside and follow. Where the cloth follows no clip (a cache played across several), or
   no evidence is given, the gap alone decides: of clips that still tie, the first in the file is taken
   and the reason names the others.

One animation, or `animation` given by name or index: that one, no search. No clip that fits: an
InputError listing every clip with its length in frames.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from crowdbake.errors import InputError
from crowdbake.params import MIN_CYCLE_FRAMES, min_cloth_frames

logger = logging.getLogger(__name__)

# A channel loops when its last key is this close to its first (metres, quaternion or scale components):
# exported cycles repeat their first key exactly or to a few 1e-4; a fall or a sit ends 0.5 away.
LOOP_TOLERANCE = 1e-2
# ...or when its last key is at most LOOP_STEPS of its own fast key steps (the STEP_PERCENTILE of its
# steps) from its first: many exports (Mixamo's walks and runs among them) end one key before the first
# pose comes round again, so a fast channel's last key sits one step away, far beyond LOOP_TOLERANCE.
# A fall ends many steps away. A percentile, not the largest step, so one jump at the end is no loop.
LOOP_STEPS = 1.5
STEP_PERCENTILE = 90


@dataclass(frozen=True)
class Clip:
    """One animation of the character: its name and length in seconds."""

    name: str
    seconds: float
    loops: bool = True

    def frames(self, fps: float) -> int:
        """Its length in cache frames at `fps` (rounded: a clip of 0.958 s at 24 fps is 23 frames)."""
        return int(round(self.seconds * fps))


@dataclass(frozen=True)
class ClipChoice:
    """The animation a bake uses and why: index into the file's animations, name, length in cache
    frames, and a one-line reason (logged, and kept in the JobRecord as `animation_choice`)."""

    index: int
    name: str
    frames: int
    reason: str

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "name": self.name, "frames": self.frames, "reason": self.reason}


def character_clips(path: str | Path) -> list[Clip]:
    """Every animation of a .glb/.gltf, in file order, with its duration (the last keyframe time of any
    of its samplers). Reads the document only, no mesh. ValueError for a broken file (as load_character)."""
    from crowdbake.formats.gltf.document import open_document

    doc = open_document(Path(path))
    clips = []
    for index, animation in enumerate(doc.gltf.animations or []):
        seconds, loops = 0.0, True
        for sampler in animation.samplers or []:
            times = doc.accessor(sampler.input)
            if len(times):
                seconds = max(seconds, float(np.max(times)))
                loops = loops and _channel_loops(doc.accessor(sampler.output), len(times), sampler.interpolation)
        clips.append(Clip(animation.name or f"animation{index}", seconds, loops))
    return clips


def _channel_loops(values: np.ndarray, keys: int, interpolation: str | None) -> bool:
    """Whether a sampler's last value is its first, judged against the channel's own motion: within
    LOOP_TOLERANCE, or within LOOP_STEPS of its fast key steps. q and -q are one rotation."""
    if interpolation == "CUBICSPLINE" and len(values) == 3 * keys:
        values = values.reshape(keys, 3, -1)[:, 1]  # (in-tangent, value, out-tangent) per key
    if len(values) < 2:
        return True
    values = np.asarray(values, np.float64).reshape(len(values), -1)
    gap = _component_gap(values[0], values[-1])
    steps = [_component_gap(a, b) for a, b in zip(values[:-1], values[1:])]
    return bool(gap <= LOOP_TOLERANCE or gap <= LOOP_STEPS * float(np.percentile(steps, STEP_PERCENTILE)))


def _component_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Largest component difference of two keys; for 4 components (a quaternion) q and -q count as one."""
    gap = np.abs(a - b)
    if gap.size == 4:
        gap = np.minimum(gap, np.abs(a + b))
    return float(gap.max())


def fitting_clips(clips: list[Clip], cache_frames: int, fps: float) -> list[int]:
    """Indices of the clips the cycle search can use on a cache of `cache_frames` frames at `fps`."""
    return [k for k, clip in enumerate(clips)
            if clip.frames(fps) >= MIN_CYCLE_FRAMES and cache_frames >= min_cloth_frames(clip.frames(fps))]


def clips_text(clips: list[Clip], fps: float) -> str:
    return ", ".join(f"{clip.name!r} ({clip.frames(fps)} frames)" for clip in clips)


def no_fit_error(clips: list[Clip], cache_frames: int, fps: float) -> InputError:
    return InputError(
        f"no animation of the character fits the cloth cache: its {cache_frames} frames at {fps:g} fps hold two "
        f"repetitions of none of {clips_text(clips, fps)}; name the walk with `animation` (and give cycle_frames)",
        "animation",
    )


def repeat_gap(cloth: np.ndarray, lag: int) -> float:
    """RMS distance (metres) between the cloth's shape at frame t and at t + lag, over every t.

    cloth: (F, V, 3) float, F > lag >= 1. The shape is each frame's vertices minus their mean."""
    frames = np.asarray(cloth, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[2] != 3:
        raise ValueError(f"cloth must be (F, V, 3), got {frames.shape}")
    if not 1 <= lag < frames.shape[0]:
        raise ValueError(f"lag {lag} must lie in 1..{frames.shape[0] - 1}")
    shape = frames - frames.mean(axis=1, keepdims=True)
    return float(np.sqrt(np.mean(np.sum((shape[lag:] - shape[:-lag]) ** 2, axis=2))))


def character_clip_evidence(path: str | Path, indices: list[int], cloth: np.ndarray, fps: float,
                            up: str | None = None, units: str | None = None) -> dict:
    """{clip index: crowdbake.bake.clip_evidence.ClipEvidence} for the clips `indices` of the character at
    `path`: the body posed by each clip at the cache's frames (frame f at time (f / fps) mod its
    duration, as the bake poses it), against the cloth (F, V, 3) in the cache's own frame (placed in Y-up
    metres as the bake places it, by `up` and `units`). Empty when the cloth sits on none of the clips'
    first poses (the bake refuses it later, naming why) or a clip cannot be read."""
    from crowdbake.bake.clip_evidence import evidence_pairs, measure_clip_evidence
    from crowdbake.bake.placement import check_placement
    from crowdbake.bake.skinning import pose_at_times
    from crowdbake.formats.gltf import load_character

    cloth = np.asarray(cloth)
    pairs = evidence_pairs(len(cloth))
    frames, rows = np.unique(pairs, return_inverse=True)

    def posed(index: int, seconds: np.ndarray):
        character = load_character(path, animation=index)
        duration = float(character.animation_duration)
        positions, normals = pose_at_times(character, seconds % duration if duration > 0 else np.zeros(len(seconds)))
        return positions, normals, np.asarray(character.faces, np.int64)

    try:
        # One conversion for every clip: the cache has one up axis and unit, whichever clip's first pose it meets.
        placement = next((p for p in (check_placement(cloth[0], posed(k, np.zeros(1))[0][0], up, units) for k in indices) if p.ok), None)
        if placement is None:
            return {}
        sampled = placement.apply(cloth[frames])
        found = {}
        for index in indices:  # one clip's body at a time: a dozen clips of a detailed character add up
            positions, normals, faces = posed(index, frames / float(fps))
            found[index] = measure_clip_evidence(sampled, positions, faces, normals, rows.reshape(pairs.shape))
        return found
    except (ValueError, KeyError, OSError, TypeError, AttributeError) as error:
        logger.info("no physical evidence for the clip choice: %s", str(error).splitlines()[0] if str(error) else type(error).__name__)
        return {}


# Repeat gaps within this share of the least one are a near-tie, broken by the physical evidence: clips of
# one length tie exactly. Not wider: robot_clips' Idle frames repeat after its 40-frame No 2.4% worse than
# after the 80-frame Idle that drove them, and the cape follows both alike (0.65 and 0.66).
GAP_NEAR_TIE = 0.02


def _evidence_key(evidence) -> tuple[float, float]:
    """Best first: the higher follow, then the less cloth inside; rounded so that noise does not decide."""
    if evidence is None:
        return (np.inf, np.inf)
    return (-round(evidence.follow, 3), round(evidence.penetration, 4))


def choose_clip(clips: list[Clip], cloth: np.ndarray, fps: float,
                evidence: Callable[[list[int]], dict] | None = None) -> ClipChoice:
    """The clip the cloth was simulated on (see the module docstring). cloth: (F, V, 3) frames at `fps`.
    evidence: the clips' physical evidence, called with the indices of the clips that fit when more than
    one does ({index: ClipEvidence}, e.g. character_clip_evidence); None or empty: the repeat gap alone.
    InputError("animation") listing the clips when none fits."""
    from crowdbake.bake.clip_evidence import MIN_FOLLOW, conclusive, rejections

    if not clips:
        raise InputError("the character has no animation: give cycle_frames", "animation")
    if len(clips) == 1:
        return ClipChoice(0, clips[0].name, clips[0].frames(fps), "the character's only animation")
    cache_frames = int(np.asarray(cloth).shape[0])
    fitting = fitting_clips(clips, cache_frames, fps)
    if not fitting:
        raise no_fit_error(clips, cache_frames, fps)
    if len(fitting) == 1:
        index = fitting[0]
        reason = (f"the only one of {len(clips)} animations ({clips_text(clips, fps)}) whose two repetitions the "
                  f"{cache_frames}-frame cloth cache holds")
    else:
        gaps = {k: round(repeat_gap(cloth, clips[k].frames(fps)), 6) for k in fitting}
        found = (evidence(fitting) if evidence is not None else None) or {}
        rejected, judged = rejections(found), conclusive(found)

        def rank(k: int) -> tuple:
            return (not clips[k].loops, k in rejected, gaps[k], clips[k].frames(fps))

        index = min(fitting, key=lambda k: (rank(k), k))
        near = [k for k in fitting if rank(k)[:2] == rank(index)[:2] and gaps[k] <= gaps[index] * (1 + GAP_NEAR_TIE)]
        if judged:  # among clips the cloth repeats after alike, the one its motion follows best
            index = min(near, key=lambda k: (*_evidence_key(found.get(k)), rank(k), k))

        def listed(k: int) -> str:
            notes = ([] if clips[k].loops else ["does not loop"]) + ([f"rejected: {rejected[k]}"] if k in rejected else [])
            return (f"{clips[k].name!r} {clips[k].frames(fps)} frames {1000 * gaps[k]:.1f} mm"
                    + (f" {found[k].text()}" if k in found else "") + (f" ({'; '.join(notes)})" if notes else ""))

        reason = (f"of {len(fitting)} animations the cloth cache could hold twice, the one after whose length the cloth "
                  f"repeats best{', of those whose body it stays outside and follows' if rejected else ''} (RMS shape gap"
                  f"{', share of the cloth inside the body and how its motion follows the body' if found else ''}: "
                  f"{', '.join(listed(k) for k in fitting)})")
        if found and not judged:
            reason += f" (the cloth follows none of them by {MIN_FOLLOW:g}: the shape gap alone decides)"
        if judged:
            def same(k: int) -> bool:
                return _evidence_key(found.get(k)) == _evidence_key(found.get(index))

            tied = [k for k in near if k != index and same(k)]
            broken = [k for k in near if k != index and not same(k)]
            if broken:
                reason += (f"; {', '.join(repr(clips[k].name) for k in broken)} repeat{'s' if len(broken) == 1 else ''} alike "
                           f"(within {GAP_NEAR_TIE:.0%}): the cloth follows {clips[index].name!r} best")
        else:
            tied = [k for k in fitting if k != index and rank(k) == rank(index)]
        if tied:
            reason += f"; {', '.join(repr(clips[k].name) for k in tied)} tie with it: name the walk with `animation`"
    clip = clips[index]
    choice = ClipChoice(index, clip.name, clip.frames(fps), reason)
    logger.info("animation %r (%d frames) picked: %s", choice.name, choice.frames, choice.reason)
    return choice
