"""Checks run on every upload before anything is stored.

Each check reads a staged file with the project's own readers (crowdbake.formats: read_pc2, read_obj,
load_character) and either returns what it measured (counts, sizes; recorded with the asset) or raises
UploadRejected with one FieldError per problem: the form field, the file (or zip entry) and where in it
(a byte offset or a line) the problem is. The API turns UploadRejected into an RFC 9457 problem.

Formats are recognised by their content, never by the name alone: a file whose name promises one format
and whose bytes are another is refused as a mismatch, before any reader sees it.
"""
from __future__ import annotations

import logging
import struct
from pathlib import Path
from typing import Any

import numpy as np

from crowdbake.errors import InputError
from crowdbake.ingest.rejections import (  # noqa: F401 (the API and the tests import these from here)
    CACHE_EXTENSIONS, CHARACTER_EXTENSIONS, COPY_CHUNK, GLB_MAGIC, INVALID_FILE, MESH_EXTENSIONS, PC2_MAGIC, PNG_SIGNATURE,
    TEXTURE_EXTENSIONS, FieldError, UploadRejected, _extension, clean_message, expect_format, where_from_message,
)
from crowdbake.params import min_cloth_frames

logger = logging.getLogger(__name__)

# -------------------------------------------------------------------------------------- characters


def _external_uris(path: Path) -> list[str]:
    """Buffer and image URIs of a .gltf or a .glb that are not embedded data URIs ([] if the JSON does
    not parse: the reader then says why)."""
    import json

    from crowdbake.formats.gltf import parse_glb

    try:
        data = path.read_bytes()
        document = parse_glb(data, path.name)[0] if data.startswith(GLB_MAGIC) else json.loads(data)
    except (ValueError, UnicodeDecodeError, RecursionError):  # RecursionError: "[[[[..." nested too deep
        return []
    if not isinstance(document, dict):
        return []
    uris = []
    for key in ("buffers", "images"):
        items = document.get(key)
        for item in items if isinstance(items, list) else []:
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                uris.append(uri)
    return uris


def _glb_where(path: Path, message: str) -> str | None:
    """The byte offset of a GLB problem: header fields by rule (magic 0, version 4, length 8), else
    the offset the reader named."""
    size = path.stat().st_size
    with open(path, "rb") as handle:
        header = handle.read(12)
    if not header.startswith(GLB_MAGIC):
        return where_from_message(message, path)  # a .gltf JSON document: the reader names the place
    if len(header) < 12:
        return f"byte {size}"
    _magic, version, length = struct.unpack("<4sII", header)
    if version != 2:
        return "byte 4"
    if length != size:
        return "byte 8"
    return where_from_message(message, path)


def check_character(path: Path, filename: str, field: str = "file") -> dict[str, Any]:
    """Validate a character (.glb, or a self-contained .gltf) with crowdbake.formats.gltf.load_character.

    Returns {format, vertex_count, triangle_count, joint_count, animation_seconds, has_texture}.
    """
    from crowdbake.formats.gltf import load_character

    file_format = expect_format(path, filename, field, CHARACTER_EXTENSIONS)
    # A GLB may name external files too (its JSON chunk can give any buffer or image a uri). The reader
    # would resolve them next to the staging file, so "../../etc/passwd" would read a server file into
    # the character: refuse every uri that is not a data URI, whatever the container.
    external = _external_uris(path)
    if external:
        raise UploadRejected(
            INVALID_FILE,
            f"an uploaded .{file_format} must embed its buffers and images",
            [FieldError(field, f"refers to the external file {uri!r}; embed it (a .glb's BIN chunk or a data URI)", filename) for uri in external],
        )
    try:
        character = load_character(path)
    except ValueError as error:
        message = clean_message(str(error), path, filename)
        raise UploadRejected(INVALID_FILE, f"the character is not a usable glTF: {message}", [FieldError(field, message, filename, _glb_where(path, str(error)))]) from None
    positions = np.asarray(character.positions)
    if positions.size == 0 or len(character.faces) == 0:
        raise UploadRejected(INVALID_FILE, "the character has no triangles", [FieldError(field, "no skinned triangles", filename)])
    if not np.isfinite(positions).all():
        raise UploadRejected(INVALID_FILE, "the character has NaN or infinite positions", [FieldError(field, "NaN or infinite vertex position", filename)])
    from crowdbake.ingest.garment import body_at_rest  # refuses a character of implausible height

    try:
        body_at_rest(character)
    except InputError as error:
        raise UploadRejected(INVALID_FILE, error.message, [FieldError(field, error.message, filename)]) from None
    return {
        "format": file_format,
        "vertex_count": int(positions.shape[0]),
        "triangle_count": int(len(character.faces)),
        "joint_count": int(len(character.joint_names)),
        "animation_seconds": float(character.animation_duration),
        "has_texture": character.texture is not None,
        "animations": _animation_summaries(path, character),
    }


def _animation_summaries(path: Path, character) -> list[dict[str, Any]]:
    from crowdbake.ingest.studio_inputs import animation_summaries

    return animation_summaries(path, character)


# ------------------------------------------------------------------------------------------- cloth

_PC2_HEADER = struct.Struct("<12siiffi")  # the PC2 layout, see crowdbake.formats.pc2
_PC2_FIELD_OFFSETS = {"magic": 0, "version": 12, "points": 16, "start": 20, "rate": 24, "samples": 28}


def _pc2_where(path: Path) -> str | None:
    """The byte offset of the first problem of a PC2 file that crowdbake.formats.pc2 rejected.

    The reader gives the verdict; this only finds the place, following the same order of checks.
    """
    size = path.stat().st_size
    with open(path, "rb") as handle:
        header = handle.read(_PC2_HEADER.size)
        if len(header) < _PC2_HEADER.size:
            return f"byte {size}"
        magic, version, points, start, rate, samples = _PC2_HEADER.unpack(header)
        if magic != PC2_MAGIC:
            return "byte 0"
        if version != 1:
            return f"byte {_PC2_FIELD_OFFSETS['version']}"
        if points < 0:
            return f"byte {_PC2_FIELD_OFFSETS['points']}"
        if samples < 0:
            return f"byte {_PC2_FIELD_OFFSETS['samples']}"
        if not np.isfinite(start):
            return f"byte {_PC2_FIELD_OFFSETS['start']}"
        if not np.isfinite(rate) or rate <= 0:
            return f"byte {_PC2_FIELD_OFFSETS['rate']}"
        expected = _PC2_HEADER.size + 12 * points * samples
        if size != expected:
            return f"byte {min(size, expected)}"
        offset = _PC2_HEADER.size
        while True:
            chunk = handle.read(COPY_CHUNK)
            if not chunk:
                return None
            values = np.frombuffer(chunk[: len(chunk) // 4 * 4], dtype="<f4")
            bad = np.flatnonzero(~np.isfinite(values))
            if bad.size:
                return f"byte {offset + 4 * int(bad[0])}"
            offset += len(chunk)


def check_cloth(
    cache_path: Path, cache_name: str, mesh_path: Path, mesh_name: str, cycle_frames: int | None = None,
    cache_field: str = "cache", mesh_field: str = "mesh",
) -> dict[str, Any]:
    """Validate a cloth cache (PC2) against its rest mesh (OBJ): both parse, the PC2 has one point per
    OBJ position, and enough frames for two cycles of `cycle_frames` (or of the shortest cycle).

    Returns {frame_count, vertex_count, triangle_count, start_frame, sample_rate}.
    """
    from crowdbake.formats.obj import read_obj
    from crowdbake.formats.pc2 import read_pc2

    expect_format(cache_path, cache_name, cache_field, CACHE_EXTENSIONS)
    expect_format(mesh_path, mesh_name, mesh_field, MESH_EXTENSIONS)
    errors: list[FieldError] = []
    cache = mesh = None
    try:
        cache = read_pc2(cache_path)
    except ValueError as error:
        errors.append(FieldError(cache_field, clean_message(str(error), cache_path, cache_name), cache_name, _pc2_where(cache_path)))
    try:
        mesh = read_obj(mesh_path)
    except ValueError as error:
        errors.append(FieldError(mesh_field, clean_message(str(error), mesh_path, mesh_name), mesh_name, where_from_message(str(error), mesh_path)))
    if errors:
        raise UploadRejected(INVALID_FILE, "the cloth files do not parse", errors)
    assert cache is not None and mesh is not None
    if len(mesh.faces) == 0:
        errors.append(FieldError(mesh_field, "the mesh has no faces", mesh_name))
    if cache.point_count != mesh.position_count:
        errors.append(
            FieldError(
                cache_field,
                f"the cache has {cache.point_count} points per frame but the mesh {mesh_name} has {mesh.position_count} vertex positions",
                cache_name,
                f"byte {_PC2_FIELD_OFFSETS['points']}",
            )
        )
    needed = min_cloth_frames(cycle_frames)
    if cache.sample_count < needed:
        errors.append(
            FieldError(
                cache_field,
                f"too few frames for two cycles: the cache has {cache.sample_count}, two cycles need {needed}",
                cache_name,
                f"byte {_PC2_FIELD_OFFSETS['samples']}",
            )
        )
    if errors:
        raise UploadRejected(INVALID_FILE, "the cloth cache and its mesh cannot be baked", errors)
    return {
        "frame_count": cache.sample_count,
        "vertex_count": cache.point_count,
        "triangle_count": int(len(mesh.faces)),
        "start_frame": cache.start_frame,
        "sample_rate": cache.sample_rate,
    }


# ---------------------------------------------------------------------------------------- textures


def check_texture(path: Path, filename: str, max_pixels: int, field: str = "file") -> dict[str, Any]:
    """Validate a PNG texture: signature, size (decompression-bomb guard, read from IHDR before
    decoding), and every chunk and pixel decodes. Returns {width, height, mode}."""
    from PIL import Image

    expect_format(path, filename, field, TEXTURE_EXTENSIONS)
    size = path.stat().st_size
    with open(path, "rb") as handle:
        head = handle.read(33)
    if not head.startswith(PNG_SIGNATURE):
        raise UploadRejected(INVALID_FILE, "not a PNG image", [FieldError(field, "the PNG signature is missing", filename, "byte 0")])
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise UploadRejected(INVALID_FILE, "a PNG image is truncated or has no header", [FieldError(field, "no IHDR chunk after the signature", filename, f"byte {min(size, 8)}")])
    width, height = struct.unpack(">II", head[16:24])
    if width == 0 or height == 0 or width * height > max_pixels:
        raise UploadRejected(INVALID_FILE, "the image is too large", [FieldError(field, f"{width}x{height} pixels, at most {max_pixels} are accepted", filename, "byte 16")])
    try:
        with Image.open(path) as image:
            image.verify()
        with Image.open(path) as image:
            image.load()
            mode = image.mode
    except Exception as error:  # Pillow raises OSError, SyntaxError, ValueError... for broken PNGs
        # Pillow names the file it opened: the staging path, which is the server's business.
        message = clean_message(str(error), path, filename) or type(error).__name__
        where = f"byte {size}" if "truncated" in message.lower() else None
        raise UploadRejected(INVALID_FILE, f"the PNG does not decode: {message}", [FieldError(field, message, filename, where)]) from None
    return {"width": int(width), "height": int(height), "mode": mode}
