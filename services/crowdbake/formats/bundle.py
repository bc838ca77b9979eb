"""Bundles (shared_formats/SPEC.md): write one atomically, verify one completely.

A bundle is a folder: manifest.json plus the files it lists with size, sha256, media type
and role. `write_bundle` builds the `files` list from the bytes it is given, so a manifest
can never disagree with what was written; `verify_bundle` checks everything a runtime
would rely on and raises FormatError with the spec's error code and the file concerned.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from crowdbake import __version__
from crowdbake.files import fsync_path
from crowdbake.formats.binary import (
    POSE_CACHE_VERSION,
    QUANTIZED_POSE_CACHE_VERSION,
    PoseCache,
    TextureArray,
    decode_pose_cache,
    decode_texture_array,
)
from crowdbake.formats.errors import FormatError, printable
from crowdbake.formats.skinned_cache import SkinnedPoseCache, decode_skinned_pose_cache, is_skinned_pose_cache
from crowdbake.formats.ranges import Ranges, check_impostor_frames, read_ranges

FORMAT_NAME = "crowdbake-bundle"
# What the bake writes: clips and transitions (a bundle of one clip holds one, named `cycle`) and
# quantized pose caches (SPEC.md "Version 3").
FORMAT_VERSION = 3
# A bundle whose body is a skinned pose cache (CBSK, SPEC.md "Version 4"); the bake writes it only then.
SKINNED_FORMAT_VERSION = 4
SKINNED_POSE_CACHE_MEDIA_TYPE = "application/vnd.crowdbake.skinned-pose-cache"
READ_FORMAT_VERSIONS = (1, 2, 3, 4)
SCHEMA_PATH = Path(__file__).resolve().parents[3] / "shared_formats" / "manifest.schema.json"
_PATH_RULE = re.compile(r"^[A-Za-z0-9._-]+(/[A-Za-z0-9._-]+)*$")
MAX_PATH_LENGTH = 200

MEDIA_TYPES = {
    "pose-cache": "application/vnd.crowdbake.pose-cache",
    "diffuse": "application/vnd.crowdbake.texture",
    "outfit-colours": "application/vnd.crowdbake.texture",
    "impostor-normal": "application/vnd.crowdbake.texture",
    "impostor-uv": "application/vnd.crowdbake.texture",
    "impostor-detail": "application/vnd.crowdbake.texture",
    "impostor-surface": "application/vnd.crowdbake.texture",
    "cycle": "application/json",
    "fidelity": "application/json",
    "texture-memory": "application/json",
}


def check_path(path: str) -> None:
    """Raise FormatError('unsafe_path') unless `path` obeys the spec's path rule (stays inside the bundle)."""
    if isinstance(path, str) and printable(path) != path:
        raise FormatError("unsafe_path", "path holds control characters (written here as \\xNN or \\u00NN), which the bundle path "
                          "rule forbids ([A-Za-z0-9._-] components)", path)
    if (
        not isinstance(path, str)
        or len(path) > MAX_PATH_LENGTH
        or not _PATH_RULE.fullmatch(path)
        or any(part in (".", "..") for part in path.split("/"))
        or path == "manifest.json"
    ):
        raise FormatError("unsafe_path", "path breaks the bundle path rule (relative, no '..', [A-Za-z0-9._-])", str(path))


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class BundleFile:
    """One file to write into a bundle. media_type defaults from the role (SPEC.md table)."""

    path: str
    data: bytes
    role: str
    media_type: str = ""

    def entry(self) -> dict[str, Any]:
        skinned = self.role == "pose-cache" and is_skinned_pose_cache(self.data)
        media_type = self.media_type or (SKINNED_POSE_CACHE_MEDIA_TYPE if skinned else MEDIA_TYPES.get(self.role))
        if not media_type:
            raise ValueError(f"role {self.role!r} needs an explicit media_type")
        return {"path": self.path, "size": len(self.data), "sha256": sha256_hex(self.data), "media_type": media_type, "role": self.role}


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).strftime("%Y-%m-%dT%H:%M:%SZ")


def build_manifest(name: str, version: str, sections: dict[str, Any], files: list[BundleFile], created: str | None = None, *,
                   format_version: int) -> dict[str, Any]:
    """The manifest dict: identity, the caller's sections (cycle or clips, meshes, ...), and the files list."""
    for bundle_file in files:
        check_path(bundle_file.path)
    paths = [bundle_file.path for bundle_file in files]
    if len(set(paths)) != len(paths):
        raise ValueError("a bundle lists each path once")
    manifest = {
        "format": FORMAT_NAME,
        "format_version": format_version,
        "name": name,
        "version": version,
        "created": created or utc_now(),
        "producer": f"crowdbake {__version__}",
    }
    manifest.update(sections)
    manifest["files"] = [bundle_file.entry() for bundle_file in sorted(files, key=lambda f: f.path)]
    return manifest


def manifest_bytes(manifest: dict[str, Any]) -> bytes:
    """Canonical manifest bytes: sorted keys, two-space indent, trailing newline (stable hashes)."""
    return (json.dumps(manifest, indent=2, sort_keys=True) + "\n").encode()


def write_bundle(out_dir: Path, manifest: dict[str, Any], files: list[BundleFile]) -> Path:
    """Write a bundle folder atomically: a temp folder beside `out_dir`, fsync, one rename.

    Refuses to replace an existing folder (published bundles are immutable); the caller
    decides what an existing identical bundle means. Returns `out_dir`.
    """
    out_dir = Path(out_dir)
    if out_dir.exists():
        raise FileExistsError(f"{out_dir} already exists; bundles are never overwritten")
    listed = {entry["path"]: entry for entry in manifest["files"]}
    if set(listed) != {f.path for f in files}:
        raise ValueError("manifest files and written files differ")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        for bundle_file in files:
            if listed[bundle_file.path]["sha256"] != sha256_hex(bundle_file.data):
                raise ValueError(f"{bundle_file.path}: bytes differ from the manifest")
            target = staging / bundle_file.path
            target.parent.mkdir(parents=True, exist_ok=True)
            with open(target, "wb") as handle:
                handle.write(bundle_file.data)
                handle.flush()
                os.fsync(handle.fileno())
        with open(staging / "manifest.json", "wb") as handle:
            handle.write(manifest_bytes(manifest))
            handle.flush()
            os.fsync(handle.fileno())
        for folder in sorted({p.parent for p in staging.rglob("*")}, key=lambda p: len(p.parts), reverse=True):
            fsync_path(folder)
        os.rename(staging, out_dir)
        fsync_path(out_dir.parent)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out_dir


@lru_cache(maxsize=1)
def _validator():
    import jsonschema

    schema = json.loads(SCHEMA_PATH.read_text())
    return jsonschema.Draft202012Validator(schema)


def validate_manifest(manifest: Any) -> Ranges:
    """Raise FormatError unless `manifest` is a manifest of format 1, 2 or 3 valid against the JSON Schema
    whose clips and transitions tile its pose frames; return those ranges (v1: one clip `cycle`)."""
    if not isinstance(manifest, dict):
        raise FormatError("manifest_invalid", "the manifest is not a JSON object", "manifest.json")
    version = manifest.get("format_version")
    if isinstance(version, int) and not isinstance(version, bool) and version > READ_FORMAT_VERSIONS[-1]:
        raise FormatError(
            "unsupported_format_version", f"format_version {version}, this reader supports {READ_FORMAT_VERSIONS[0]} to "
            f"{READ_FORMAT_VERSIONS[-1]}", "manifest.json"
        )
    if isinstance(version, int) and version >= 2 and "cycle" in manifest:  # the schema's `"cycle": false` would say only
        # "False schema does not allow"
        raise FormatError("manifest_invalid", f"at cycle: a format_version {version} manifest holds clips and transitions, not v1's cycle",
                          "manifest.json")
    errors = sorted(_validator().iter_errors(manifest), key=lambda e: list(e.absolute_path))
    if errors:
        first = errors[0]
        where = "/".join(str(part) for part in first.absolute_path) or "(top level)"
        raise FormatError("manifest_invalid", f"at {where}: {first.message}", "manifest.json")
    return read_ranges(manifest)


@dataclass
class Bundle:
    """A verified bundle: its manifest, its clips and transitions (v1: one clip `cycle`) and decoded binaries by path."""

    root: Path
    manifest: dict[str, Any]
    ranges: Ranges
    pose_caches: dict[str, PoseCache | SkinnedPoseCache] = field(default_factory=dict)
    textures: dict[str, TextureArray] = field(default_factory=dict)


def verify_bundle(root: Path) -> Bundle:
    """Verify a bundle folder as SPEC.md's "Verifying a bundle" says; raise FormatError on the first problem."""
    root = Path(root)
    try:
        manifest = json.loads((root / "manifest.json").read_bytes())
    except FileNotFoundError:
        raise FormatError("manifest_invalid", "no manifest.json in the bundle folder", "manifest.json") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise FormatError("manifest_invalid", f"not JSON: {error}", "manifest.json") from None
    ranges = validate_manifest(manifest)

    contents: dict[str, bytes] = {}
    entries: dict[str, dict[str, Any]] = {}
    for entry in manifest["files"]:
        path = entry["path"]
        check_path(path)
        if path in entries:
            raise FormatError("manifest_invalid", "path listed twice", path)
        entries[path] = entry
        file_path = root / path
        if not file_path.is_file():
            raise FormatError("missing_file", "listed in the manifest but absent", path)
        size = file_path.stat().st_size
        if size != entry["size"]:
            raise FormatError("size_mismatch", f"{size} bytes, manifest says {entry['size']}", path)
        data = file_path.read_bytes()
        if sha256_hex(data) != entry["sha256"]:
            raise FormatError("sha256_mismatch", "bytes differ from the manifest's sha256", path)
        contents[path] = data

    bundle = Bundle(root, manifest, ranges)
    for path, entry in entries.items():
        if entry["role"] == "pose-cache":
            decode = decode_skinned_pose_cache if is_skinned_pose_cache(contents[path]) else decode_pose_cache
            bundle.pose_caches[path] = decode(contents[path], path)
        elif entry["media_type"] == MEDIA_TYPES["diffuse"]:
            bundle.textures[path] = decode_texture_array(contents[path], path)
    _cross_check(bundle)
    return bundle


def _require(condition: bool, message: str, path: str) -> None:
    if not condition:
        raise FormatError("invalid_data", message, path)


def pose_cache_version(format_version: int) -> int:
    """The CBPC version a bundle of `format_version` holds (SPEC.md "Version 3")."""
    return QUANTIZED_POSE_CACHE_VERSION if format_version >= 3 else POSE_CACHE_VERSION


def _cross_check(bundle: Bundle) -> None:
    """SPEC.md's cross-checks: every reference resolves and every size agrees."""
    manifest = bundle.manifest
    frames = bundle.ranges.pose_frames
    cache_version = pose_cache_version(manifest["format_version"])

    def texture(path: str) -> TextureArray:
        _require(path in bundle.textures, "referenced but not listed as a texture", path)
        return bundle.textures[path]

    for mesh in manifest["meshes"]:
        path = mesh["file"]
        _require(path in bundle.pose_caches, "mesh file is not listed as a pose-cache", path)
        cache = bundle.pose_caches[path]
        _require(cache.vertex_count == mesh["vertex_count"], f"{cache.vertex_count} vertices, manifest says {mesh['vertex_count']}", path)
        _require(cache.triangle_count == mesh["triangle_count"], f"{cache.triangle_count} triangles, manifest says {mesh['triangle_count']}", path)
        _require(cache.frame_count == frames, f"{cache.frame_count} frames, the bundle has {frames} pose frames", path)
        if isinstance(cache, SkinnedPoseCache):
            _require(manifest["format_version"] >= SKINNED_FORMAT_VERSION, f"a skinned pose cache (CBSK) in a format_version "
                     f"{manifest['format_version']} bundle: only format_version {SKINNED_FORMAT_VERSION} holds them", path)
            _require(mesh["kind"] == "body", f"a skinned pose cache (CBSK) as a {mesh['kind']}: only a body is skinned", path)
        else:
            _require(cache.version == cache_version, f"pose cache version {cache.version}, a format_version "
                     f"{manifest['format_version']} bundle holds version {cache_version}", path)
        _require(cache.frames_per_second == float(np.float32(manifest["frames_per_second"])),
                 f"frames_per_second {cache.frames_per_second}, the manifest says {manifest['frames_per_second']}", path)
        _require(mesh["material"] < len(manifest["materials"]), f"material {mesh['material']} does not exist", path)
    for material in manifest["materials"]:
        diffuse = texture(material["diffuse"])
        _require(len(diffuse.layers) == material["variations"], f"{len(diffuse.layers)} layers, manifest says {material['variations']} variations", material["diffuse"])
    outfits = manifest["outfits"]
    outfit_map = texture(outfits["file"])
    _require(
        (outfit_map.width, outfit_map.height, outfit_map.pixel_format) == (16, outfits["count"], "rgba8"),
        f"outfit map must be rgba8 16x{outfits['count']}",
        outfits["file"],
    )
    impostor = manifest["impostor"]
    tile, crop = impostor["tile_size"], impostor.get("crop")
    if crop is not None:
        _require(crop["x"] + crop["width"] <= tile and crop["y"] + crop["height"] <= tile,
                 f"impostor/crop reaches outside the {tile}-texel tile", "manifest.json")
    cell_width, cell_height = (tile, tile) if crop is None else (crop["width"], crop["height"])
    width = cell_width * len(impostor["azimuths_deg"])
    height = cell_height * len(impostor["elevations_deg"])
    _require(all(0 <= f < frames for f in impostor["frame_indices"]), "frame_indices outside the cycle", "manifest.json")
    _require(impostor["frame_indices"] == sorted(set(impostor["frame_indices"])), "frame_indices must ascend", "manifest.json")
    check_impostor_frames(bundle.ranges, impostor["frame_indices"])
    for kind, path in impostor["maps"].items():
        atlas = texture(path)
        _require(
            (atlas.width, atlas.height, len(atlas.layers)) == (width, height, len(impostor["frame_indices"])),
            f"{kind} atlas is {atlas.width}x{atlas.height}x{len(atlas.layers)}, layout needs {width}x{height}x{len(impostor['frame_indices'])}",
            path,
        )
    _require(bundle.textures[impostor["maps"]["uv"]].pixel_format in ("rgba16", "uv32", "uvblock"), "the UV map must be rgba16, uv32 or uvblock (12+ bits per coordinate)", impostor["maps"]["uv"])
    if "surface" in impostor["maps"]:
        surface = impostor["maps"]["surface"]
        _require(bundle.textures[surface].pixel_format in ("bc1", "bc2", "rgba8"), "the surface map must be bc1, bc2 or rgba8", surface)
