"""A chosen cycle (cycle.json from `crowdbake cycle`, optionally its looped.pc2): one set of checks for
`crowdbake bake --cycle`, the cycle upload (POST /v1/assets/cycles) and a bake request that names one.

- cycle_fields / check_cycle_document: the document alone and against the cloth's frame count
  (InputError("cycle")), as the validate stage applies them;
- check_cycle_upload: an uploaded pair (UploadRejected with FieldErrors, as every upload check);
- check_cycle_fits_cloth: a bake request's cycle asset against its cloth asset, from what both uploads
  recorded.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from crowdbake.errors import InputError
from crowdbake.params import CLOSE_METHODS

# sniff_format (crowdbake.ingest.uploads) calls any JSON object "gltf": for cycle.json that means "a JSON
# document", and only bytes of another known format (a PNG, a PC2...) are a mismatch.
CYCLE_EXTENSIONS = {".json": "gltf"}


def cycle_fields(document: Any, name: str = "cycle.json") -> dict[str, Any]:
    """The fields a bake reads of a cycle document, checked: {start_frame, cycle_frames, method}.
    InputError("cycle") naming the field when the document is no object, a frame number is not a
    non-negative integer, the cycle is shorter than 2 frames or closing.method is unknown."""
    if not isinstance(document, dict):
        raise InputError(f"{name} must hold a JSON object", "cycle")
    for key in ("start_frame", "cycle_frames"):
        value = document.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise InputError(f"{name}: {key} must be a non-negative integer", "cycle")
    if document["cycle_frames"] < 2:
        raise InputError(f"{name}: cycle_frames must be at least 2", "cycle")
    closing = document.get("closing") or {}
    method = closing.get("method", "none") if isinstance(closing, dict) else None
    if method not in CLOSE_METHODS:
        raise InputError(f"{name}: closing.method must be one of {CLOSE_METHODS}", "cycle")
    return {"start_frame": document["start_frame"], "cycle_frames": document["cycle_frames"], "method": method}


def cycle_range_problem(start_frame: int, cycle_frames: int, frame_count: int, name: str = "cycle.json") -> str | None:
    """Why the cycle [start_frame, start_frame + cycle_frames) does not fit a cache of frame_count frames."""
    if start_frame + cycle_frames > frame_count:
        return f"{name}: the cycle [{start_frame}, {start_frame + cycle_frames}) runs past the cache's {frame_count} frames"
    return None


def read_cycle_document(path: Path, name: str | None = None) -> Any:
    """The parsed JSON of a cycle file; InputError("cycle") when it does not parse."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:
        raise InputError(f"{name or Path(path).name} is not JSON: {error}", "cycle") from None


def check_cycle_document(path: Path, frame_count: int) -> dict[str, Any]:
    """The whole document of a given cycle.json, checked alone and against a cache of frame_count frames."""
    document = read_cycle_document(path)
    fields = cycle_fields(document, Path(path).name)
    problem = cycle_range_problem(fields["start_frame"], fields["cycle_frames"], frame_count, Path(path).name)
    if problem is not None:
        raise InputError(problem, "cycle")
    return document


def check_cycle_upload(cycle_path: Path, cycle_name: str, looped_path: Path | None = None, looped_name: str | None = None) -> dict[str, Any]:
    """Validate an uploaded cycle.json (and its looped.pc2, which must hold exactly the cycle's frames).

    Returns {start_frame, cycle_frames, closing, looped_points (None without looped.pc2)}, recorded
    with the asset for the check of a bake request (check_cycle_fits_cloth).
    """
    from crowdbake.formats.pc2 import read_pc2
    from crowdbake.ingest.uploads import CACHE_EXTENSIONS, INVALID_FILE, FieldError, UploadRejected, _pc2_where, clean_message, expect_format

    expect_format(cycle_path, cycle_name, "cycle", CYCLE_EXTENSIONS)
    try:
        fields = cycle_fields(read_cycle_document(cycle_path, cycle_name), cycle_name)
    except InputError as error:
        raise UploadRejected(INVALID_FILE, "the cycle document cannot be used", [FieldError("cycle", error.message, cycle_name)]) from None
    info: dict[str, Any] = {"start_frame": fields["start_frame"], "cycle_frames": fields["cycle_frames"],
                            "closing": fields["method"], "looped_points": None}
    if looped_path is None:
        return info
    assert looped_name is not None
    expect_format(looped_path, looped_name, "looped", CACHE_EXTENSIONS)
    try:
        looped = read_pc2(looped_path)
    except ValueError as error:
        message = clean_message(str(error), looped_path, looped_name)
        raise UploadRejected(INVALID_FILE, "the looped cache does not parse", [FieldError("looped", message, looped_name, _pc2_where(looped_path))]) from None
    if looped.sample_count != fields["cycle_frames"]:
        raise UploadRejected(INVALID_FILE, "the looped cache is not the cycle's loop", [FieldError(
            "looped", f"{looped.sample_count} frames, but {cycle_name} says cycle_frames {fields['cycle_frames']}", looped_name, "byte 28")])
    info["looped_points"] = looped.point_count
    return info


def check_cycle_fits_cloth(cycle_info: dict[str, Any], cloth_info: dict[str, Any]) -> None:
    """A bake request's cycle against its cloth, from what both uploads recorded: the cycle lies within
    the cache's frames (as the validate stage checks), and a cycle that must be closed again (no
    looped.pc2, or one of another garment) has the frame after it (as the cycle stage needs).
    InputError("cycle")."""
    start, frames, have = cycle_info["start_frame"], cycle_info["cycle_frames"], cloth_info.get("frame_count", 0)
    problem = cycle_range_problem(start, frames, have)
    if problem is not None:
        raise InputError(problem, "cycle")
    reuses_loop = cycle_info.get("looped_points") is not None and cycle_info["looped_points"] == cloth_info.get("vertex_count")
    if not reuses_loop and cycle_info.get("closing", "none") != "none" and start + frames + 1 > have:
        raise InputError(f"closing the cycle needs frame {start + frames}, the cache ends at {have - 1} (upload looped.pc2 with cycle.json)", "cycle")
