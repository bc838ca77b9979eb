"""A character baked without a simulated garment (no cloth cache): the body alone.

Crowds need characters in plain clothes too. Without a cloth there is nothing to search a cycle in: the
cycle is the animation's own loop, sampled at the `fps` parameter (default BODY_FPS), its length
duration x fps frames from frame 0, closed by the animation itself ("closing": "none", no seam). The
validate stage takes the counts from here, the cycle node writes this cycle (its record's `source` says
so), and the poses, impostor, pack and publish nodes run as usual on the body's one part: the bundle has
no garment mesh.
"""
from __future__ import annotations

from typing import Any

from crowdbake.errors import InputError

# The sampling rate of the animation when no cloth cache gives one and `fps` is not given: 30 frames a
# second, the rate of most game animation exports (glTF keyframes are in seconds, so any rate samples them).
BODY_FPS = 30.0

# What CycleRecord.source and cycle.json's "source" say for a body-only bake.
ANIMATION_LOOP = "animation loop (no cloth: no cycle search)"


def body_only_counts(character, params, character_name: str) -> tuple[dict[str, int], float, dict[str, Any] | None]:
    """(the JobRecord's counts, the sampling rate, the animation choice or None) for a bake without a
    cloth cache. InputError when the character has no animation or cycle_frames was given (the
    animation's own length is the cycle)."""
    if params.cycle_frames is not None:
        raise InputError("cycle_frames applies to a cloth cache; without one the cycle is the animation's own loop", "cycle_frames")
    fps = float(params.fps) if params.fps is not None else BODY_FPS
    if not character.animation_duration > 0:
        raise InputError(f"{character_name} has no animation: a body without cloth needs its walk to loop", "character")
    frames = max(int(round(character.animation_duration * fps)), 2)
    counts = {
        "body_vertices": int(len(character.positions)),
        "body_triangles": int(len(character.faces)),
        "garment_vertices": 0,
        "garment_triangles": 0,
        "cache_frames": frames,
        "cycle_frames": frames,
    }
    choice = None
    if params.animation is None and len(character.animation_names) > 1:
        choice = {"index": 0, "name": character.animation_name, "frames": frames,
                  "reason": "no cloth to tell the clips apart: the first animation (name another with `animation`)"}
    return counts, fps, choice


def animation_loop_cycle(cycle_frames: int, fps: float) -> dict[str, Any]:
    """cycle.json for a body-only bake: the whole animation, frame 0 on, closed by the animation itself."""
    return {
        "source": ANIMATION_LOOP,
        "start_frame": 0,
        "end_frame": int(cycle_frames),
        "cycle_frames": int(cycle_frames),
        "closing": {"method": "none"},
        "seam": {"position_jump_ratio": 0.0, "velocity_jump_ratio": 0.0},
        "input": {"fps": float(fps), "cycle_frames_source": "character animation"},
    }
