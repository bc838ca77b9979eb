"""Checks of a bake request against the assets it names, before anything is queued: what the uploads
measured (asset info) must allow the cycle search the validate stage will run."""
from __future__ import annotations

from typing import Any

from crowdbake.errors import InputError
from crowdbake.params import cycle_frames_from_animation, min_cloth_frames


def cycle_frames_for(character_info: dict[str, Any], cloth_info: dict[str, Any], cycle_frames: int | None) -> int:
    """The walk cycle's length in cache frames, as the validate stage will take it: the parameter, else
    the character's animation at the cache's rate (crowdbake.params.cycle_frames_from_animation).
    InputError("params.cycle_frames") when neither gives one."""
    if cycle_frames is not None:
        return int(cycle_frames)
    frames = cycle_frames_from_animation(float(character_info.get("animation_seconds") or 0.0), float(cloth_info.get("sample_rate") or 1.0))
    if frames <= 0:
        raise InputError("give cycle_frames, or upload a character with a walk animation", "params.cycle_frames")
    return max(frames, 2)


def check_two_cycles(character_info: dict[str, Any], cloth_info: dict[str, Any], cycle_frames: int | None) -> int:
    """The cycle length the bake will use; InputError("cloth") when the cache is too short for two."""
    length = cycle_frames_for(character_info, cloth_info, cycle_frames)
    needed = min_cloth_frames(length)
    have = cloth_info.get("frame_count", 0)
    if have < needed:
        raise InputError(f"too few frames for two cycles of {length}: the cache has {have}, two cycles need {needed}", "cloth")
    return length
