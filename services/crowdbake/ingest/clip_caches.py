"""Several clips from one cloth cache per clip: each cache a separate simulation of one clip, started from
rest and playing that clip from its frame 0. `crowdbake bake --clip-cloth NAME=CACHE[,MESH]` (repeatable)
and a REST bake's `clip_cloth` ({clip: cloth asset}) come here.

The caches are joined, in the order given, into the one cache and timeline the several-clip bake reads
(crowdbake.stages.cycle_job): a segment per cache, no blends, each segment marked `new_simulation` so no
transition is searched across the join (no simulation carried the cloth from one clip into the next). The
bundle (format 3) then holds every clip's loop and no transitions.

    parse_clip_cloth(values) -> [ClipCloth]                 the command line's NAME=CACHE[,MESH]
    join_clip_frames(caches, clips, periods, fps) -> (frames, timeline document)   numpy in/out, checked
    write_joined_inputs(entries, character, fps, folder) -> (cloth.pc2, cloth.obj, timeline.json)

Every refusal is an InputError naming the field "clip_cloth" (the CLI shows it as --clip-cloth, REST as
clip_cloth.NAME).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from crowdbake.errors import InputError
from crowdbake.params import BASE_FPS, CYCLES_NEEDED, MIN_CYCLE_FRAMES, cache_fps

if TYPE_CHECKING:
    import numpy as np

# numpy is imported where the caches are read: `crowdbake submit` parses --clip-cloth with this module
# and runs without the bake stack (services/tests/test_client_package.py).
FIELD = "clip_cloth"


@dataclass(frozen=True)
class ClipCloth:
    """One clip's cloth: `clip` names an animation of the character; cache: its simulated cache (any
    format crowdbake reads); mesh: the rest mesh (.obj) a .pc2 / .mdd needs, or None."""

    clip: str
    cache: Path
    mesh: Path | None = None


def clip_field(clip: str) -> str:
    """The field an error about one clip's cache names (REST: clip_cloth.NAME)."""
    return f"{FIELD}.{clip}"


def parse_clip_cloth(values: list[str], default_mesh: Path | None = None) -> list[ClipCloth]:
    """NAME=CACHE[,MESH] strings (order kept) -> ClipCloth; MESH defaults to `default_mesh` (--cloth-mesh).
    InputError("clip_cloth") for a malformed value or a clip given twice."""
    entries: list[ClipCloth] = []
    for value in values:
        name, sep, files = value.partition("=")
        paths = [part for part in files.split(",")] if sep else []
        if not name.strip() or not paths or not paths[0] or len(paths) > 2 or (len(paths) == 2 and not paths[1]):
            raise InputError(f"{value!r} must read NAME=CACHE or NAME=CACHE,MESH.obj", FIELD)
        entries.append(ClipCloth(name.strip(), Path(paths[0]), Path(paths[1]) if len(paths) == 2 else default_mesh))
    check_distinct([entry.clip for entry in entries])
    return entries


def check_distinct(clips: list[str]) -> None:
    """InputError("clip_cloth") unless there are clips, each named once."""
    if not clips:
        raise InputError("name at least one clip and its cloth cache", FIELD)
    seen = set()
    for clip in clips:
        if clip in seen:
            raise InputError(f"clip {clip!r} is given two cloth caches: give one cache per clip", FIELD)
        seen.add(clip)


def check_clip_lengths(clips: list[str], frame_counts: list[int], periods: dict[str, int]) -> None:
    """Each clip known to the character ({clip: period in cache frames}) and its cache at least two of
    its periods long (the loop search's need, crowdbake.params.min_cloth_frames). InputError naming the clip."""
    for clip, count in zip(clips, frame_counts):
        if clip not in periods:
            listed = ", ".join(repr(name) for name in periods) or "none"
            raise InputError(f"clip {clip!r}: the character has no such animation (it has {listed})", FIELD)
        if periods[clip] < MIN_CYCLE_FRAMES:
            raise InputError(f"clip {clip!r} lasts {periods[clip]} frames at this rate: too short to loop", FIELD)
        needed = CYCLES_NEEDED * periods[clip]
        if count < needed:
            raise InputError(f"clip {clip!r}: its cache has {count} frames, fewer than two cycles of the clip "
                             f"({periods[clip]} frames each, {needed} in all)", FIELD)


def join_clip_frames(frames: list[np.ndarray], clips: list[str], periods: dict[str, int], fps: float) -> tuple[np.ndarray, dict]:
    """The caches end to end and their timeline.

    frames: per clip (F_i, P, 3) float cloth points (same P for all); clips: the clip of each; periods:
    {clip: frames a cycle} at `fps` frames per second. Returns ((sum F_i, P, 3) float32, the timeline.json
    document: a segment per cache, all its frames pure, clip frame 0 at its first frame, `new_simulation`
    from the second on). InputError("clip_cloth") for differing point counts or a short cache."""
    import numpy as np

    check_distinct(clips)
    counts = [int(np.shape(f)[0]) for f in frames]
    check_clip_lengths(clips, counts, periods)
    points = {int(np.shape(f)[1]) for f in frames}
    if len(points) != 1:
        shown = ", ".join(f"{clip} {np.shape(f)[1]}" for clip, f in zip(clips, frames))
        raise InputError(f"the clips' caches must move the same garment: their point counts differ ({shown})", FIELD)
    segments, first = [], 0
    for k, (clip, count) in enumerate(zip(clips, counts)):
        last = first + count - 1
        segments.append({"clip": clip, "first_frame": first, "last_frame": last, "pure_first_frame": first, "pure_last_frame": last,
                         "clip_frames": periods[clip], **({"new_simulation": True} if k else {})})
        first = last + 1
    document = {"fps": float(fps), "total_frames": first, "segments": segments}
    return np.concatenate([np.asarray(f, dtype=np.float32) for f in frames]), document


def _same_rest_mesh(a, b) -> bool:
    """Same garment: the rest meshes' triangles, UVs and point order agree (positions may differ: each
    simulation starts from rest on its own clip's first pose)."""
    import numpy as np

    if a.position_count != b.position_count or a.faces.shape != b.faces.shape or not np.array_equal(a.faces, b.faces):
        return False
    if not np.array_equal(a.source_index, b.source_index):
        return False
    if (a.uvs is None) != (b.uvs is None):
        return False
    return a.uvs is None or (a.uvs.shape == b.uvs.shape and np.allclose(a.uvs, b.uvs, atol=1e-6))


def write_joined_inputs(entries: list[ClipCloth], character: Path, fps: float | None, folder: Path) -> tuple[Path, Path, Path]:
    """Read every clip's cache, check them against each other and the character, and write the joined
    cache (folder/cloth.pc2 + cloth.obj, the first cache's rest mesh) and folder/timeline.json. `fps`:
    the bake's fps parameter or None (each cache's own rate, which must agree). The files take the
    newest source's modification time, so a bake's `created` stays a property of its inputs."""
    from crowdbake.formats.cloth_cache import ClothCache, write_pc2_obj
    from crowdbake.formats.errors import FormatError
    from crowdbake.ingest.clip_choice import character_clips
    from crowdbake.ingest.garment import read_cloth

    check_distinct([entry.clip for entry in entries])
    try:
        known = {clip.name: clip.seconds for clip in character_clips(character)}
    except (ValueError, FormatError, OSError, KeyError, TypeError, AttributeError) as error:
        raise InputError(f"{Path(character).name}: {str(error).splitlines()[0] if str(error) else type(error).__name__}", "character") from None
    caches, rates = [], []
    for entry in entries:
        if entry.clip not in known:
            listed = ", ".join(repr(name) for name in known) or "none"
            raise InputError(f"clip {entry.clip!r}: the character has no such animation (it has {listed})", FIELD)
        for path in (entry.cache, entry.mesh):
            if path is not None and not Path(path).is_file():
                raise InputError(f"clip {entry.clip!r}: {path} does not exist or is not a file", FIELD)
        try:
            cache = read_cloth(entry.cache, entry.mesh)
        except InputError as error:
            raise InputError(f"clip {entry.clip!r}: {error.message}", FIELD) from None
        try:
            rates.append(cache_fps(fps, cache.fps, cache.frame_step))
        except InputError as error:
            raise InputError(f"clip {entry.clip!r}: {error.message}", FIELD) from None
        if caches and cache.point_count != caches[0].point_count:
            raise InputError(f"clip {entry.clip!r}: its cache moves {cache.point_count} points, clip {entries[0].clip!r}'s "
                             f"{caches[0].point_count}: the clips' caches must move the same garment", FIELD)
        if caches and not _same_rest_mesh(cache.mesh, caches[0].mesh):
            raise InputError(f"clip {entry.clip!r}: its rest mesh differs from clip {entries[0].clip!r}'s (triangles, UVs or "
                             "point order): the clips' caches must move the same garment", FIELD)
        caches.append(cache)
    if len({round(rate, 6) for rate in rates}) > 1:
        shown = ", ".join(f"{e.clip} {rate:g}" for e, rate in zip(entries, rates))
        raise InputError(f"the clips' caches play at different rates ({shown} frames per second): give them one rate", FIELD)
    rate = rates[0]
    periods = {clip: int(round(seconds * rate)) for clip, seconds in known.items()}
    frames, document = join_clip_frames([cache.frames for cache in caches], [e.clip for e in entries], periods, rate)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    # Read back at `rate` when no fps parameter is given (a PC2 stores only BASE_FPS / its sample interval).
    joined = ClothCache(caches[0].mesh, frames, None, BASE_FPS / rate, "pc2")
    paths = folder / "cloth.pc2", folder / "cloth.obj", folder / "timeline.json"
    write_pc2_obj(joined, paths[0], paths[1])
    paths[2].write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
    newest = max(Path(p).stat().st_mtime for e in entries for p in (e.cache, e.mesh) if p is not None)
    for path in paths:
        os.utime(path, (newest, newest))
    return paths


def check_clip_cloth_request(character_info: dict, clips: list[str], cloth_infos: list[dict], fps: float | None) -> None:
    """A REST bake's clip_cloth from what the uploads recorded (as write_joined_inputs checks the files;
    the rest meshes' triangles and UVs are compared by the worker). InputError naming the entry
    (field "clip_cloth.K.clip" for the name, "clip_cloth.K" for its cloth) for a clip given twice, one the
    character lacks (when its clips are all known), a cache of other point or triangle counts than the first,
    another frame rate, or fewer frames than two of its clip's cycles."""
    from crowdbake.ingest.bake_request import request_fps
    from crowdbake.ingest.studio_inputs import MAX_ANIMATION_SUMMARIES

    if not clips:
        raise InputError("name at least one clip and its cloth cache", FIELD)
    summaries = character_info.get("animations")
    every_clip_known = isinstance(summaries, list) and len(summaries) < MAX_ANIMATION_SUMMARIES
    seconds = {entry.get("name"): float(entry.get("seconds") or 0.0) for entry in summaries or []}
    first_rate = None
    for k, (clip, info) in enumerate(zip(clips, cloth_infos)):
        if clip in clips[:k]:
            raise InputError(f"clip {clip!r} is given two cloth caches (entries {clips.index(clip)} and {k}): give one cache per clip", f"{FIELD}.{k}.clip")
        if clip not in seconds:
            if every_clip_known:
                listed = ", ".join(repr(name) for name in seconds) or "none"
                raise InputError(f"clip {clip!r}: the character has no such animation (it has {listed})", f"{FIELD}.{k}.clip")
            continue
        try:
            rate = request_fps(info, fps)
        except InputError as error:
            raise InputError(f"clip {clip!r}: {error.message}", f"{FIELD}.{k}") from None
        first_rate = rate if first_rate is None else first_rate
        if abs(rate - first_rate) > 1e-6 * first_rate:
            raise InputError(f"clip {clip!r}: its cache plays at {rate:g} frames per second, clip {clips[0]!r}'s at {first_rate:g}: "
                             "give them one rate", f"{FIELD}.{k}")
        for count in ("vertex_count", "triangle_count"):
            if k and info.get(count) != cloth_infos[0].get(count):
                raise InputError(f"clip {clip!r}: its cache has {info.get(count)} {count.split('_')[0]}s, clip {clips[0]!r}'s "
                                 f"{cloth_infos[0].get(count)}: the clips' caches must move the same garment", f"{FIELD}.{k}")
        period = int(round(seconds[clip] * rate))
        if period < MIN_CYCLE_FRAMES:
            raise InputError(f"clip {clip!r} lasts {period} frames at {rate:g} fps: too short to loop", f"{FIELD}.{k}.clip")
        needed = CYCLES_NEEDED * period
        if info.get("frame_count", 0) < needed:
            raise InputError(f"clip {clip!r}: its cache has {info.get('frame_count', 0)} frames, fewer than two cycles of the clip "
                             f"({period} frames each, {needed} in all)", f"{FIELD}.{k}")
