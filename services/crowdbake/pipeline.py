"""The bake pipeline: validate → cycle → poses → impostors (fan-out) → pack → publish.

Every stage is a plain function over a per-job work directory. Stages take paths and small parameters
(never big arrays), read their inputs from files written by earlier stages, and write their outputs there
too, so a Celery task can wrap each one thinly and a worker on another machine can run any of them given
the folder. Each stage is

- idempotent: it records a key (a hash of its inputs) with its result; rerunning it when its outputs
  exist under the same key returns the recorded result at once;
- deterministic: the same inputs give the same bytes (no clocks, no random seeds, no dict-order effects),
  so baking twice gives byte-identical bundles (manifest included, see `created` below).

Work directory layout:

    job.json                 inputs (copied into inputs/), their sha256, the parameters, created
    inputs/                  character.glb|gltf, cloth.pc2, cloth.obj, textures/, cycle.json (+ looped.pc2)
    cycle/                   cycle.json, looped.pc2, report.html (crowdbake.cycle_report) + stage.json
    poses/                   <part>_lod<k>.cbpc, textures.npz, poses.json (+ stage.json)
    impostor/parts/<id>.npz  one impostor task's views (normal, UV, detail maps; fidelity references)
    bundle/                  the packed bundle (manifest.json + files), not yet published

`created` in the manifest is the only clock-like value. It is BakeInputs.created when given, else the
SOURCE_DATE_EPOCH environment variable (the reproducible-builds convention), else the newest modification
time of the input files: a property of the inputs, so a rebake of unchanged files gives the same bytes.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import re
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable

import numpy as np

from crowdbake import __version__

logger = logging.getLogger(__name__)

STAGES = ("validate", "cycle", "poses", "impostors", "pack", "publish")
Progress = Callable[[str, int, int], None]

CLOSE_METHODS = ("none", "linear", "hermite")
UV_FORMATS = ("uv32", "rgba16")  # impostor UV map pixel formats a bake can write (SPEC.md); the first is the default
NAME_RULE = re.compile(r"^[a-z0-9][a-z0-9._-]{0,63}$")
VERSION_RULE = re.compile(r"^[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}$")
CREATED_RULE = re.compile(r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}Z$")
PART_RULE = re.compile(r"^[a-z0-9_-]{1,32}$")
# PC2 stores the interval between samples in frames, not a rate: the cache's rate is this over
# sample_rate unless the cycle search recorded one (crowdbake.cycle_report.BASE_FPS, the film rate).
BASE_FPS = 24.0
# Upper limits that keep one bake within a worker's memory: 64 azimuths x 9 elevations x 1024² tiles is
# already a 64k-wide atlas; the runtime's texture limits are lower still.
MAX_TILE_SIZE = 1024
MAX_AZIMUTHS = 64
MAX_ELEVATIONS = 9
MAX_IMPOSTOR_FRAMES = 256
# Samples per texel side of the fidelity stage's mesh reference (crowdbake.bake.fidelity).
FIDELITY_SUPERSAMPLE = 4
# Default outfits when the inputs bring no outfits.png: a fixed seed keeps the bake deterministic.
DEFAULT_OUTFIT_COUNT = 8
_DEFAULT_OUTFIT_SEED = 2006
# Variations drawn in the figure-4 series at least: twice the paper's 8 diffuse textures (figure 2b), so the
# crossover of a bundle with 16-bit UV maps (about 8) shows.
FIGURE4_MIN_VARIATIONS = 16


class InputError(ValueError):
    """Bad input, reported to the user: `field` names the input or parameter at fault (None: general)."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.message = message
        self.field = field


class VersionConflict(Exception):
    """The bundle <name>/<version> is already published with other bytes; published bundles never change."""


class StageOrderError(RuntimeError):
    """A stage ran before the stage it depends on produced its outputs in this work directory."""


# --------------------------------------------------------------------------------------------------
# Parameters and inputs


@dataclass(frozen=True)
class BakeParams:
    """Everything that shapes a bake besides the input files (JSON-serialisable: to_dict/from_dict).

    cycle_frames: the walk cycle's length in frames; None = the character's animation length.
    close, candidates, cycle_views: the cycle search's closing, candidates kept by pass 1, pass-2 views.
    impostor_frames: cycle frames baked into impostors (the paper: 10); azimuths: views per ring;
    elevations_deg: one ring per elevation; tile_size: texels per view side.
    lod_ratio / lod_triangles: the low LOD as a fraction of the high one, or a triangle count for the
    whole character (at most one; neither = the paper's 1,899 / 13,056).
    compress: BC1 normal maps, BC2 detail maps and diffuse textures (else rgba8).
    uv_format: the impostor UV map's pixel format: "uv32" (4 bytes a texel, 14-bit coordinates) or
    "rgba16" (8 bytes a texel, 16-bit coordinates); SPEC.md.
    """

    cycle_frames: int | None = None
    close: str = "hermite"
    candidates: int = 5
    cycle_views: int = 5
    impostor_frames: int = 10
    azimuths: int = 16
    elevations_deg: tuple[float, ...] = (0.0, 20.0, 40.0)
    tile_size: int = 128
    lod_ratio: float | None = None
    lod_triangles: int | None = None
    compress: bool = True
    uv_format: str = "uv32"

    def validate(self) -> None:
        """Raise InputError(message, field) for the first parameter out of range."""

        def need(condition: bool, name: str, message: str) -> None:
            if not condition:
                raise InputError(f"{name}: {message}", name)

        def integer(value: Any) -> bool:
            return isinstance(value, (int, np.integer)) and not isinstance(value, bool)

        need(self.cycle_frames is None or (integer(self.cycle_frames) and self.cycle_frames >= 2), "cycle_frames", "must be an integer of at least 2 frames")
        need(self.close in CLOSE_METHODS, "close", f"must be one of {', '.join(CLOSE_METHODS)}")
        need(integer(self.candidates) and self.candidates >= 1, "candidates", "must be at least 1")
        need(integer(self.cycle_views) and self.cycle_views >= 1, "cycle_views", "must be at least 1")
        need(integer(self.impostor_frames) and 1 <= self.impostor_frames <= MAX_IMPOSTOR_FRAMES, "impostor_frames", f"must lie in 1..{MAX_IMPOSTOR_FRAMES}")
        need(integer(self.azimuths) and 1 <= self.azimuths <= MAX_AZIMUTHS, "azimuths", f"must lie in 1..{MAX_AZIMUTHS}")
        elevations = self.elevations_deg
        need(isinstance(elevations, (tuple, list)) and 1 <= len(elevations) <= MAX_ELEVATIONS, "elevations_deg", f"needs 1..{MAX_ELEVATIONS} values")
        need(all(isinstance(e, (int, float)) and not isinstance(e, bool) and -90.0 <= e <= 90.0 for e in elevations), "elevations_deg", "values must lie in -90..90 degrees")
        need(len(set(elevations)) == len(elevations), "elevations_deg", "values must be distinct")
        need(integer(self.tile_size) and 4 <= self.tile_size <= MAX_TILE_SIZE and self.tile_size % 4 == 0, "tile_size", f"must be a multiple of 4 in 4..{MAX_TILE_SIZE}")
        need(self.lod_ratio is None or self.lod_triangles is None, "lod_ratio", "give lod_ratio or lod_triangles, not both")
        need(self.lod_ratio is None or (isinstance(self.lod_ratio, (int, float)) and 0.0 < self.lod_ratio <= 1.0), "lod_ratio", "must lie in (0, 1]")
        need(self.lod_triangles is None or (integer(self.lod_triangles) and self.lod_triangles >= 2), "lod_triangles", "must be at least 2")
        need(isinstance(self.compress, bool), "compress", "must be true or false")
        need(self.uv_format in UV_FORMATS, "uv_format", f"must be one of {', '.join(UV_FORMATS)}")

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["elevations_deg"] = [float(e) for e in self.elevations_deg]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "BakeParams":
        """Parameters from JSON; unknown keys and bad values raise InputError."""
        if not isinstance(data, dict):
            raise InputError("parameters must be a JSON object", None)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InputError(f"unknown parameter {unknown[0]!r}", unknown[0])
        values = dict(data)
        if "elevations_deg" in values and isinstance(values["elevations_deg"], list):
            values["elevations_deg"] = tuple(values["elevations_deg"])
        params = cls(**values)
        params.validate()
        return params


@dataclass(frozen=True)
class BakeInputs:
    """The files and identity of one bake. textures: folder with diffuse_*.png and outfits.png (optional:
    else the glTF's texture, one variation, default outfits); cycle: an existing cycle.json (skips the
    search); created: the manifest's RFC 3339 UTC time (see the module docstring when None)."""

    character: Path
    cloth: Path
    cloth_mesh: Path
    textures: Path | None
    cycle: Path | None
    name: str
    version: str
    params: BakeParams = BakeParams()
    created: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "character": str(self.character),
            "cloth": str(self.cloth),
            "cloth_mesh": str(self.cloth_mesh),
            "textures": None if self.textures is None else str(self.textures),
            "cycle": None if self.cycle is None else str(self.cycle),
            "name": self.name,
            "version": self.version,
            "params": self.params.to_dict(),
            "created": self.created,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "BakeInputs":
        def optional_path(key: str) -> Path | None:
            value = data.get(key)
            return None if value is None else Path(value)

        try:
            return cls(
                character=Path(data["character"]),
                cloth=Path(data["cloth"]),
                cloth_mesh=Path(data["cloth_mesh"]),
                textures=optional_path("textures"),
                cycle=optional_path("cycle"),
                name=data["name"],
                version=data["version"],
                params=BakeParams.from_dict(data.get("params", {})),
                created=data.get("created"),
            )
        except KeyError as missing:
            raise InputError(f"missing input {missing.args[0]!r}", str(missing.args[0])) from None


@dataclass
class BakeSummary:
    """What run_bake did: where the bundle is, how big, how long each stage took, how faithful."""

    bundle: Path
    name: str
    version: str
    timings_s: dict[str, float]
    files: dict[str, int]
    meshes: list[dict[str, Any]]
    cycle: dict[str, Any]
    impostor: dict[str, Any]
    fidelity: dict[str, Any]
    compression: dict[str, Any]
    texture_memory: dict[str, Any]

    @property
    def total_bytes(self) -> int:
        return int(sum(self.files.values()))

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["bundle"] = str(self.bundle)
        data["total_bytes"] = self.total_bytes
        return data


# --------------------------------------------------------------------------------------------------
# Small file helpers


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _key(*parts: Any) -> str:
    """A stable hash of JSON-able parts: the identity of a stage's inputs."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def _write_bytes_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(data)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _write_json_atomic(path: Path, document: Any) -> None:
    _write_bytes_atomic(path, (json.dumps(document, indent=2, sort_keys=True) + "\n").encode())


def _read_json(path: Path) -> Any:
    return json.loads(Path(path).read_text(encoding="utf-8"))


def _stamp_path(work: Path, stage: str) -> Path:
    return Path(work) / stage / "stage.json"


def _cached(work: Path, stage: str, key: str, outputs: list[Path]) -> dict | None:
    """The recorded result of `stage` if it ran with `key` and its outputs are all there."""
    stamp = _stamp_path(work, stage)
    if not stamp.is_file():
        return None
    try:
        recorded = _read_json(stamp)
    except (OSError, json.JSONDecodeError):
        return None
    if recorded.get("key") != key or not all(Path(p).exists() for p in outputs):
        return None
    result = dict(recorded["result"])
    result["cached"] = True
    return result


def _record(work: Path, stage: str, key: str, result: dict) -> dict:
    _write_json_atomic(_stamp_path(work, stage), {"key": key, "result": result})
    return dict(result, cached=False)


def _job(work: Path) -> dict:
    path = Path(work) / "job.json"
    if not path.is_file():
        raise StageOrderError(f"{work}: no job.json; run stage_validate first")
    return _read_json(path)


def _stage_key(work: Path, stage: str) -> str:
    stamp = _stamp_path(work, stage)
    if not stamp.is_file():
        raise StageOrderError(f"{work}: stage {stage!r} has not run yet")
    return _read_json(stamp)["key"]


def _report(progress: Progress | None, stage: str, done: int, total: int) -> None:
    if progress is not None:
        progress(stage, done, total)


def _rfc3339(seconds: float) -> str:
    moment = _dt.datetime.fromtimestamp(int(seconds), tz=_dt.timezone.utc)
    return moment.strftime("%Y-%m-%dT%H:%M:%SZ")


# --------------------------------------------------------------------------------------------------
# Stage: validate


def _load_rgba_png(path: Path) -> np.ndarray:
    """(H, W, 4) uint8 from a PNG; an image without alpha gets alpha 0 (region 0: keep its colours)."""
    from PIL import Image

    with Image.open(path) as image:
        has_alpha = "A" in image.getbands() or image.mode == "P" and "transparency" in image.info
        rgba = np.array(image.convert("RGBA"))
    if not has_alpha:
        rgba[..., 3] = 0
    return rgba


def _texture_files(folder: Path) -> tuple[list[Path], Path | None]:
    diffuse = sorted(folder.glob("diffuse_*.png"))
    outfits = folder / "outfits.png"
    return diffuse, outfits if outfits.is_file() else None


def _check_textures(folder: Path) -> dict[str, Any]:
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder", "textures")
    diffuse, outfits = _texture_files(folder)
    if not diffuse:
        raise InputError(f"{folder} holds no diffuse_*.png", "textures")
    sizes = set()
    for path in diffuse:
        try:
            from PIL import Image

            with Image.open(path) as image:
                sizes.add(image.size)
        except OSError as error:
            raise InputError(f"{path.name} is not a readable PNG: {error}", "textures") from None
    if len(sizes) != 1:
        raise InputError(f"diffuse textures differ in size: {sorted(sizes)}", "textures")
    outfit_count = None
    if outfits is not None:
        try:
            from PIL import Image

            with Image.open(outfits) as image:
                width, outfit_count = image.size
        except OSError as error:
            raise InputError(f"outfits.png is not a readable PNG: {error}", "textures") from None
        if width != 16:
            raise InputError(f"outfits.png must be 16 texels wide (one per region), got {width}", "textures")
    (width, height), = sizes
    return {"variations": len(diffuse), "size": [width, height], "outfits": outfit_count}


def _check_cycle_document(path: Path, frame_count: int) -> dict[str, Any]:
    try:
        document = _read_json(path)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path.name} is not JSON: {error}", "cycle") from None
    if not isinstance(document, dict):
        raise InputError(f"{path.name} must hold a JSON object", "cycle")
    for key in ("start_frame", "cycle_frames"):
        value = document.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise InputError(f"{path.name}: {key} must be a non-negative integer", "cycle")
    if document["cycle_frames"] < 2:
        raise InputError(f"{path.name}: cycle_frames must be at least 2", "cycle")
    if document["start_frame"] + document["cycle_frames"] > frame_count:
        raise InputError(
            f"{path.name}: the cycle [{document['start_frame']}, {document['start_frame'] + document['cycle_frames']}) "
            f"runs past the cache's {frame_count} frames",
            "cycle",
        )
    method = (document.get("closing") or {}).get("method", "none")
    if method not in CLOSE_METHODS:
        raise InputError(f"{path.name}: closing.method must be one of {CLOSE_METHODS}", "cycle")
    return document


def _gltf_dependencies(path: Path) -> list[str]:
    """Relative paths of the files a .gltf refers to (buffers, images), checked to stay beside it."""
    from urllib.parse import unquote

    try:
        document = _read_json(path)
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


def stage_validate(inputs: BakeInputs, work: Path) -> dict:
    """Check every input and parameter, copy the inputs into work/inputs, write work/job.json.

    Raises InputError(message, field) on bad input. Returns {"key", counts of what was found, "seconds"}.
    """
    started = time.perf_counter()
    work = Path(work)
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

    sources: dict[str, Path] = {}
    for field_name, suffixes in (("character", (".glb", ".gltf")), ("cloth", (".pc2",)), ("cloth_mesh", (".obj",))):
        path = Path(getattr(inputs, field_name))
        if not path.is_file():
            raise InputError(f"{path} does not exist or is not a file", field_name)
        if path.suffix.lower() not in suffixes:
            raise InputError(f"{path.name}: expected a {' or '.join(suffixes)} file", field_name)
        sources[field_name] = path
    if inputs.cycle is not None:
        if not Path(inputs.cycle).is_file():
            raise InputError(f"{inputs.cycle} does not exist or is not a file", "cycle")
        sources["cycle"] = Path(inputs.cycle)

    texture_files: list[Path] = []
    if inputs.textures is not None:
        texture_info = _check_textures(Path(inputs.textures))
        diffuse, outfits = _texture_files(Path(inputs.textures))
        texture_files = diffuse + ([outfits] if outfits is not None else [])
    else:
        texture_info = None

    gltf_files = _gltf_dependencies(sources["character"]) if sources["character"].suffix.lower() == ".gltf" else []

    # Hash everything first: the key decides whether this work folder already holds this job.
    hashes = {name: _sha256_file(path) for name, path in sources.items()}
    hashes.update({f"gltf/{relative}": _sha256_file(sources["character"].parent / relative) for relative in gltf_files})
    hashes.update({f"textures/{path.name}": _sha256_file(path) for path in texture_files})
    looped_beside_cycle = None
    if inputs.cycle is not None:
        candidate = Path(inputs.cycle).with_name("looped.pc2")
        if candidate.is_file():
            looped_beside_cycle = candidate
            hashes["cycle_looped"] = _sha256_file(candidate)
    key = _key("validate", hashes, params.to_dict(), inputs.name, inputs.version, inputs.created, __version__)
    existing = work / "job.json"
    if existing.is_file():
        try:
            if _read_json(existing).get("key") == key:
                cached = _cached(work, "validate", key, [existing, work / "inputs"])
                if cached is not None:
                    return cached
        except (OSError, json.JSONDecodeError):
            pass

    from crowdbake.formats.errors import FormatError
    from crowdbake.formats.gltf import load_character
    from crowdbake.formats.obj import read_obj
    from crowdbake.formats.pc2 import read_pc2

    try:
        character = load_character(sources["character"])
    except (ValueError, FormatError, OSError, KeyError) as error:
        raise InputError(f"{sources['character'].name}: {error}", "character") from None
    try:
        cache = read_pc2(sources["cloth"])
    except (ValueError, OSError) as error:
        raise InputError(str(error), "cloth") from None
    try:
        mesh = read_obj(sources["cloth_mesh"])
    except (ValueError, OSError) as error:
        raise InputError(str(error), "cloth_mesh") from None
    if mesh.position_count != cache.point_count:
        raise InputError(
            f"{sources['cloth_mesh'].name} has {mesh.position_count} positions but {sources['cloth'].name} has "
            f"{cache.point_count} points",
            "cloth_mesh",
        )
    if len(mesh.faces) == 0:
        raise InputError(f"{sources['cloth_mesh'].name} has no faces", "cloth_mesh")
    if len(character.faces) == 0:
        raise InputError(f"{sources['character'].name} has no triangles", "character")
    fps = BASE_FPS / cache.sample_rate
    if params.cycle_frames is not None:
        cycle_frames = params.cycle_frames
    elif character.animation_duration > 0:
        cycle_frames = int(round(character.animation_duration * fps))
    else:
        raise InputError("the character has no animation: give cycle_frames", "cycle_frames")
    if inputs.cycle is not None:
        cycle_document = _check_cycle_document(sources["cycle"], cache.sample_count)
        cycle_frames = cycle_document["cycle_frames"]
    elif cache.sample_count < 2 * cycle_frames:
        raise InputError(
            f"{sources['cloth'].name} has {cache.sample_count} frames; the cycle search needs two cycles of "
            f"{cycle_frames}",
            "cloth",
        )
    lod_parts = len(character.faces) + len(mesh.faces)
    if params.lod_triangles is not None and params.lod_triangles >= lod_parts:
        raise InputError(f"lod_triangles {params.lod_triangles} is not below the {lod_parts} triangles of the character", "lod_triangles")

    # Copy the inputs in (copy2 keeps modification times, which `created` may come from).
    inputs_dir = work / "inputs"
    if inputs_dir.exists():
        shutil.rmtree(inputs_dir)
    inputs_dir.mkdir(parents=True)
    names = {
        "character": "character" + sources["character"].suffix.lower(),
        "cloth": "cloth.pc2",
        "cloth_mesh": "cloth.obj",
    }
    if sources["character"].suffix.lower() == ".gltf":
        # A .gltf refers to its buffers and images by relative path: bring them along, keeping the paths.
        (inputs_dir / "gltf").mkdir()
        shutil.copy2(sources["character"], inputs_dir / "gltf" / sources["character"].name)
        for relative in gltf_files:
            target = inputs_dir / "gltf" / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(sources["character"].parent / relative, target)
        names["character"] = f"gltf/{sources['character'].name}"
    else:
        shutil.copy2(sources["character"], inputs_dir / names["character"])
    shutil.copy2(sources["cloth"], inputs_dir / names["cloth"])
    shutil.copy2(sources["cloth_mesh"], inputs_dir / names["cloth_mesh"])
    if inputs.cycle is not None:
        names["cycle"] = "cycle.json"
        shutil.copy2(sources["cycle"], inputs_dir / "cycle.json")
        if looped_beside_cycle is not None:
            names["cycle_looped"] = "looped.pc2"
            shutil.copy2(looped_beside_cycle, inputs_dir / "looped.pc2")
    if texture_files:
        (inputs_dir / "textures").mkdir()
        for path in texture_files:
            shutil.copy2(path, inputs_dir / "textures" / path.name)
        names["textures"] = "textures"

    created = inputs.created
    created_from = "given"
    if created is None and os.environ.get("SOURCE_DATE_EPOCH", "").strip():
        try:
            created = _rfc3339(float(os.environ["SOURCE_DATE_EPOCH"]))
            created_from = "SOURCE_DATE_EPOCH"
        except ValueError:
            raise InputError("SOURCE_DATE_EPOCH must be a number of seconds", "created") from None
    if created is None:
        newest = max(path.stat().st_mtime for path in [*sources.values(), *texture_files])
        created = _rfc3339(newest)
        created_from = "input modification time"

    cloth_stem = re.sub(r"[^a-z0-9_-]", "", sources["cloth_mesh"].stem.lower())[:32]
    garment_part = cloth_stem if PART_RULE.match(cloth_stem or "-") and cloth_stem != "body" else "garment"
    job = {
        "key": key,
        "name": inputs.name,
        "version": inputs.version,
        "created": created,
        "created_from": created_from,
        "params": params.to_dict(),
        "inputs": names,
        "hashes": hashes,
        "garment_part": garment_part,
        "textures": texture_info,
        "producer": f"crowdbake {__version__}",
    }
    _write_json_atomic(work / "job.json", job)
    result = {
        "key": key,
        "body_vertices": int(len(character.positions)),
        "body_triangles": int(len(character.faces)),
        "garment_vertices": int(mesh.vertex_count),
        "garment_triangles": int(len(mesh.faces)),
        "cache_frames": int(cache.sample_count),
        "cycle_frames": int(cycle_frames),
        "created": created,
        "created_from": created_from,
        "seconds": time.perf_counter() - started,
    }
    return _record(work, "validate", key, result)


# --------------------------------------------------------------------------------------------------
# Stage: cycle


def _bundle_cycle_document(document: dict) -> dict:
    """cycle.json as published: without timings and local paths, which differ between runs."""
    cleaned = json.loads(json.dumps(document))
    cleaned.pop("timings_s", None)
    cleaned.pop("files", None)
    if isinstance(cleaned.get("input"), dict):
        cleaned["input"].pop("sources", None)
    return cleaned


def stage_cycle(work: Path, progress: Progress | None = None) -> dict:
    """Find and close the cloth cycle (crowdbake.cycle_report), or take the given cycle.json.

    Writes work/cycle/cycle.json and work/cycle/looped.pc2 (exactly cycle_frames frames, frame 0 = Fs).
    """
    started = time.perf_counter()
    work = Path(work)
    job = _job(work)
    key = _key("cycle", _stage_key(work, "validate"))
    out = work / "cycle"
    cycle_json, looped = out / "cycle.json", out / "looped.pc2"
    cached = _cached(work, "cycle", key, [cycle_json, looped])
    if cached is not None:
        return cached
    params = BakeParams.from_dict(job["params"])
    inputs = work / "inputs"
    names = job["inputs"]
    out.mkdir(parents=True, exist_ok=True)

    from crowdbake.formats.pc2 import read_pc2, write_pc2

    if "cycle" in names:
        # A cycle chosen earlier: reuse its looped cache when it came along, else close it again.
        document = _read_json(inputs / names["cycle"])
        start, frames = int(document["start_frame"]), int(document["cycle_frames"])
        method = (document.get("closing") or {}).get("method", "none")
        cache = read_pc2(inputs / names["cloth"])
        looped_points = None
        if "cycle_looped" in names:
            given = read_pc2(inputs / names["cycle_looped"])
            if given.points.shape == (frames, cache.point_count, 3):
                looped_points = given.points
            else:
                logger.warning("looped.pc2 beside cycle.json has shape %s, not (%d, %d, 3); closing again", given.points.shape, frames, cache.point_count)
        if looped_points is None:
            from crowdbake.bake.loop_closing import close_cycle

            if start + frames + 1 > cache.sample_count and method != "none":
                raise InputError(f"closing the cycle needs frame {start + frames}, the cache ends at {cache.sample_count - 1}", "cycle")
            if method == "none":
                looped_points = cache.points[start : start + frames]
            else:
                looped_points = close_cycle(cache.points, start, frames, method).looped
        document.setdefault("end_frame", start + frames)
        document.setdefault("input", {})
        if "fps" not in document["input"]:
            document["input"]["fps"] = BASE_FPS / cache.sample_rate
        _write_json_atomic(cycle_json, document)
        write_pc2(looped, looped_points, start_frame=0.0, sample_rate=cache.sample_rate)
        _report(progress, "cycle", 1, 1)
    else:
        from crowdbake.bake.cycle import CycleParams
        from crowdbake.cycle_report import run_cycle_job

        cycle_params = CycleParams(max_candidates=params.candidates, views=params.cycle_views, close=params.close)

        def forward(stage: str, done: int, total: int) -> None:
            _report(progress, f"cycle:{stage}", done, total)

        try:
            run_cycle_job(
                inputs / names["cloth"],
                inputs / names["cloth_mesh"],
                out,
                character=inputs / names["character"],
                cycle_frames=params.cycle_frames,
                params=cycle_params,
                progress=forward,
            )
        except ValueError as error:
            raise InputError(f"cycle search: {error}", "cloth") from None
        document = _read_json(cycle_json)

    seam = document.get("seam") or {}
    result = {
        "start_frame": int(document["start_frame"]),
        "end_frame": int(document.get("end_frame", document["start_frame"] + document["cycle_frames"])),
        "cycle_frames": int(document["cycle_frames"]),
        "closing": (document.get("closing") or {}).get("method", "none"),
        "position_jump_ratio": seam.get("position_jump_ratio"),
        "velocity_jump_ratio": seam.get("velocity_jump_ratio"),
        "fps": float((document.get("input") or {}).get("fps") or BASE_FPS),
        "root_motion_removed": bool((document.get("root_motion") or {}).get("removed", False)),
        "seconds": time.perf_counter() - started,
    }
    return _record(work, "cycle", key, result)


# --------------------------------------------------------------------------------------------------
# Stage: poses


def _pose_body_cycle(character, fps: float, start: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Body positions and normals (frames, V, 3) at cache frames start .. start+frames-1, animation looped.

    Cloth sample k is at animation time (k / fps) modulo the animation's duration (the walk repeats while
    the cloth is simulated).
    """
    from crowdbake.bake.skinning import pose_character

    duration = float(character.animation_duration)
    if duration <= 0:
        positions, normals = pose_character(character, fps, 1)
        return np.repeat(positions, frames, axis=0), np.repeat(normals, frames, axis=0)
    loop = duration * fps
    whole = int(round(loop))
    if whole >= 1 and abs(loop - whole) < 1e-3:
        positions, normals = pose_character(character, fps, whole)
        index = (start + np.arange(frames)) % whole
        return positions[index], normals[index]
    posed = [pose_character(character, fps, 1, start_time=((start + k) / fps) % duration) for k in range(frames)]
    return np.concatenate([p for p, _ in posed]), np.concatenate([n for _, n in posed])


def _unit_normals(normals: np.ndarray) -> np.ndarray:
    """Normals with zero-length ones replaced by FALLBACK_NORMAL (a pose cache needs unit vectors)."""
    from crowdbake.bake.poses import FALLBACK_NORMAL

    normals = np.asarray(normals, dtype=np.float32)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    fixed = np.where(length > 0.5, normals / np.where(length > 0, length, 1.0), FALLBACK_NORMAL)
    return fixed.astype(np.float32)


def default_outfits(count: int = DEFAULT_OUTFIT_COUNT) -> np.ndarray:
    """(count, 16, 4) uint8 outfit map when the inputs bring none: region 0 white, others fixed colours."""
    rng = np.random.default_rng(_DEFAULT_OUTFIT_SEED)
    outfits = np.empty((count, 16, 4), dtype=np.uint8)
    outfits[..., :3] = rng.integers(64, 256, size=(count, 16, 3))
    outfits[..., 3] = 255
    outfits[:, 0, :3] = 255
    return outfits


def _materials(job: dict, inputs: Path, character) -> tuple[list[dict], np.ndarray]:
    """Materials [{"name", "layers" (L, H, W, 4) uint8}] and the outfit map (O, 16, 4) uint8."""
    names = job["inputs"]
    if "textures" in names:
        diffuse, outfits_path = _texture_files(inputs / names["textures"])
        layers = np.stack([_load_rgba_png(path) for path in diffuse])
        materials = [{"name": "character", "layers": layers}]
        if outfits_path is not None:
            outfits = _load_rgba_png(outfits_path).reshape(-1, 16, 4)
            outfits[..., 3] = 255
        else:
            outfits = default_outfits()
        return materials, outfits
    if character.texture is not None:
        body = np.asarray(character.texture, dtype=np.uint8).copy()
        # A glTF alpha is opacity, not a region code: region 0 keeps the texture's own colours.
        body[..., 3] = 0
    else:
        body = np.full((4, 4, 4), 200, dtype=np.uint8)
        body[..., 3] = 0
    # The garment's UVs address no texture we were given: a plain white one in region 1 takes the outfit colour.
    garment = np.full((4, 4, 4), 255, dtype=np.uint8)
    garment[..., 3] = 17
    return [{"name": "body", "layers": body[None]}, {"name": "garment", "layers": garment[None]}], default_outfits()


def _diffuse_format(layers: np.ndarray, compress: bool) -> str:
    height, width = layers.shape[1:3]
    return "bc2" if compress and height % 4 == 0 and width % 4 == 0 else "rgba8"


def stage_poses(work: Path, progress: Progress | None = None) -> dict:
    """Bake the poses: body (linear blend skinning) and cloth per cycle frame, high and low LOD.

    Writes work/poses/<part>_lod<k>.cbpc, textures.npz (materials, their encoded and decoded diffuse
    layers, the outfit map) and poses.json (parts, LOD figures, the impostor framing and frames).
    """
    from crowdbake.bake import compression, lod, poses
    from crowdbake.bake.atlas import AtlasLayout
    from crowdbake.formats.binary import encode_pose_cache
    from crowdbake.formats.gltf import load_character
    from crowdbake.formats.obj import read_obj
    from crowdbake.formats.pc2 import read_pc2

    started = time.perf_counter()
    work = Path(work)
    job = _job(work)
    key = _key("poses", _stage_key(work, "cycle"))
    out = work / "poses"
    summary_path = out / "poses.json"
    cached = _cached(work, "poses", key, [summary_path, out / "textures.npz"])
    if cached is not None:
        return cached
    params = BakeParams.from_dict(job["params"])
    cycle = _read_json(_stamp_path(work, "cycle"))["result"]
    inputs = work / "inputs"
    names = job["inputs"]
    fps, start, frames = float(cycle["fps"]), int(cycle["start_frame"]), int(cycle["cycle_frames"])
    steps = 6
    _report(progress, "poses", 0, steps)

    character = load_character(inputs / names["character"])
    body_positions, body_normals = _pose_body_cycle(character, fps, start, frames)
    if cycle.get("root_motion_removed"):
        # The cycle search worked in the root's frame (the character travels): follow it for the body.
        from crowdbake.bake.cycle import estimate_root_offsets

        source_frames = read_pc2(inputs / names["cloth"]).sample_count
        everything, _ = _pose_body_cycle(character, fps, 0, source_frames)
        offsets = estimate_root_offsets(everything)[start : start + frames]
        body_positions = (body_positions - offsets[:, None, :]).astype(np.float32)
    _report(progress, "poses", 1, steps)

    mesh = read_obj(inputs / names["cloth_mesh"])
    looped = read_pc2(work / "cycle" / "looped.pc2")
    if looped.points.shape[0] != frames:
        raise StageOrderError(f"looped.pc2 has {looped.points.shape[0]} frames, the cycle {frames}")
    garment_positions = poses.cloth_on_vertices(looped.points, mesh.source_index)
    garment_normals = poses.vertex_normals(garment_positions, mesh.faces, weld=mesh.source_index)
    if mesh.uvs is None:
        logger.warning("%s has no texture coordinates: the garment's UV map will read (0, 0)", names["cloth_mesh"])
    garment_uvs = mesh.uvs if mesh.uvs is not None else np.zeros((mesh.vertex_count, 2), np.float32)
    materials, outfits = _materials(job, inputs, character)
    garment_material = 0 if len(materials) == 1 else 1
    high = {
        "body": poses.PartPoses(
            faces=np.asarray(character.faces, dtype=np.uint32),
            uvs=np.asarray(character.uvs, dtype=np.float32),
            positions=np.asarray(body_positions, dtype=np.float32),
            normals=_unit_normals(body_normals),
        ),
        job["garment_part"]: poses.PartPoses(
            faces=np.asarray(mesh.faces, dtype=np.uint32),
            uvs=np.asarray(garment_uvs, dtype=np.float32),
            positions=garment_positions,
            normals=_unit_normals(garment_normals),
        ),
    }
    kinds = {"body": "body", job["garment_part"]: "garment"}
    part_material = {"body": 0, job["garment_part"]: garment_material}
    _report(progress, "poses", 2, steps)

    # The low LOD: the paper's ratio unless told otherwise; garments keep their borders.
    counts = [part.triangle_count for part in high.values()]
    if params.lod_triangles is not None:
        targets = lod.target_for_parts(counts, params.lod_triangles)
    else:
        ratio = params.lod_ratio if params.lod_ratio is not None else lod.PAPER_LOD_RATIO
        targets = [max(1, int(round(count * ratio))) for count in counts]
    parts = []
    for (name, part), target in zip(high.items(), targets):
        simplified = lod.simplify(part.positions[0], part.faces, target, uvs=part.uvs, lock_border=kinds[name] == "garment")
        low = poses.low_lod(part, simplified)
        for level, version in ((0, part), (1, low)):
            path = out / f"{name}_lod{level}.cbpc"
            _write_bytes_atomic(path, encode_pose_cache(version.faces, version.uvs, version.positions, version.normals, fps))
            parts.append(
                {
                    "part": name,
                    "kind": kinds[name],
                    "lod": level,
                    "file": path.name,
                    "material": part_material[name],
                    "vertex_count": version.vertex_count,
                    "triangle_count": version.triangle_count,
                }
            )
        parts[-1].update(target_triangles=int(target), relative_error=float(simplified.relative_error), locked_border=bool(simplified.locked_border))
    _report(progress, "poses", 4, steps)

    # Textures: encode the diffuse layers once; the impostor tasks and fidelity use what a runtime samples.
    arrays: dict[str, np.ndarray] = {"outfits": outfits}
    material_docs = []
    for index, material in enumerate(materials):
        layers = material["layers"]
        pixel_format = _diffuse_format(layers, params.compress)
        height, width = layers.shape[1:3]
        encoded = [compression.encode(layer, pixel_format) for layer in layers]
        decoded = np.stack([compression.decode(data, pixel_format, width, height) for data in encoded])
        arrays[f"material_{index}"] = layers
        arrays[f"material_{index}_encoded"] = np.frombuffer(b"".join(encoded), dtype=np.uint8)
        arrays[f"material_{index}_decoded"] = decoded
        # Variation 0 on its own: the impostor tasks need only it, and np.load reads whole arrays.
        arrays[f"material_{index}_v0"] = layers[0]
        arrays[f"material_{index}_decoded_v0"] = decoded[0]
        material_docs.append(
            {"name": material["name"], "variations": int(len(layers)), "width": int(width), "height": int(height), "pixel_format": pixel_format}
        )
    buffer = _npz_bytes(arrays)
    _write_bytes_atomic(out / "textures.npz", buffer)
    _report(progress, "poses", 5, steps)

    centre, radius = poses.common_bounds(*(part.positions for part in high.values()))
    layout = AtlasLayout.rings(params.tile_size, params.azimuths, tuple(params.elevations_deg))
    frame_indices = poses.impostor_frame_indices(frames, params.impostor_frames)
    summary = {
        "frames_per_second": fps,
        "cycle_frames": frames,
        "parts": parts,
        "materials": material_docs,
        "outfit_count": int(len(outfits)),
        "bounds": {"center": [float(c) for c in centre], "radius": float(radius)},
        "layout": layout.to_manifest(),
        "frame_indices": frame_indices,
        "fidelity_frame": frame_indices[0],
    }
    _write_json_atomic(summary_path, summary)
    _report(progress, "poses", steps, steps)
    result = {
        "meshes": [{k: p[k] for k in ("part", "lod", "vertex_count", "triangle_count")} for p in parts],
        "lod": [
            {k: p[k] for k in ("part", "triangle_count", "target_triangles", "relative_error", "locked_border")}
            for p in parts
            if p["lod"] == 1
        ],
        "frames": frames,
        "seconds": time.perf_counter() - started,
    }
    return _record(work, "poses", key, result)


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    import io

    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


# --------------------------------------------------------------------------------------------------
# Stage: impostors (fan-out)


def _poses_summary(work: Path) -> dict:
    path = Path(work) / "poses" / "poses.json"
    if not path.is_file():
        raise StageOrderError(f"{work}: stage 'poses' has not run yet")
    return _read_json(path)


def impostor_tasks(work: Path) -> list[dict]:
    """The impostor bake split into independent tasks: one per (baked frame, elevation ring).

    Each task is a small JSON-able dict {"id", "frame", "elevation", "views": [[a, e], ...],
    "references"}; "references" marks the fidelity frame's tasks, which also render the mesh references.
    The order is deterministic (frame, then elevation).
    """
    summary = _poses_summary(work)
    layout = summary["layout"]
    tasks = []
    for frame in summary["frame_indices"]:
        for elevation in range(len(layout["elevations_deg"])):
            tasks.append(
                {
                    "id": f"f{frame:04d}-e{elevation}",
                    "frame": int(frame),
                    "elevation": elevation,
                    "views": [[azimuth, elevation] for azimuth in range(len(layout["azimuths_deg"]))],
                    "references": frame == summary["fidelity_frame"],
                }
            )
    return tasks


@dataclass
class _Scene:
    """The high LOD of every part at one frame, concatenated, with its materials' textures."""

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray
    triangle_material: np.ndarray
    diffuse: list[np.ndarray]  # variation 0 per material, as given (detail maps)
    diffuse_runtime: list[np.ndarray]  # variation 0 per material, as the runtime samples it (after compression)
    outfit_row: np.ndarray


def _read_pose_frame(path: Path, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(indices (T, 3), uvs (V, 2), positions (V, 3), normals (V, 3)) of one frame of a CBPC the poses
    stage wrote (and checked): a memory map reads only that frame, not the whole cycle."""
    from crowdbake.formats.binary import POSE_CACHE_HEADER_SIZE

    with open(path, "rb") as handle:
        vertex_count, index_count, frame_count = np.frombuffer(handle.read(28)[16:28], "<u4").tolist()
    if not 0 <= frame < frame_count:
        raise ValueError(f"{path.name}: frame {frame} outside its {frame_count} frames")
    data = np.memmap(path, dtype=np.uint8, mode="r")
    offset = POSE_CACHE_HEADER_SIZE

    def take(dtype: str, count: int, start: int) -> np.ndarray:
        return np.frombuffer(data[start : start + 4 * count], dtype=dtype).copy()

    indices = take("<u4", index_count, offset).reshape(-1, 3)
    offset += 4 * index_count
    uvs = take("<f4", 2 * vertex_count, offset).reshape(-1, 2)
    offset += 8 * vertex_count
    frame_floats = 3 * vertex_count
    positions = take("<f4", frame_floats, offset + 4 * frame_floats * frame).reshape(-1, 3)
    offset += 4 * frame_floats * frame_count
    normals = take("<f4", frame_floats, offset + 4 * frame_floats * frame).reshape(-1, 3)
    return indices, uvs, positions, normals


def _load_scene(work: Path, frame: int) -> _Scene:
    work = Path(work)
    summary = _poses_summary(work)
    positions, normals, uvs, faces, materials = [], [], [], [], []
    offset = 0
    for part in summary["parts"]:
        if part["lod"] != 0:
            continue
        indices, part_uvs, part_positions, part_normals = _read_pose_frame(work / "poses" / part["file"], frame)
        positions.append(part_positions)
        normals.append(part_normals)
        uvs.append(part_uvs)
        faces.append(indices.astype(np.int64) + offset)
        materials.append(np.full(len(indices), part["material"], dtype=np.int64))
        offset += len(part_uvs)
    with np.load(work / "poses" / "textures.npz") as textures:
        count = len(summary["materials"])
        diffuse = [textures[f"material_{m}_v0"] for m in range(count)]
        runtime = [textures[f"material_{m}_decoded_v0"] for m in range(count)]
        outfit_row = textures["outfits"][0]
    return _Scene(
        np.concatenate(positions).astype(np.float64),
        np.concatenate(normals).astype(np.float64),
        np.concatenate(uvs).astype(np.float64),
        np.concatenate(faces),
        np.concatenate(materials),
        diffuse,
        runtime,
        outfit_row,
    )


def _part_path(work: Path, task: dict) -> Path:
    if not re.match(r"^[A-Za-z0-9_-]{1,64}$", str(task.get("id", ""))):
        raise ValueError(f"impostor task id {task.get('id')!r} is not a plain name")
    return Path(work) / "impostor" / "parts" / f"{task['id']}.npz"


def _midpoint_azimuths(azimuths: list[float]) -> list[float]:
    """The azimuth halfway to the next baked one, per baked azimuth (wrapping at 360°)."""
    if len(azimuths) == 1:
        return [(azimuths[0] + 180.0) % 360.0]
    following = azimuths[1:] + [azimuths[0] + 360.0]
    return [((a + b) / 2.0) % 360.0 for a, b in zip(azimuths, following)]


def stage_impostor_views(work: Path, task: dict) -> Path:
    """Render one task's views (normal, UV and detail maps) into work/impostor/parts/<id>.npz.

    Fidelity-frame tasks also render, per view, the mesh reference at the view's angle and at the angle
    halfway to the next azimuth (crowdbake.bake.fidelity). Returns the .npz path. Idempotent: a part
    written for the same poses and task is kept.
    """
    from crowdbake.bake import fidelity, impostor_maps
    from crowdbake.render.impostor import shared_renderer

    work = Path(work)
    path = _part_path(work, task)
    key = _key("impostor-part", _stage_key(work, "poses"), task)
    stats_path = path.with_suffix(".json")
    if path.is_file() and stats_path.is_file():
        try:
            if _read_json(stats_path).get("key") == key:
                return path
        except (OSError, json.JSONDecodeError):
            pass
    summary = _poses_summary(work)
    layout = summary["layout"]
    tile = int(layout["tile_size"])
    centre, radius = summary["bounds"]["center"], summary["bounds"]["radius"]
    frame = int(task["frame"])
    if frame not in summary["frame_indices"]:
        raise ValueError(f"impostor task frame {frame} is not one of the baked frames {summary['frame_indices']}")
    scene = _load_scene(work, frame)
    views = [(int(a), int(e)) for a, e in task["views"]]
    timings = {"render": 0.0, "maps": 0.0, "references": 0.0}

    normal, uv, detail, repaired = [], [], [], 0
    renderer = shared_renderer(tile)
    renderer.set_mesh(scene.positions, scene.faces)
    for a, e in views:
        view = impostor_maps.ortho_view(centre, radius, layout["azimuths_deg"][a], layout["elevations_deg"][e], tile)
        clock = time.perf_counter()
        image = renderer.render(view)
        timings["render"] += time.perf_counter() - clock
        clock = time.perf_counter()
        coverage = impostor_maps.resolve_coverage(view, image.ids, scene.positions, scene.faces, image.depth)
        maps = impostor_maps.view_maps(
            view, coverage, scene.positions, scene.normals, scene.uvs, scene.faces, scene.triangle_material, scene.diffuse
        )
        timings["maps"] += time.perf_counter() - clock
        repaired += coverage.repaired
        normal.append(maps.normal)
        uv.append(maps.uv)
        detail.append(maps.detail)

    arrays = {
        "views": np.asarray(views, dtype=np.int64).reshape(-1, 2),
        "normal": np.stack(normal),
        "uv": np.stack(uv),
        "detail": np.stack(detail),
    }
    if task.get("references"):
        clock = time.perf_counter()
        size = tile * FIDELITY_SUPERSAMPLE
        midpoints = _midpoint_azimuths(list(layout["azimuths_deg"]))
        references, between = [], []
        renderer = shared_renderer(size)
        renderer.set_mesh(scene.positions, scene.faces)
        for a, e in views:
            for azimuth, store in ((layout["azimuths_deg"][a], references), (midpoints[a], between)):
                view = impostor_maps.ortho_view(centre, radius, azimuth, layout["elevations_deg"][e], size)
                coverage = renderer.coverage(view, scene.positions, scene.faces)
                store.append(
                    fidelity.mesh_reference(
                        view, coverage, FIDELITY_SUPERSAMPLE, scene.positions, scene.normals, scene.uvs, scene.faces,
                        scene.triangle_material, scene.diffuse_runtime, scene.outfit_row, fidelity.camera_light(view),
                    ).astype(np.float32)
                )
        arrays["reference"] = np.stack(references)
        arrays["reference_between"] = np.stack(between)
        arrays["between_azimuths"] = np.asarray([midpoints[a] for a, _ in views], dtype=np.float64)
        timings["references"] = time.perf_counter() - clock

    _write_bytes_atomic(path, _npz_bytes(arrays))
    _write_json_atomic(stats_path, {"key": key, "views": len(views), "repaired_texels": repaired, "seconds": timings})
    return path


def stage_impostors(work: Path, progress: Progress | None = None) -> dict:
    """Every impostor task in this process, in order (what the CLI does; the service fans them out)."""
    started = time.perf_counter()
    tasks = impostor_tasks(work)
    for done, task in enumerate(tasks):
        _report(progress, "impostors", done, len(tasks))
        stage_impostor_views(work, task)
    _report(progress, "impostors", len(tasks), len(tasks))
    stats = impostor_statistics(work)
    stats["seconds"] = time.perf_counter() - started
    return stats


def impostor_statistics(work: Path) -> dict:
    """Views, renders and seconds summed over the written impostor parts (from their .json sidecars)."""
    totals = {"tasks": 0, "views": 0, "repaired_texels": 0, "render_seconds": 0.0, "maps_seconds": 0.0, "reference_seconds": 0.0}
    for task in impostor_tasks(work):
        stats_path = _part_path(work, task).with_suffix(".json")
        if not stats_path.is_file():
            continue
        stats = _read_json(stats_path)
        totals["tasks"] += 1
        totals["views"] += int(stats["views"])
        totals["repaired_texels"] += int(stats["repaired_texels"])
        totals["render_seconds"] += float(stats["seconds"]["render"])
        totals["maps_seconds"] += float(stats["seconds"]["maps"])
        totals["reference_seconds"] += float(stats["seconds"]["references"])
    return totals


# --------------------------------------------------------------------------------------------------
# Stage: pack


def _load_parts(work: Path, tasks: list[dict]) -> dict[str, Any]:
    missing = [task["id"] for task in tasks if not _part_path(work, task).is_file()]
    if missing:
        raise StageOrderError(f"{len(missing)} impostor tasks have not run, first {missing[0]}")
    parts = {}
    for task in tasks:
        with np.load(_part_path(work, task)) as data:
            parts[task["id"]] = {name: data[name] for name in data.files}
    return parts


def stage_pack(work: Path, progress: Progress | None = None) -> dict:
    """Atlases, block compression, fidelity, figure-4 memory and the manifest → work/bundle/ (verified)."""
    from crowdbake.bake import compression, impostor_maps, texture_memory
    from crowdbake.bake.atlas import AtlasLayout, assemble
    from crowdbake.formats.binary import encode_texture_array, layer_size
    from crowdbake.formats.bundle import BundleFile, build_manifest, verify_bundle, write_bundle

    started = time.perf_counter()
    work = Path(work)
    job = _job(work)
    tasks = impostor_tasks(work)
    task_keys = []
    for task in tasks:
        stats_path = _part_path(work, task).with_suffix(".json")
        task_keys.append(_read_json(stats_path)["key"] if stats_path.is_file() else None)
    key = _key("pack", _stage_key(work, "poses"), task_keys)
    bundle_dir = work / "bundle"
    cached = _cached(work, "pack", key, [bundle_dir / "manifest.json"])
    if cached is not None:
        return cached
    params = BakeParams.from_dict(job["params"])
    summary = _poses_summary(work)
    cycle = _read_json(_stamp_path(work, "cycle"))["result"]
    layout_doc = summary["layout"]
    layout = AtlasLayout(layout_doc["tile_size"], tuple(layout_doc["azimuths_deg"]), tuple(layout_doc["elevations_deg"]))
    frame_indices = summary["frame_indices"]
    parts = _load_parts(work, tasks)
    steps = len(frame_indices) + 3
    _report(progress, "pack", 0, steps)

    files: list[BundleFile] = []
    # Pose caches, as baked.
    meshes = []
    for part in summary["parts"]:
        path = f"meshes/{part['file']}"
        files.append(BundleFile(path, (work / "poses" / part["file"]).read_bytes(), "pose-cache"))
        meshes.append({k: part[k] for k in ("part", "kind", "lod", "material", "vertex_count", "triangle_count")} | {"file": path})

    # Materials and outfits.
    material_entries = []
    with np.load(work / "poses" / "textures.npz") as textures:
        texture_arrays = {name: textures[name] for name in textures.files}
    compression_report: dict[str, Any] = {}
    for index, material in enumerate(summary["materials"]):
        path = f"textures/{material['name']}_diffuse.cbtx"
        data = encode_texture_array(
            material["width"], material["height"], material["pixel_format"], _split_layers(texture_arrays[f"material_{index}_encoded"], material)
        )
        files.append(BundleFile(path, data, "diffuse"))
        material_entries.append({"name": material["name"], "diffuse": path, "variations": material["variations"]})
        if material["pixel_format"] != "rgba8":
            errors = [
                compression.compression_error(original, decoded)
                for original, decoded in zip(texture_arrays[f"material_{index}"], texture_arrays[f"material_{index}_decoded"])
            ]
            compression_report[f"diffuse_{material['name']}"] = _worst_errors(errors, material["pixel_format"])
    outfits = texture_arrays["outfits"]
    files.append(BundleFile("textures/outfits.cbtx", encode_texture_array(16, len(outfits), "rgba8", outfits[None]), "outfit-colours"))

    # Impostor atlases: layer k = frame_indices[k]; tiles from the tasks.
    formats = {"normal": "bc1" if params.compress else "rgba8", "uv": params.uv_format, "detail": "bc2" if params.compress else "rgba8"}
    layers: dict[str, list[bytes]] = {kind: [] for kind in formats}
    normal_errors, detail_errors = [], []
    fidelity_atlases: dict[str, np.ndarray] = {}
    by_frame: dict[int, list[dict]] = {}
    for task in tasks:
        by_frame.setdefault(task["frame"], []).append(task)
    for step, frame in enumerate(frame_indices, start=1):
        atlases = {}
        for kind in formats:
            tiles = {}
            for task in by_frame[frame]:
                data = parts[task["id"]]
                for (a, e), tile in zip(data["views"].tolist(), data[kind]):
                    tiles[(a, e)] = tile
            atlases[kind] = assemble(layout, tiles)
        covered = atlases["uv"][..., 3] > 0
        # The tiles carry 16-bit UV maps; what the bundle stores (and fidelity measures) is `stored`.
        stored = dict(atlases, uv16=atlases["uv"])
        if formats["uv"] == "uv32":
            stored["uv"] = impostor_maps.uv_map_to_uv32(atlases["uv"])
        for kind, pixel_format in formats.items():
            if pixel_format == "rgba16":
                encoded = atlases[kind].astype("<u2").tobytes()
            elif pixel_format == "uv32":
                encoded = stored[kind].astype("<u4").tobytes()
            else:
                encoded = compression.encode(atlases[kind], pixel_format)
            layers[kind].append(encoded)
            if pixel_format in ("bc1", "bc2"):
                decoded = compression.decode(encoded, pixel_format, layout.width, layout.height)
                (normal_errors if kind == "normal" else detail_errors).append(compression.compression_error(atlases[kind], decoded, covered))
                if frame == summary["fidelity_frame"] and kind == "normal":
                    fidelity_atlases["normal_decoded"] = decoded
        if frame == summary["fidelity_frame"]:
            fidelity_atlases.update(stored)
        _report(progress, "pack", step, steps)
    maps = {}
    for kind, role in (("normal", "impostor-normal"), ("uv", "impostor-uv"), ("detail", "impostor-detail")):
        path = f"impostor/{kind}.cbtx"
        files.append(BundleFile(path, encode_texture_array(layout.width, layout.height, formats[kind], layers[kind]), role))
        maps[kind] = path
    if normal_errors:
        compression_report["impostor_normal"] = _worst_errors(normal_errors, formats["normal"])
    if detail_errors:
        compression_report["impostor_detail"] = _worst_errors(detail_errors, formats["detail"])

    # Fidelity at 1:1 texel-to-pixel: per view, and at the angles between views with the nearest view.
    fidelity_doc = _fidelity(summary, layout, tasks, parts, fidelity_atlases, texture_arrays, formats)
    fidelity_doc["compression"] = compression_report
    files.append(BundleFile("fidelity.json", _json_bytes(fidelity_doc), "fidelity"))
    _report(progress, "pack", len(frame_indices) + 1, steps)

    # Figure 4 from this bundle's bytes (layer payloads: what a GPU holds).
    layer_bytes = {kind: layer_size(formats[kind], layout.width, layout.height) * len(frame_indices) for kind in formats}
    diffuse_per_variation = sum(layer_size(m["pixel_format"], m["width"], m["height"]) for m in summary["materials"])
    bundle_bytes = texture_memory.MapBytes(layer_bytes["normal"], layer_bytes["uv"], layer_bytes["detail"], diffuse_per_variation)
    variations = max(m["variations"] for m in summary["materials"])
    memory_doc = texture_memory.texture_memory_report(bundle_bytes, max(FIGURE4_MIN_VARIATIONS, variations), variations)
    files.append(BundleFile("texture_memory.json", _json_bytes(memory_doc), "texture-memory"))

    cycle_document = _bundle_cycle_document(_read_json(work / "cycle" / "cycle.json"))
    files.append(BundleFile("cycle.json", _json_bytes(cycle_document), "cycle"))

    sections = {
        "frames_per_second": summary["frames_per_second"],
        "cycle": {
            "source_start_frame": cycle["start_frame"],
            "source_end_frame": cycle["start_frame"] + cycle["cycle_frames"],
            "frames": cycle["cycle_frames"],
            "closing": cycle["closing"],
            "position_jump_ratio": _nonnegative(cycle.get("position_jump_ratio")),
            "velocity_jump_ratio": _nonnegative(cycle.get("velocity_jump_ratio")),
        },
        "materials": material_entries,
        "outfits": {"file": "textures/outfits.cbtx", "count": int(len(outfits)), "regions": 16},
        "meshes": meshes,
        "impostor": {
            **layout.to_manifest(),
            "frame_indices": frame_indices,
            "bounds": summary["bounds"],
            "maps": maps,
        },
    }
    manifest = build_manifest(job["name"], job["version"], sections, files, created=job["created"])
    if bundle_dir.exists():
        shutil.rmtree(bundle_dir)
    write_bundle(bundle_dir, manifest, files)
    verify_bundle(bundle_dir)
    _report(progress, "pack", steps, steps)
    result = {
        "files": {f.path: len(f.data) for f in sorted(files, key=lambda f: f.path)},
        "fidelity": {k: fidelity_doc[k] for k in ("impostor", "nearest_view", "impostor_uncompressed_normals")},
        "uv_precision": fidelity_doc["uv_precision"],
        "compression": compression_report,
        "texture_memory": {
            "paper_mib": {"1": memory_doc["paper"]["uv_mapped_mib"][0], "detail_8": memory_doc["paper"]["detail_mapped_mib"][7], "uv_8": memory_doc["paper"]["uv_mapped_mib"][7]},
            "bundle_break_even_variations": memory_doc["bundle"]["break_even_variations"],
        },
        "seconds": time.perf_counter() - started,
    }
    return _record(work, "pack", key, result)


def _split_layers(encoded: np.ndarray, material: dict) -> list[bytes]:
    from crowdbake.formats.binary import layer_size

    size = layer_size(material["pixel_format"], material["width"], material["height"])
    data = encoded.tobytes()
    return [data[k * size : (k + 1) * size] for k in range(material["variations"])]


def _worst_errors(errors: list[dict], pixel_format: str) -> dict:
    return {
        "pixel_format": pixel_format,
        "layers": len(errors),
        "rgb_max": max(e["rgb_max"] for e in errors),
        "rgb_mean_abs": float(np.mean([e["rgb_mean_abs"] for e in errors])),
        "rgb_rmse_worst": max(e["rgb_rmse"] for e in errors),
        "rgb_psnr_db_worst": min(e["rgb_psnr_db"] for e in errors),
        "alpha_max": max(e["alpha_max"] for e in errors),
    }


def _nonnegative(value: Any) -> float:
    """Seam ratios for the manifest: a number >= 0 (an undefined ratio, for a still cloth, is 0)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return 0.0
    return number if np.isfinite(number) and number >= 0 else 0.0


def _json_bytes(document: Any) -> bytes:
    """Canonical JSON bytes; non-finite floats become null (JSON has no infinity)."""

    def clean(value: Any) -> Any:
        if isinstance(value, float) and not np.isfinite(value):
            return None
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v) for v in value]
        return value

    return (json.dumps(clean(document), indent=2, sort_keys=True, allow_nan=False) + "\n").encode()


def _fidelity(summary, layout, tasks, parts, atlases, texture_arrays, formats) -> dict:
    from crowdbake.bake import fidelity, impostor_maps
    from crowdbake.bake.atlas import nearest_view, tile_of

    centre, radius = summary["bounds"]["center"], summary["bounds"]["radius"]
    count = len(summary["materials"])
    runtime_diffuse = [texture_arrays[f"material_{m}_decoded"][0] for m in range(count)]
    outfit_row = texture_arrays["outfits"][0]
    per_view, between, uncompressed = [], [], []
    for task in tasks:
        if not task["references"]:
            continue
        data = parts[task["id"]]
        for index, (a, e) in enumerate(data["views"].tolist()):
            view = impostor_maps.ortho_view(centre, radius, layout.azimuths_deg[a], layout.elevations_deg[e], layout.tile_size)
            light = fidelity.camera_light(view)
            uv_tile = tile_of(layout, atlases["uv"], a, e)
            normal_tile = tile_of(layout, atlases["normal_decoded"] if "normal_decoded" in atlases else atlases["normal"], a, e)
            image = fidelity.impostor_image(uv_tile, normal_tile, runtime_diffuse, outfit_row, light)
            score = fidelity.compare(data["reference"][index], image)
            per_view.append({"azimuth_deg": layout.azimuths_deg[a], "elevation_deg": layout.elevations_deg[e], **score})
            exact = fidelity.impostor_image(uv_tile, tile_of(layout, atlases["normal"], a, e), runtime_diffuse, outfit_row, light)
            uncompressed.append(fidelity.compare(data["reference"][index], exact))

            azimuth = float(data["between_azimuths"][index])
            mid_view = impostor_maps.ortho_view(centre, radius, azimuth, layout.elevations_deg[e], layout.tile_size)
            na, ne = nearest_view(layout, azimuth, layout.elevations_deg[e])
            near_image = fidelity.impostor_image(
                tile_of(layout, atlases["uv"], na, ne),
                tile_of(layout, atlases["normal_decoded"] if "normal_decoded" in atlases else atlases["normal"], na, ne),
                runtime_diffuse, outfit_row, fidelity.camera_light(mid_view),
            )
            between.append(
                {"azimuth_deg": azimuth, "elevation_deg": layout.elevations_deg[e], "nearest_azimuth_deg": layout.azimuths_deg[na], **fidelity.compare(data["reference_between"][index], near_image)}
            )
    texture_size = max(max(m["width"], m["height"]) for m in summary["materials"])
    return {
        "description": "Impostor vs mesh at 1:1 texel-to-pixel (crowdbake.bake.fidelity): SSIM and PSNR per view "
        "of the fidelity frame; nearest_view: the mesh halfway between two azimuths against the nearest baked view",
        "frame": summary["fidelity_frame"],
        "tile_size": layout.tile_size,
        "supersample": FIDELITY_SUPERSAMPLE,
        "light": {"ambient": fidelity.AMBIENT, "diffuse": fidelity.DIFFUSE, "direction_in_camera": fidelity.LIGHT_IN_CAMERA.tolist()},
        "normal_map_format": formats["normal"],
        "uv_map_format": formats["uv"],
        "impostor": fidelity.summarize(per_view),
        "impostor_uncompressed_normals": fidelity.summarize(uncompressed),
        "nearest_view": fidelity.summarize(between),
        "per_view": per_view,
        "between_views": between,
        "uv_precision": {"texture_size": texture_size, **fidelity.uv_precision(atlases["uv16"], texture_size)},
    }


# --------------------------------------------------------------------------------------------------
# Stage: publish


def _same_tree(a: Path, b: Path) -> bool:
    def listing(root: Path) -> dict[str, Path]:
        return {p.relative_to(root).as_posix(): p for p in root.rglob("*") if p.is_file()}

    left, right = listing(a), listing(b)
    if set(left) != set(right):
        return False
    return all(left[name].stat().st_size == right[name].stat().st_size and left[name].read_bytes() == right[name].read_bytes() for name in left)


def stage_publish(work: Path, bundles_root: Path) -> Path:
    """Publish work/bundle atomically as bundles_root/<name>/<version> and return that path.

    The same bytes already published: nothing to do. Other bytes under that version: VersionConflict.
    """
    from crowdbake.formats.bundle import BundleFile, verify_bundle, write_bundle

    work = Path(work)
    job = _job(work)
    source = work / "bundle"
    if not (source / "manifest.json").is_file():
        raise StageOrderError(f"{work}: stage 'pack' has not run yet")
    bundle = verify_bundle(source)
    target = Path(bundles_root) / job["name"] / job["version"]
    if target.exists():
        if _same_tree(source, target):
            return target
        raise VersionConflict(f"{job['name']}/{job['version']} is already published with other bytes")
    files = [BundleFile(entry["path"], (source / entry["path"]).read_bytes(), entry["role"], entry["media_type"]) for entry in bundle.manifest["files"]]
    try:
        write_bundle(target, bundle.manifest, files)
    except (FileExistsError, OSError):
        # Another publisher got there first (the final rename found the folder): same bytes or a conflict.
        if target.exists() and _same_tree(source, target):
            return target
        if target.exists():
            raise VersionConflict(f"{job['name']}/{job['version']} was published concurrently with other bytes") from None
        raise
    if not _same_tree(source, target):
        raise VersionConflict(f"{target} differs from the packed bundle after publishing")
    return target


# --------------------------------------------------------------------------------------------------
# Everything in one process


def _mesh_summary(meshes: list[dict], lods: list[dict]) -> list[dict]:
    """The manifest's meshes, low LODs with their target and meshoptimizer's error."""
    out = []
    for mesh in meshes:
        entry = {k: mesh[k] for k in ("part", "kind", "lod", "vertex_count", "triangle_count", "file")}
        if mesh["lod"] == 1:
            for lod in lods:
                if lod["part"] == mesh["part"]:
                    entry.update(target_triangles=lod["target_triangles"], relative_error=lod["relative_error"], locked_border=lod["locked_border"])
        out.append(entry)
    return out


def run_bake(inputs: BakeInputs, out_root: Path, work: Path | None = None, progress: Progress | None = None) -> BakeSummary:
    """Run every stage in this process and publish to out_root/<name>/<version>; returns a BakeSummary.

    work: the work directory (kept, so a rerun resumes); None = a temporary one, removed afterwards.
    """
    temporary = work is None
    work = Path(tempfile.mkdtemp(prefix="crowdbake-work-")) if temporary else Path(work)
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    try:
        clock = time.perf_counter()
        stage_validate(inputs, work)
        timings["validate"] = time.perf_counter() - clock
        clock = time.perf_counter()
        cycle = stage_cycle(work, progress)
        timings["cycle"] = time.perf_counter() - clock
        clock = time.perf_counter()
        poses = stage_poses(work, progress)
        timings["poses"] = time.perf_counter() - clock
        clock = time.perf_counter()
        stage_impostors(work, progress)
        timings["impostors"] = time.perf_counter() - clock
        impostor = impostor_statistics(work)
        clock = time.perf_counter()
        pack = stage_pack(work, progress)
        timings["pack"] = time.perf_counter() - clock
        clock = time.perf_counter()
        bundle = stage_publish(work, Path(out_root))
        timings["publish"] = time.perf_counter() - clock
        _report(progress, "publish", 1, 1)
    finally:
        if temporary:
            shutil.rmtree(work, ignore_errors=True)
    manifest = _read_json(bundle / "manifest.json")
    return BakeSummary(
        bundle=bundle,
        name=manifest["name"],
        version=manifest["version"],
        timings_s=timings,
        files={entry["path"]: entry["size"] for entry in manifest["files"]},
        meshes=_mesh_summary(manifest["meshes"], poses["lod"]),
        cycle={k: cycle[k] for k in ("start_frame", "end_frame", "cycle_frames", "closing", "position_jump_ratio", "velocity_jump_ratio", "fps")},
        impostor=impostor,
        fidelity=dict(pack["fidelity"], uv_precision=pack["uv_precision"]),
        compression=pack["compression"],
        texture_memory=pack["texture_memory"],
    )
