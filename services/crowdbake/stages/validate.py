"""Stage 1, validate: check every input and parameter, copy the inputs into work/inputs, write the job.

Each input file is parsed once here (the character, the cloth cache, its mesh); later stages read the
copies. Every cloth cache crowdbake takes (PC2 or MDD with an OBJ, Alembic, a zip of OBJ frames) is
staged as work/inputs/cloth.pc2 + cloth.obj in Y-up metres, its frame rate in the JobRecord (`fps`),
after its first frame was checked against the character (crowdbake.ingest.garment.place_cloth). `created` in the manifest is the only clock-like value: BakeInputs.created when given, else the
SOURCE_DATE_EPOCH environment variable (the reproducible-builds convention), else the newest
modification time of the input files: a property of the inputs, so a rebake of unchanged files gives the
same bytes.
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import re
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from PIL import Image

import logging

from crowdbake import __version__
from crowdbake.errors import InputError
from crowdbake.files import sha256_file
from crowdbake.formats.errors import FormatError
from crowdbake.formats.gltf import load_character
from crowdbake.formats.cloth_cache import ClothCache, write_pc2_obj
from crowdbake.ingest.cycle_document import check_cycle_document
from crowdbake.ingest.garment import CACHE_SUFFIXES, body_at_rest, check_garment_fit, needs_mesh, place_cloth, read_cloth
from crowdbake.params import CREATED_RULE, NAME_RULE, PART_RULE, VERSION_RULE, BakeParams, cache_fps, min_cloth_frames
from crowdbake.stages.records import JobRecord
from crowdbake.stages.workdir import StageOutcome, WorkDir, read_json, stage_key

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BakeInputs:
    """The files and identity of one bake. cloth: None bakes the body alone (crowdbake.stages.body_only), or .pc2 or .mdd (with cloth_mesh, an .obj), .abc or an
    OBJ-sequence .zip (cloth_mesh None); textures: folder with diffuse_*.png or .jpg and outfits.png
    (optional: else the glTF's texture, one variation, default outfits); cycle: an existing cycle.json (skips the
    search); created: the manifest's RFC 3339 UTC time (see the module docstring when None); timeline: a clip
    timeline (crowdbake.ingest.timeline) when the cache plays several clips: a loop per clip and the
    transitions between them (crowdbake.stages.cycle_job), every one in the bundle (format v2) when there are several clips."""

    character: Path
    cloth: Path | None
    cloth_mesh: Path | None
    textures: Path | None
    cycle: Path | None
    name: str
    version: str
    params: BakeParams = BakeParams()
    created: str | None = None
    timeline: Path | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "character": str(self.character),
            "cloth": None if self.cloth is None else str(self.cloth),
            "cloth_mesh": None if self.cloth_mesh is None else str(self.cloth_mesh),
            "textures": None if self.textures is None else str(self.textures),
            "cycle": None if self.cycle is None else str(self.cycle),
            "name": self.name,
            "version": self.version,
            "params": self.params.to_dict(),
            "created": self.created,
            # Only when given: a bake without a timeline records (and keys) no timeline entry at all.
            **({"timeline": str(self.timeline)} if self.timeline is not None else {}),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "BakeInputs":
        def optional_path(key: str) -> Path | None:
            value = data.get(key)
            return None if value is None else Path(value)

        try:
            return cls(
                character=Path(data["character"]),
                cloth=optional_path("cloth"),
                cloth_mesh=optional_path("cloth_mesh"),
                textures=optional_path("textures"),
                cycle=optional_path("cycle"),
                name=data["name"],
                version=data["version"],
                params=BakeParams.from_dict(data.get("params", {})),
                created=data.get("created"),
                timeline=optional_path("timeline"),
            )
        except KeyError as missing:
            raise InputError(f"missing input {missing.args[0]!r}", str(missing.args[0])) from None


def rfc3339(seconds: float) -> str:
    moment = _dt.datetime.fromtimestamp(int(seconds), tz=_dt.timezone.utc)
    return moment.strftime("%Y-%m-%dT%H:%M:%SZ")


# Diffuse variations may be PNG or JPEG (crowdbake.formats.images.read_texture_variation); only a PNG
# carries the alpha channel whose values are colour-region codes.
DIFFUSE_SUFFIXES = (".png", ".jpg", ".jpeg")


def texture_files(folder: Path) -> tuple[list[Path], Path | None]:
    """(diffuse_*.png / .jpg / .jpeg sorted by name, outfits.png or None) of a textures folder."""
    diffuse = sorted((path for path in folder.glob("diffuse_*") if path.suffix.lower() in DIFFUSE_SUFFIXES), key=lambda path: path.name)
    outfits = folder / "outfits.png"
    return diffuse, outfits if outfits.is_file() else None


def without_region_codes(diffuse: list[Path]) -> list[str]:
    """Names of the JPEG variations: no alpha, so every texel is region 0 and no outfit colour applies."""
    return [path.name for path in diffuse if path.suffix.lower() in (".jpg", ".jpeg")]


def _check_textures(folder: Path) -> dict[str, Any]:
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder", "textures")
    diffuse, outfits = texture_files(folder)
    for other in ("outfits.jpg", "outfits.jpeg"):
        if (folder / other).is_file():
            raise InputError(f"{other}: the outfit map must be a PNG (16 exact colours a row; JPEG blurs them)", "textures")
    if not diffuse:
        raise InputError(f"{folder} holds no diffuse_*.png or diffuse_*.jpg", "textures")
    sizes = set()
    for path in diffuse:
        try:
            with Image.open(path) as image:
                sizes.add(image.size)
        except OSError as error:
            raise InputError(f"{path.name} is not a readable PNG or JPEG: {error}", "textures") from None
    if len(sizes) != 1:
        raise InputError(f"diffuse textures differ in size: {sorted(sizes)}", "textures")
    outfit_count = None
    if outfits is not None:
        try:
            with Image.open(outfits) as image:
                width, outfit_count = image.size
        except OSError as error:
            raise InputError(f"outfits.png is not a readable PNG: {error}", "textures") from None
        if width != 16:
            raise InputError(f"outfits.png must be 16 texels wide (one per region), got {width}", "textures")
    (width, height), = sizes
    info: dict[str, Any] = {"variations": len(diffuse), "size": [width, height], "outfits": outfit_count}
    jpegs = without_region_codes(diffuse)
    if jpegs:
        # Said once here, recorded with the job and shown by `crowdbake bake`.
        info["without_region_codes"] = jpegs
        info["note"] = (f"{', '.join(jpegs)}: a JPEG has no alpha, so no colour-region codes: every texel is region 0 and "
                        "keeps its own colour, no outfit colour applies (use PNG with region codes in alpha for outfits)")
        logger.warning("%s", info["note"])
    return info


def gltf_dependencies(path: Path) -> list[str]:
    """Relative paths of the files a .gltf refers to (buffers, images), checked to stay beside it."""
    try:
        document = read_json(path)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path.name} is not glTF JSON: {error}", "character") from None
    relatives = []
    for entry in list(document.get("buffers", [])) + list(document.get("images", [])):
        uri = entry.get("uri") if isinstance(entry, dict) else None
        if not isinstance(uri, str) or uri.startswith("data:"):
            continue
        relative = unquote(uri)
        resolved = (path.parent / relative).resolve()
        if path.parent.resolve() not in resolved.parents or not resolved.is_file():
            raise InputError(f"{path.name} refers to {uri!r}, which is not a file beside it", "character")
        relatives.append(Path(relative).as_posix())
    return sorted(set(relatives))


def _check_identity(inputs: BakeInputs) -> BakeParams:
    params = inputs.params
    if not isinstance(params, BakeParams):
        raise InputError("params must be BakeParams", "params")
    params.validate()
    if not isinstance(inputs.name, str) or not NAME_RULE.match(inputs.name):
        raise InputError(f"name {inputs.name!r} must match {NAME_RULE.pattern}", "name")
    if not isinstance(inputs.version, str) or not VERSION_RULE.match(inputs.version):
        raise InputError(f"version {inputs.version!r} must match {VERSION_RULE.pattern}", "version")
    if inputs.created is not None and not (isinstance(inputs.created, str) and CREATED_RULE.match(inputs.created)):
        raise InputError(f"created {inputs.created!r} must be RFC 3339 UTC like 2006-09-04T12:00:00Z", "created")
    return params


def _source_files(inputs: BakeInputs) -> dict[str, Path]:
    sources: dict[str, Path] = {}
    wanted = [("character", (".glb", ".gltf"))]
    if inputs.cloth is not None:
        wanted.append(("cloth", CACHE_SUFFIXES))
    elif inputs.cloth_mesh is not None:
        raise InputError("a cloth mesh was given without its cloth cache", "cloth")
    if inputs.cloth is not None and (inputs.cloth_mesh is not None or needs_mesh(inputs.cloth)):
        wanted.append(("cloth_mesh", (".obj",)))
    for field_name, suffixes in wanted:
        value = getattr(inputs, field_name)
        if value is None:
            raise InputError(f"{Path(inputs.cloth).name}: a {Path(inputs.cloth).suffix.lower()} cache needs its rest mesh (.obj)", field_name)
        path = Path(value)
        if not path.is_file():
            raise InputError(f"{path} does not exist or is not a file", field_name)
        if path.suffix.lower() not in suffixes:
            raise InputError(f"{path.name}: expected a {' or '.join(suffixes)} file", field_name)
        sources[field_name] = path
    if inputs.cycle is not None:
        if inputs.cloth is None:
            raise InputError("a cycle.json chooses a cycle of a cloth cache: give the cloth too", "cycle")
        if not Path(inputs.cycle).is_file():
            raise InputError(f"{inputs.cycle} does not exist or is not a file", "cycle")
        sources["cycle"] = Path(inputs.cycle)
    if inputs.timeline is not None:
        if inputs.cloth is None:
            raise InputError("a timeline says which clip plays at each frame of a cloth cache: give the cloth too", "timeline")
        if inputs.cycle is not None:
            raise InputError("a cycle.json chooses one cycle; a timeline asks for a loop per clip: give one of them", "timeline")
        if not Path(inputs.timeline).is_file():
            raise InputError(f"{inputs.timeline} does not exist or is not a file", "timeline")
        sources["timeline"] = Path(inputs.timeline)
    return sources


@dataclass(frozen=True)
class _Parsed:
    """What parsing the inputs gave: the counts the job records, the cloth in Y-up metres and its rate;
    converted: the cloth's frame was changed (up axis or units)."""

    counts: dict[str, int]
    cloth: ClothCache | None
    fps: float
    converted: bool
    animation: int | str = 0
    animation_choice: dict | None = None


def _parse_and_check(inputs: BakeInputs, sources: dict[str, Path], params: BakeParams) -> _Parsed:
    """Parse each input file once and cross-check them."""
    if "cloth" not in sources:
        return _parse_body_only(sources, params)
    cache = read_cloth(sources["cloth"], sources.get("cloth_mesh"))
    timeline = None
    if "timeline" in sources:  # several clips: the timeline names them and the bundle's (crowdbake.stages.cycle_job)
        timeline = _check_timeline(sources, cache, params)
        params = replace(params, animation=timeline[0], cycle_frames=timeline[1])
    # Not told which animation: the one the cloth repeats after (crowdbake.ingest.clip_choice).
    choice = None
    if params.animation is None and params.cycle_frames is None:
        choice = _choose_animation(sources["character"], cache, cache_fps(params.fps, cache.fps, cache.frame_step), params.up, params.units)
    animation = choice.index if choice is not None else (params.animation if params.animation is not None else 0)
    try:
        character = load_character(sources["character"], animation=animation)
    except (ValueError, FormatError, OSError, KeyError) as error:
        text = str(error).splitlines()[0] if str(error) else type(error).__name__
        field = "animation" if "animation" in text and params.animation not in (0, None) else "character"
        raise InputError(f"{sources['character'].name}: {text}", field) from None
    if len(character.faces) == 0:
        raise InputError(f"{sources['character'].name} has no triangles", "character")
    # The garment must sit on the character: a Z-up or centimetre cache is refused (naming up / units) or
    # converted as declared, before any stage spends minutes on it.
    placed = place_cloth(cache, body_at_rest(character), params.up, params.units)
    fps = cache_fps(params.fps, cache.fps, cache.frame_step)
    # ...and follow this body over the whole cache (not a garment made for another). The check poses one
    # clip over every frame: a cache of several clips is checked by the timeline's clips instead.
    if params.fit and timeline is None:
        check_garment_fit(character, placed, fps)
    if params.cycle_frames is not None:
        cycle_frames = params.cycle_frames
    elif character.animation_duration > 0:
        cycle_frames = int(round(character.animation_duration * fps))
    else:
        raise InputError("the character has no animation: give cycle_frames", "cycle_frames")
    if inputs.cycle is not None:
        cycle_frames = check_cycle_document(sources["cycle"], cache.frame_count)["cycle_frames"]
    elif cache.frame_count < min_cloth_frames(cycle_frames):
        raise InputError(
            f"{sources['cloth'].name} has {cache.frame_count} frames; the cycle search needs two cycles of "
            f"{cycle_frames}",
            "cloth",
        )
    lod_parts = len(character.faces) + len(cache.faces)
    if params.lod_triangles is not None and params.lod_triangles >= lod_parts:
        raise InputError(f"lod_triangles {params.lod_triangles} is not below the {lod_parts} triangles of the character", "lod_triangles")
    counts = {
        "body_vertices": int(len(character.positions)),
        "body_triangles": int(len(character.faces)),
        "garment_vertices": int(cache.mesh.vertex_count),
        "garment_triangles": int(len(cache.faces)),
        "cache_frames": int(cache.frame_count),
        "cycle_frames": int(cycle_frames),
    }
    return _Parsed(counts, placed, fps, placed is not cache, animation, choice.to_json() if choice is not None else None)


def _check_timeline(sources: dict[str, Path], cache: ClothCache, params: BakeParams) -> tuple[str, int]:
    """The timeline against the cache and the character's clips: (the clip the bundle carries, its period).
    InputError("timeline") naming the field by its JSON pointer, or ("animation") for a clip it does not play."""
    from crowdbake.ingest.clip_choice import character_clips
    from crowdbake.ingest.timeline import check_timeline_fits, read_timeline
    from crowdbake.bake.timeline import primary_clip

    if params.cycle_frames is not None:
        raise InputError("the timeline gives each clip's period: drop cycle_frames", "cycle_frames")
    timeline = read_timeline(sources["timeline"])
    try:
        known = {clip.name: clip.seconds for clip in character_clips(sources["character"])}
    except (ValueError, FormatError, OSError, KeyError, TypeError, AttributeError) as error:
        raise InputError(f"{sources['character'].name}: {str(error).splitlines()[0] if str(error) else type(error).__name__}", "character") from None
    check_timeline_fits(timeline, cache.frame_count, cache_fps(params.fps, cache.fps, cache.frame_step), known, sources["timeline"].name)
    try:
        clip = primary_clip(timeline, params.animation)
    except ValueError as error:
        raise InputError(str(error), "animation") from None
    return clip, timeline.period(clip)


def _parse_body_only(sources: dict[str, Path], params: BakeParams) -> _Parsed:
    from crowdbake.stages.body_only import body_only_counts

    try:
        character = load_character(sources["character"], animation=params.animation if params.animation is not None else 0)
    except (ValueError, FormatError, OSError, KeyError) as error:
        text = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise InputError(f"{sources['character'].name}: {text}", "animation" if "animation" in text else "character") from None
    if len(character.faces) == 0:
        raise InputError(f"{sources['character'].name} has no triangles", "character")
    counts, fps, choice = body_only_counts(character, params, sources["character"].name)
    if choice is not None:
        logger.info("animation %r picked: %s", choice["name"], choice["reason"])
    return _Parsed(counts, None, fps, False, params.animation if params.animation is not None else 0, choice)


def _choose_animation(path: Path, cache: ClothCache, fps: float, up: str | None, units: str | None):
    """choose_clip on the character's clips, with the cloth's physical evidence; a broken file is left to
    load_character to name."""
    from crowdbake.ingest.clip_choice import character_clip_evidence, character_clips, choose_clip

    try:
        clips = character_clips(path)
    except (ValueError, FormatError, OSError, KeyError, TypeError, AttributeError):
        return None
    if len(clips) < 2:
        return None
    return choose_clip(clips, cache.frames, fps, lambda indices: character_clip_evidence(path, indices, cache.frames, fps, up, units))


def _copy_inputs(work: WorkDir, inputs: BakeInputs, sources: dict[str, Path], gltf_files: list[str],
                 looped_beside_cycle: Path | None, textures: list[Path], parsed: _Parsed) -> dict[str, str]:
    """Copy the inputs into work/inputs (copy2 keeps modification times, which `created` may come from).
    A PC2 + OBJ in Y-up metres is copied as it is; any other cache, or a converted one, is written as the
    PC2 + OBJ pair the stages read."""
    inputs_dir = work.inputs
    if inputs_dir.exists():
        shutil.rmtree(inputs_dir)
    inputs_dir.mkdir(parents=True)
    character = sources["character"]
    names = {"character": "character" + character.suffix.lower(), "cloth": "cloth.pc2", "cloth_mesh": "cloth.obj"}
    if character.suffix.lower() == ".gltf":
        # A .gltf refers to its buffers and images by relative path: bring them along, keeping the paths.
        (inputs_dir / "gltf").mkdir()
        shutil.copy2(character, inputs_dir / "gltf" / character.name)
        for relative in gltf_files:
            target = inputs_dir / "gltf" / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(character.parent / relative, target)
        names["character"] = f"gltf/{character.name}"
    else:
        shutil.copy2(character, inputs_dir / names["character"])
    if parsed.cloth is None:
        del names["cloth"], names["cloth_mesh"]
    elif sources["cloth"].suffix.lower() == ".pc2" and not parsed.converted:
        shutil.copy2(sources["cloth"], inputs_dir / names["cloth"])
        shutil.copy2(sources["cloth_mesh"], inputs_dir / names["cloth_mesh"])
    else:
        write_pc2_obj(parsed.cloth, inputs_dir / names["cloth"], inputs_dir / names["cloth_mesh"])
    if inputs.timeline is not None:
        names["timeline"] = "timeline.json"
        shutil.copy2(sources["timeline"], inputs_dir / "timeline.json")
    if inputs.cycle is not None:
        names["cycle"] = "cycle.json"
        shutil.copy2(sources["cycle"], inputs_dir / "cycle.json")
        if looped_beside_cycle is not None:
            names["cycle_looped"] = "looped.pc2"
            shutil.copy2(looped_beside_cycle, inputs_dir / "looped.pc2")
    if textures:
        (inputs_dir / "textures").mkdir()
        for path in textures:
            shutil.copy2(path, inputs_dir / "textures" / path.name)
        names["textures"] = "textures"
    return names


def _created(given: str | None, files: list[Path]) -> tuple[str, str]:
    """The manifest's time and where it came from (see the module docstring)."""
    if given is not None:
        return given, "given"
    if os.environ.get("SOURCE_DATE_EPOCH", "").strip():
        try:
            return rfc3339(float(os.environ["SOURCE_DATE_EPOCH"])), "SOURCE_DATE_EPOCH"
        except ValueError:
            raise InputError("SOURCE_DATE_EPOCH must be a number of seconds", "created") from None
    return rfc3339(max(path.stat().st_mtime for path in files)), "input modification time"


def garment_part_name(cloth_mesh: Path) -> str:
    """The garment's part name in the bundle: the OBJ's (or the self-contained cache's) stem when it is a
    plain name, else "garment"."""
    stem = re.sub(r"[^a-z0-9_-]", "", Path(cloth_mesh).stem.lower())[:32]
    return stem if PART_RULE.match(stem or "-") and stem != "body" else "garment"


def stage_validate(inputs: BakeInputs, work: Path) -> StageOutcome[JobRecord]:
    """Check every input and parameter, copy the inputs into work/inputs, write the JobRecord.

    Raises InputError(message, field) on bad input.
    """
    started = time.perf_counter()
    folder = WorkDir(work)
    params = _check_identity(inputs)
    sources = _source_files(inputs)
    texture_list: list[Path] = []
    texture_info = None
    if inputs.textures is not None:
        texture_info = _check_textures(Path(inputs.textures))
        diffuse, outfits = texture_files(Path(inputs.textures))
        texture_list = diffuse + ([outfits] if outfits is not None else [])
    gltf_files = gltf_dependencies(sources["character"]) if sources["character"].suffix.lower() == ".gltf" else []

    # Hash everything first: the key decides whether this work folder already holds this job.
    hashes = {name: sha256_file(path) for name, path in sources.items()}
    hashes.update({f"gltf/{relative}": sha256_file(sources["character"].parent / relative) for relative in gltf_files})
    hashes.update({f"textures/{path.name}": sha256_file(path) for path in texture_list})
    looped_beside_cycle = None
    if inputs.cycle is not None:
        candidate = Path(inputs.cycle).with_name("looped.pc2")
        if candidate.is_file():
            looped_beside_cycle = candidate
            hashes["cycle_looped"] = sha256_file(candidate)
    key = stage_key("validate", hashes, params.to_dict(), inputs.name, inputs.version, inputs.created, __version__)
    cached = folder.cached("validate", key, JobRecord, [folder.inputs])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)

    parsed = _parse_and_check(inputs, sources, params)
    names = _copy_inputs(folder, inputs, sources, gltf_files, looped_beside_cycle, texture_list, parsed)
    created, created_from = _created(inputs.created, [*sources.values(), *texture_list])
    record = JobRecord(
        key=key, name=inputs.name, version=inputs.version, created=created, created_from=created_from,
        params={**params.to_dict(), "animation": parsed.animation}, animation_choice=parsed.animation_choice, inputs=names, hashes=hashes, garment_part=garment_part_name(sources.get("cloth_mesh", sources.get("cloth", Path("garment")))),
        textures=texture_info, producer=f"crowdbake {__version__}", **parsed.counts,
        fps=parsed.fps, cloth_format=parsed.cloth.source if parsed.cloth is not None else "none",
    )
    seconds = time.perf_counter() - started
    folder.save("validate", key, record, seconds)
    return StageOutcome(record, False, seconds)


def load_job(work: Path) -> JobRecord:
    """The job the validate stage wrote; StageOrderError when it has not run in this folder."""
    return WorkDir(work).load("validate", JobRecord)
