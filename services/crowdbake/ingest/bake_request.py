"""Checks of a bake request against the assets it names, before anything is queued: what the uploads
measured (asset info) must allow the cycle search the validate stage will run, name an animation the
character has, and put the garment on the character (crowdbake.bake.placement)."""
from __future__ import annotations

from typing import Any

import numpy as np

from crowdbake.errors import InputError
from crowdbake.ingest.studio_inputs import MAX_ANIMATION_SUMMARIES
from crowdbake.params import cache_fps, cycle_frames_from_animation, min_cloth_frames


def chosen_animation(character_info: dict[str, Any], animation: int | str = 0) -> dict[str, Any] | None:
    """The summary the character upload recorded for `animation` (index or name), None when the upload
    recorded none (older assets, or beyond crowdbake.ingest.studio_inputs.MAX_ANIMATION_SUMMARIES).
    InputError("params.animation") when the character has no such animation."""
    summaries = character_info.get("animations")
    if not isinstance(summaries, list):
        return None
    if animation is None:  # not told: the validate stage picks (crowdbake.ingest.clip_choice); one is that one
        return summaries[0] if len(summaries) == 1 else None
    names = [entry.get("name") for entry in summaries]
    if isinstance(animation, str):
        if animation in names:
            return summaries[names.index(animation)]
        if len(summaries) < MAX_ANIMATION_SUMMARIES:  # every name is known: this one is not among them
            listed = ", ".join(repr(name) for name in names) or "none"
            raise InputError(f"the character has no animation named {animation!r} (it has {listed})", "params.animation")
        return None
    if animation == 0 and not summaries:  # the default on a character without animation: nothing to pick
        return None
    if animation < len(summaries):
        return summaries[animation]
    if len(summaries) < MAX_ANIMATION_SUMMARIES:
        raise InputError(f"the character has {len(summaries)} animation(s): index {animation} does not exist", "params.animation")
    return None


def request_fps(cloth_info: dict[str, Any], fps: float | None) -> float:
    """The cache's frame rate as the validate stage will take it (crowdbake.params.cache_fps)."""
    return cache_fps(fps, cloth_info.get("fps"), cloth_info.get("sample_rate") or 1.0)


def cycle_frames_for(character_info: dict[str, Any], cloth_info: dict[str, Any], cycle_frames: int | None,
                     fps: float | None = None, animation: int | str = 0) -> int:
    """The walk cycle's length in cache frames, as the validate stage will take it: the parameter, else
    the chosen animation at the cache's rate (crowdbake.params.cycle_frames_from_animation).
    InputError("params.cycle_frames") when neither gives one; FrameRateError when the cache's rate is
    outside crowdbake.params' range, whether or not it sets the length (the validate stage refuses it too)."""
    rate = request_fps(cloth_info, fps)
    if cycle_frames is not None:
        return int(cycle_frames)
    summaries = character_info.get("animations")
    if animation is None and isinstance(summaries, list) and len(summaries) > 1:
        return _shortest_fitting(summaries, int(cloth_info.get("frame_count", 0)), rate)
    summary = chosen_animation(character_info, animation)
    seconds = summary.get("seconds") if summary is not None else character_info.get("animation_seconds")
    frames = cycle_frames_from_animation(float(seconds or 0.0), rate)
    if frames <= 0:
        raise InputError("give cycle_frames, or upload a character with a walk animation", "params.cycle_frames")
    return max(frames, 2)


def check_two_cycles(character_info: dict[str, Any], cloth_info: dict[str, Any], cycle_frames: int | None,
                     fps: float | None = None, animation: int | str = 0) -> int:
    """The cycle length the bake will use; InputError("cloth") when the cache is too short for two."""
    length = cycle_frames_for(character_info, cloth_info, cycle_frames, fps, animation)
    needed = min_cloth_frames(length)
    have = cloth_info.get("frame_count", 0)
    if have < needed:
        raise InputError(f"too few frames for two cycles of {length}: the cache has {have}, two cycles need {needed}", "cloth")
    return length


def check_request_placement(character_info: dict[str, Any], cloth_info: dict[str, Any], animation: int | str = 0,
                            up: str | None = None, units: str | None = None) -> None:
    """The garment's first frame against the character's bounds at the chosen animation's time 0, from
    what the uploads recorded (skipped when they recorded nothing: the validate stage checks the files).
    InputError("params.up" | "params.units" | "cloth") with a message that names the parameter to set."""
    from crowdbake.ingest.garment import check_cloth_placement, rest_wording

    sample = cloth_info.get("placement_sample")
    summary = chosen_animation(character_info, animation)
    bounds = summary.get("rest_bounds") if summary is not None else None
    if not sample or not bounds:
        return
    try:
        check_cloth_placement(np.asarray(sample, np.float64), np.asarray(bounds, np.float64), up, units)
    except InputError as error:
        field = f"params.{error.field}" if error.field in ("up", "units") else "cloth"
        raise InputError(rest_wording(error.message), field) from None


def _shortest_fitting(summaries: list[dict[str, Any]], cache_frames: int, fps: float) -> int:
    """Several clips and none named: the validate stage picks among those the cache holds twice
    (crowdbake.ingest.clip_choice); the request passes when one does (the shortest's length is returned).
    InputError("params.animation") listing the clips when none does."""
    from crowdbake.ingest.clip_choice import Clip, fitting_clips, no_fit_error

    clips = [Clip(str(entry.get("name")), float(entry.get("seconds") or 0.0)) for entry in summaries]
    fitting = fitting_clips(clips, cache_frames, fps)
    if not fitting:
        error = no_fit_error(clips, cache_frames, fps)
        raise InputError(error.message, "params.animation")
    return min(clips[k].frames(fps) for k in fitting)
