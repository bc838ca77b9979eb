"""A chosen cycle (cycle.json from `crowdbake cycle`, optionally its looped.pc2): one set of checks for
`crowdbake bake --cycle`, the cycle upload (POST /v1/assets/cycles) and a bake request that names one.

- cycle_fields / check_cycle_document: the document alone and against the cloth's frame count
  (InputError("cycle")), as the validate stage applies them;
- check_cycle_upload: an uploaded pair (UploadRejected with FieldErrors, as every upload check);
- check_cycle_fits_cloth: a bake request's cycle asset against its cloth asset, from what both uploads
  recorded.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from crowdbake.errors import InputError
from crowdbake.ingest.json_documents import loads_strict
from crowdbake.params import CLOSE_METHODS, MIN_CYCLE_FRAMES, fps_problem

# sniff_format (crowdbake.ingest.uploads) calls any JSON object "gltf": for cycle.json that means "a JSON
# document", and only bytes of another known format (a PNG, a PC2...) are a mismatch.
CYCLE_EXTENSIONS = {".json": "gltf"}


class CycleFieldError(InputError):
    """A field of a cycle document a bake cannot use; `pointer` is its JSON pointer (RFC 6901)."""

    def __init__(self, message: str, pointer: str):
        super().__init__(message, "cycle")
        self.pointer = pointer


# Frame numbers of a cycle document: a PC2 counts its samples in a signed 32-bit field, so no cache
# has a frame past this; a bigger number is refused before any arithmetic or allocation sees it.
MAX_FRAME_NUMBER = (1 << 31) - 1


def _refuse(name: str, pointer: str, problem: str) -> CycleFieldError:
    return CycleFieldError(f"{name}: {pointer} {problem}", pointer)


def _frame_number(document: dict, key: str, name: str) -> int:
    value = document.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= MAX_FRAME_NUMBER:
        raise _refuse(name, f"/{key}", f"must be an integer in 0..{MAX_FRAME_NUMBER}, got {_shown(value)}")
    return value


def _shown(value: Any) -> str:
    """A value for a message, cut short (a 4,000-digit number is not repeated back)."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _section(document: dict, key: str, name: str) -> dict:
    """An optional object member (absent or null: {})."""
    value = document.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise _refuse(name, f"/{key}", f"must be a JSON object, got {type(value).__name__}")
    return value


def cycle_fields(document: Any, name: str = "cycle.json") -> dict[str, Any]:
    """Every field a bake reads of a cycle document (crowdbake.stages.cycle), checked:
    {start_frame, end_frame, cycle_frames, method, fps (None: the cache's), root_motion_removed}.

    CycleFieldError (an InputError("cycle")) naming the field by its JSON pointer when the document is
    no object; a frame number is no integer in 0..MAX_FRAME_NUMBER; the cycle is shorter than 2 frames;
    end_frame is not start_frame + cycle_frames; closing, input, seam or root_motion is no object;
    closing.method is unknown; input.fps is outside crowdbake.params' MIN_FPS..MAX_FPS; a seam ratio
    is no finite non-negative number; root_motion.removed is no boolean."""
    if not isinstance(document, dict):
        raise CycleFieldError(f"{name} must hold a JSON object", "")
    start, frames = _frame_number(document, "start_frame", name), _frame_number(document, "cycle_frames", name)
    if frames < MIN_CYCLE_FRAMES:
        raise _refuse(name, "/cycle_frames", f"must be at least {MIN_CYCLE_FRAMES}")
    end = document.get("end_frame", start + frames)
    if end != start + frames or isinstance(end, bool) or not isinstance(end, int):
        raise _refuse(name, "/end_frame", f"must be start_frame + cycle_frames ({start + frames}), got {_shown(end)}")
    method = _section(document, "closing", name).get("method", "none")
    if method not in CLOSE_METHODS:
        raise _refuse(name, "/closing/method", f"must be one of {CLOSE_METHODS}")
    fps = _section(document, "input", name).get("fps")
    if fps is not None and (problem := fps_problem(fps)) is not None:
        raise _refuse(name, "/input/fps", problem)
    seam = _section(document, "seam", name)
    for key in ("position_jump_ratio", "velocity_jump_ratio"):
        ratio = seam.get(key)
        if ratio is not None and (isinstance(ratio, bool) or not isinstance(ratio, (int, float)) or not math.isfinite(ratio) or ratio < 0):
            raise _refuse(name, f"/seam/{key}", f"must be a finite non-negative number or null, got {_shown(ratio)}")
    removed = _section(document, "root_motion", name).get("removed", False)
    if not isinstance(removed, bool):
        raise _refuse(name, "/root_motion/removed", f"must be true or false, got {_shown(removed)}")
    return {"start_frame": start, "end_frame": end, "cycle_frames": frames, "method": method,
            "fps": None if fps is None else float(fps), "root_motion_removed": removed}


def cycle_range_problem(start_frame: int, cycle_frames: int, frame_count: int, name: str = "cycle.json") -> str | None:
    """Why the cycle [start_frame, start_frame + cycle_frames) does not fit a cache of frame_count frames."""
    if start_frame + cycle_frames > frame_count:
        return f"{name}: the cycle [{start_frame}, {start_frame + cycle_frames}) runs past the cache's {frame_count} frames"
    return None


def read_cycle_document(path: Path, name: str | None = None) -> Any:
    """The parsed JSON of a cycle file; InputError("cycle") when it does not parse or names a key twice
    in one object."""
    try:
        return loads_strict(Path(path).read_text(encoding="utf-8"))
    # ValueError covers json's refusal of an integer over 4,300 digits, which is not a JSONDecodeError.
    except (OSError, ValueError, RecursionError) as error:
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
        where = getattr(error, "pointer", None)
        raise UploadRejected(INVALID_FILE, "the cycle document cannot be used", [FieldError("cycle", error.message, cycle_name, where or None)]) from None
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
