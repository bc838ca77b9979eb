"""A clip timeline (timeline.json): which clip, at which clip frame, plays at each frame of a cloth cache
simulated across several clips. One set of checks for `crowdbake bake --timeline`, `crowdbake cycle
--timeline`, the timeline upload (POST /v1/assets/timelines) and a bake request that names one.

The document (as ../shared/assets/robot_clips/timeline.json):

    {"fps": 24, "total_frames": 717,
     "segments": [{"clip": "Idle", "first_frame": 0, "last_frame": 320, "pure_first_frame": 0,
                   "pure_last_frame": 314, "clip_frames": 80}, ...],
     "frames": [{"frame": 0, "clip": "Idle", "clip_frame": 0, ...}, ...]}      (optional)

Frames are 0-based cache samples, ranges inclusive; a segment blends with its neighbours outside its
pure frames. `"new_simulation": true` on a segment says its cloth was simulated apart from the segment
before (one cache per clip, crowdbake.ingest.clip_caches): no transition is taken across it. Without `frames`, clip frame f of a segment is (f - first_frame) mod clip_frames.

- timeline_fields: the document alone (TimelineFieldError naming the JSON pointer);
- check_timeline_fits: against the cache (frame count, rate) and the character's clips.

Every field is typed and bounded at this boundary, and every count is checked before anything is made
per claimed item: a file of a few bytes may not claim a billion frames, and the work of reading one is
linear in its size (a segment blends only with its neighbours, so segments cover each frame at most twice).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from crowdbake.bake.timeline import FrameBlends, Segment, Timeline
from crowdbake.errors import InputError
from crowdbake.ingest.json_documents import loads_strict
from crowdbake.params import MAX_CYCLE_FRAMES, MIN_CYCLE_FRAMES, fps_problem

# The most frames a timeline may describe: the longest cloth cache a bake reads as an OBJ sequence
# (crowdbake.formats.cloth_cache.MAX_SEQUENCE_FRAMES), about 70 minutes at 24 fps; the sample's is 717.
# It bounds every per-frame array made from a timeline.
MAX_TIMELINE_FRAMES = 100_000
# A timeline with a row per frame takes about 130 bytes a frame (../shared/assets/robot_clips: 94 kB for
# 717 frames), so 16 MiB holds MAX_TIMELINE_FRAMES rows with room to spare; parsed, it stays within a
# few hundred megabytes of Python objects.
MAX_TIMELINE_BYTES = 16 << 20
# Clip names become file names of the bundle (clips/<name>.pc2): short, printable, no path separator.
MAX_CLIP_NAME = 64
# A timeline's rate and the cache's agree when within this relative difference (24 vs 23.976 does not).
FPS_TOLERANCE = 1e-4
_SEGMENT_FRAMES = ("first_frame", "last_frame", "pure_first_frame", "pure_last_frame")


class TimelineFieldError(InputError):
    """A field of a timeline a bake cannot use; `pointer` is its JSON pointer (RFC 6901)."""

    def __init__(self, message: str, pointer: str):
        super().__init__(message, "timeline")
        self.pointer = pointer


def _refuse(name: str, pointer: str, problem: str) -> TimelineFieldError:
    return TimelineFieldError(f"{name}: {pointer} {problem}", pointer)


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _integer(container: dict, key: str, pointer: str, name: str, low: int = 0, high: int = MAX_TIMELINE_FRAMES) -> int:
    value = container.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise _refuse(name, pointer, f"must be an integer in {low}..{high}, got {_shown(value)}")
    return value


def clip_name_problem(value: Any) -> str | None:
    """Why `value` cannot name a clip (it becomes a file name), or None."""
    if not isinstance(value, str) or not value:
        return f"must be a clip name, got {_shown(value)}"
    if len(value) > MAX_CLIP_NAME:
        return f"must be a clip name of at most {MAX_CLIP_NAME} characters, got {len(value)}"
    if not value.isprintable() or "/" in value or "\\" in value:
        return f"must be a clip name without control characters or path separators, got {_shown(value)}"
    return None


def _clip(container: dict, key: str, pointer: str, name: str) -> str:
    value = container.get(key)
    if (problem := clip_name_problem(value)) is not None:
        raise _refuse(name, pointer, problem)
    return value


def _segment(entry: Any, k: int, total: int, name: str) -> Segment:
    pointer = f"/segments/{k}"
    if not isinstance(entry, dict):
        raise _refuse(name, pointer, "must be a JSON object")
    clip = _clip(entry, "clip", f"{pointer}/clip", name)
    first, last, pure_first, pure_last = (_integer(entry, key, f"{pointer}/{key}", name, 0, total - 1) for key in _SEGMENT_FRAMES)
    if not first <= pure_first <= pure_last <= last:
        raise _refuse(name, f"{pointer}/pure_first_frame",
                      f"needs first_frame <= pure_first_frame <= pure_last_frame <= last_frame, got {first}, {pure_first}, {pure_last}, {last}")
    period = entry.get("clip_frames")
    if not isinstance(period, int) or isinstance(period, bool) or not MIN_CYCLE_FRAMES <= period <= MAX_CYCLE_FRAMES:
        raise _refuse(name, f"{pointer}/clip_frames",
                      f"must be an integer of at least {MIN_CYCLE_FRAMES} (the clip's frames) and at most {MAX_CYCLE_FRAMES}, got {_shown(period)}")
    restart = entry.get("new_simulation", False)
    if not isinstance(restart, bool):
        raise _refuse(name, f"{pointer}/new_simulation", f"must be true or false, got {_shown(restart)}")
    return Segment(clip, first, last, pure_first, pure_last, period, restart)


def _blends_from_rows(rows: list, periods: dict[str, int], name: str) -> FrameBlends:
    """The rows' blends (weight, blend_from, blend_from_frame), checked: a weight in 0..1 (default 1), a
    clip fading out that the segments name, its frame within its period."""
    weight = np.ones(len(rows))
    blend_from: list[str | None] = [None] * len(rows)
    blend_from_frame = np.zeros(len(rows), dtype=np.int64)
    for f, row in enumerate(rows):
        value = row.get("weight", 1.0)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0.0 <= value <= 1.0:
            raise _refuse(name, f"/frames/{f}/weight", f"must be a number in 0..1, got {_shown(value)}")
        weight[f] = float(value)
        if row.get("blend_from") is None:
            if value < 1.0:
                raise _refuse(name, f"/frames/{f}/blend_from", f"must name the clip fading out: the weight is {value:g}")
            continue
        fading = _clip_of(row, "blend_from", f"/frames/{f}/blend_from", periods, name)
        blend_from[f] = fading
        blend_from_frame[f] = _integer(row, "blend_from_frame", f"/frames/{f}/blend_from_frame", name, 0, periods[fading] - 1)
    return FrameBlends(tuple(row["clip"] for row in rows), weight, tuple(blend_from), blend_from_frame)


def _clip_of(row: dict, key: str, pointer: str, periods: dict[str, int], name: str) -> str:
    """The clip a row names under `key`, which must be one of the segments' clips."""
    clip = row.get(key)
    if not isinstance(clip, str) or clip not in periods:
        shown = ", ".join(list(periods)[:8]) + (", ..." if len(periods) > 8 else "")
        raise _refuse(name, pointer, f"must be a clip of the segments ({shown}), got {_shown(clip)}")
    return clip


def _clip_frames_from_rows(rows: Any, segments: list[Segment], total: int, name: str) -> np.ndarray:
    """(total,) int64 clip frame per cache frame from the per-frame rows, checked against the segments."""
    if not isinstance(rows, list) or len(rows) != total:
        raise _refuse(name, "/frames", f"must list one row per frame ({total}), got {_shown(len(rows) if isinstance(rows, list) else rows)}")
    clip_frame = np.zeros(total, dtype=np.int64)
    periods = {s.clip: s.clip_frames for s in segments}
    for f, row in enumerate(rows):
        if not isinstance(row, dict):
            raise _refuse(name, f"/frames/{f}", "must be a JSON object")
        if "frame" in row and (type(row["frame"]) is not int or row["frame"] != f):  # bool is no frame number
            raise _refuse(name, f"/frames/{f}/frame", f"must be {f} (rows in frame order), got {_shown(row['frame'])}")
        clip = _clip_of(row, "clip", f"/frames/{f}/clip", periods, name)
        clip_frame[f] = _integer(row, "clip_frame", f"/frames/{f}/clip_frame", name, 0, periods[clip] - 1)
    # A pure frame shows its segment's clip alone: the row's clip, or the clip it fades from at weight 0
    # (the first frame of a blend, where the next strip starts at weight 0).
    for k, s in enumerate(segments):
        for f in range(s.pure_first_frame, s.pure_last_frame + 1):
            row = rows[f]
            if row["clip"] == s.clip:
                continue
            if row.get("blend_from") == s.clip and row.get("weight") == 0:
                clip_frame[f] = _integer(row, "blend_from_frame", f"/frames/{f}/blend_from_frame", name, 0, s.clip_frames - 1)
                continue
            raise _refuse(name, f"/frames/{f}/clip", f"must be {s.clip!r}: frame {f} is a pure frame of segment {k}, got {_shown(row['clip'])}")
    return clip_frame


def _check_segment_order(segments: list[Segment], total: int, name: str) -> dict[str, int]:
    """The segments as a sequence over the cache, checked; returns {clip: period}. They must start at frame
    0, follow each other without a gap to the cache's last frame, keep their pure frames apart and blend only
    with their neighbours (so no frame lies in more than two segments); a clip keeps one period, and two
    clips' names differ under case folding (each becomes a file name)."""
    periods: dict[str, int] = {}
    folded: dict[str, str] = {}
    for k, s in enumerate(segments):
        if k and s.first_frame <= segments[k - 1].first_frame:
            raise _refuse(name, f"/segments/{k}/first_frame", f"must come after segment {k - 1}'s ({segments[k - 1].first_frame}): segments in playing order")
        if k and s.first_frame > segments[k - 1].last_frame + 1:
            raise _refuse(name, f"/segments/{k}/first_frame", f"{s.first_frame} leaves frames after segment {k - 1}'s last ({segments[k - 1].last_frame}) "
                                                              "that no clip plays")
        if k >= 2 and s.first_frame <= segments[k - 2].last_frame:
            raise _refuse(name, f"/segments/{k}/first_frame", f"{s.first_frame} lies within segment {k - 2} (to {segments[k - 2].last_frame}): "
                                                              "a segment blends only with its neighbours")
        if k and s.pure_first_frame <= segments[k - 1].pure_last_frame:
            raise _refuse(name, f"/segments/{k}/pure_first_frame",
                          f"{s.pure_first_frame} overlaps segment {k - 1}'s pure frames (to {segments[k - 1].pure_last_frame}): only blends may overlap")
        if folded.setdefault(s.clip.casefold(), s.clip) != s.clip:
            raise _refuse(name, f"/segments/{k}/clip", f"{s.clip!r} differs from the clip {folded[s.clip.casefold()]!r} only in case: "
                                                       "both would be one file of the bundle")
        if periods.setdefault(s.clip, s.clip_frames) != s.clip_frames:
            raise _refuse(name, f"/segments/{k}/clip_frames", f"{s.clip!r} has {periods[s.clip]} frames in an earlier segment, here {s.clip_frames}")
    if segments[0].first_frame != 0:
        raise _refuse(name, "/segments/0/first_frame", f"must be 0: the segments cover the cache from its first frame, got {segments[0].first_frame}")
    if segments[-1].last_frame != total - 1:
        last = len(segments) - 1
        raise _refuse(name, f"/segments/{last}/last_frame", f"must be {total - 1}: the segments cover the cache's total_frames ({total}), "
                                                            f"got {segments[last].last_frame}")
    return periods


def _clip_frames_from_segments(segments: list[Segment], total: int) -> np.ndarray:
    """(total,) int64 clip frame per cache frame when the timeline has no rows: (f - first_frame) mod
    clip_frames of the newest segment playing. Segments cover each frame at most twice, so this is
    O(total_frames)."""
    clip_frame = np.zeros(total, dtype=np.int64)
    for s in segments:
        np.remainder(np.arange(s.last_frame - s.first_frame + 1), s.clip_frames, out=clip_frame[s.first_frame:s.last_frame + 1])
    return clip_frame


def timeline_fields(document: Any, name: str = "timeline.json") -> Timeline:
    """The timeline a bake reads, checked alone. TimelineFieldError (InputError("timeline")) naming the
    field by its JSON pointer when: the document is no object; fps is outside crowdbake.params' range;
    total_frames is no integer in 2..MAX_TIMELINE_FRAMES; segments is no non-empty list; a segment lacks
    a clip name (clip_name_problem), has a frame outside the cache or out of order within it, or a clip
    period outside MIN_CYCLE_FRAMES..MAX_CYCLE_FRAMES; the segments do not cover the cache in order
    (_check_segment_order); a per-frame row disagrees or is of the wrong type."""
    if not isinstance(document, dict):
        raise TimelineFieldError(f"{name} must hold a JSON object", "")
    fps = document.get("fps")
    if (problem := fps_problem(fps)) is not None:
        raise _refuse(name, "/fps", problem)
    total = _integer(document, "total_frames", "/total_frames", name, 2)
    entries = document.get("segments")
    if not isinstance(entries, list) or not entries:
        raise _refuse(name, "/segments", "must be a non-empty list of segments")
    segments = [_segment(entry, k, total, name) for k, entry in enumerate(entries)]
    periods = _check_segment_order(segments, total, name)
    blends = None
    if document.get("frames") is not None:
        clip_frame = _clip_frames_from_rows(document["frames"], segments, total, name)
        blends = _blends_from_rows(document["frames"], periods, name)
    else:
        clip_frame = _clip_frames_from_segments(segments, total)
    return Timeline(float(fps), total, tuple(segments), clip_frame, blends)


def read_timeline(path: Path, name: str | None = None) -> Timeline:
    """timeline_fields of a file; InputError("timeline") when it is over MAX_TIMELINE_BYTES or does not
    parse (duplicate keys included)."""
    shown = name or Path(path).name
    try:
        size = Path(path).stat().st_size
        if size > MAX_TIMELINE_BYTES:
            raise InputError(f"{shown} is {size} bytes; a timeline has at most {MAX_TIMELINE_BYTES}", "timeline")
        document = loads_strict(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as error:
        raise InputError(f"{shown} is not JSON: {error}", "timeline") from None
    return timeline_fields(document, shown)


def check_timeline_fits(timeline: Timeline, frame_count: int, fps: float | None, clips: dict[str, float] | None,
                        name: str = "timeline.json") -> None:
    """The timeline against the cloth cache (frame_count frames at `fps`, None: not known) and the
    character's clips ({name: seconds}, None: not known). TimelineFieldError naming the field when the
    frame count or rate differ, a clip is missing (listing the character's clips), or a clip's period is
    not its duration at the rate."""
    if timeline.total_frames != frame_count:
        raise _refuse(name, "/total_frames", f"is {timeline.total_frames}, but the cloth cache has {frame_count} frames")
    if fps is not None and not math.isclose(timeline.fps, fps, rel_tol=FPS_TOLERANCE):
        raise _refuse(name, "/fps", f"is {timeline.fps:g}, but the cloth cache plays at {fps:g} frames per second")
    if clips is None:
        return
    for k, s in enumerate(timeline.segments):
        if s.clip not in clips:
            listed = ", ".join(repr(c) for c in clips) or "none"
            raise _refuse(name, f"/segments/{k}/clip", f"names {s.clip!r}, which the character lacks (it has {listed})")
        frames = int(round(clips[s.clip] * timeline.fps))
        if frames != s.clip_frames:
            raise _refuse(name, f"/segments/{k}/clip_frames",
                          f"is {s.clip_frames}, but {s.clip!r} lasts {clips[s.clip]:.4g} s = {frames} frames at {timeline.fps:g} fps")


def check_timeline_upload(path: Path, filename: str) -> dict[str, Any]:
    """Validate an uploaded timeline.json (POST /v1/assets/timelines); UploadRejected with the JSON pointer
    as `where`. Returns what the bake request's check needs: {fps, total_frames, clips: {name: frames}}."""
    from crowdbake.ingest.uploads import INVALID_FILE, FieldError, UploadRejected, expect_format

    expect_format(path, filename, "timeline", {".json": "gltf"})  # sniff_format calls any JSON object "gltf"
    try:
        timeline = read_timeline(path, filename)
    except InputError as error:
        where = getattr(error, "pointer", None)
        raise UploadRejected(INVALID_FILE, "the timeline cannot be used", [FieldError("timeline", error.message, filename, where or None)]) from None
    return {"fps": timeline.fps, "total_frames": timeline.total_frames, "clips": dict(timeline.periods), "segments": len(timeline.segments)}


def check_timeline_request(timeline_info: dict[str, Any], character_info: dict[str, Any], cloth_info: dict[str, Any],
                           fps: float, animation: int | str | None) -> None:
    """A bake request's timeline against its cloth and character, from what the uploads recorded (as the
    validate stage checks the files): TimelineFieldError for the frame count, the rate or a clip the
    character lacks; InputError("params.animation") for an animation the timeline does not play."""
    from crowdbake.ingest.studio_inputs import MAX_ANIMATION_SUMMARIES

    total, rate, periods = timeline_info["total_frames"], float(timeline_info["fps"]), timeline_info["clips"]
    if total != cloth_info.get("frame_count"):
        raise _refuse("timeline", "/total_frames", f"is {total}, but the cloth cache has {cloth_info.get('frame_count')} frames")
    if not math.isclose(rate, fps, rel_tol=FPS_TOLERANCE):
        raise _refuse("timeline", "/fps", f"is {rate:g}, but the cloth cache plays at {fps:g} frames per second")
    summaries = character_info.get("animations")
    if isinstance(summaries, list) and len(summaries) < MAX_ANIMATION_SUMMARIES:  # every clip is known
        seconds = {entry.get("name"): float(entry.get("seconds") or 0.0) for entry in summaries}
        for clip, frames in periods.items():
            if clip not in seconds:
                listed = ", ".join(repr(name) for name in seconds) or "none"
                raise _refuse("timeline", "/segments", f"names {clip!r}, which the character lacks (it has {listed})")
            if int(round(seconds[clip] * rate)) != frames:
                raise _refuse("timeline", "/segments", f"gives {clip!r} {frames} frames, but it lasts {seconds[clip]:.4g} s = "
                                                       f"{int(round(seconds[clip] * rate))} frames at {rate:g} fps")
    if animation is not None and animation not in periods:
        raise InputError(f"animation {animation!r} is not a clip of the timeline (it plays {', '.join(periods)}): name one of them", "params.animation")
