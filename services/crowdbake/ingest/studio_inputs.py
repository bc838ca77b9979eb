"""Upload checks for the inputs studios export besides PC2 + OBJ and PNG, and what an upload records so
a bake request can check placement without opening the files again.

- `check_point_cache`: an MDD (with its OBJ) or an Alembic .abc (alone) cloth upload, read with
  crowdbake.formats.cloth_cache; Alembic needs the `crowdbake[alembic]` extra on the API host.
- `placement_sample`: a few hundred points of the cloth's first frame (with its extremes), recorded in
  the cloth asset's info; `animation_summaries`: each animation's length and the character's bounds at
  its time 0, recorded in the character asset's info. crowdbake.ingest.bake_request checks the pair
  with crowdbake.bake.placement (which reads only the body's bounds) before a bake is queued.
- `check_jpeg_texture`: a JPEG diffuse variation (no alpha, so no colour-region codes).
"""
from __future__ import annotations

import os
import shutil
import struct
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

from crowdbake.ingest.rejections import INVALID_FILE, UNSUPPORTED_FORMAT, FieldError, UploadRejected, clean_message, expect_format
from crowdbake.params import fps_problem, min_cloth_frames

POINT_CACHE_EXTENSIONS = {".mdd": "mdd", ".abc": "abc"}
JPEG_EXTENSIONS = {".jpg": "jpeg", ".jpeg": "jpeg"}
MEDIA_TYPES = {"mdd": "application/x-mdd", "abc": "application/x-alembic", "jpeg": "image/jpeg"}
# Points of the first frame kept for the placement check: enough for its 90 % inside test to within a
# few percent, small enough for a JSON column (about 8 KB).
PLACEMENT_SAMPLE_POINTS = 256
# Animations whose rest bounds an upload records; a character with more is checked at bake time only.
MAX_ANIMATION_SUMMARIES = 16
JPEG_REGION_NOTE = ("a JPEG has no alpha channel, so no colour-region codes: every texel is region 0 and keeps its own "
                    "colour, no outfit colour applies (use a PNG with region codes in alpha for outfits)")


def placement_sample(first_frame: np.ndarray, count: int = PLACEMENT_SAMPLE_POINTS) -> list[list[float]]:
    """first_frame (P, 3) -> at most count + 6 points as lists: evenly spaced indices plus each axis's
    lowest and highest point, so the sample's bounds are the frame's."""
    points = np.asarray(first_frame, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return []
    picked = set(np.linspace(0, len(points) - 1, min(count, len(points))).round().astype(int).tolist())
    picked.update(points.argmin(axis=0).tolist())
    picked.update(points.argmax(axis=0).tolist())
    return [[float(f"{value:.6g}") for value in points[index]] for index in sorted(picked)]


def pc2_first_frame(path: Path) -> np.ndarray:
    """The first frame (P, 3) of a PC2 file already validated by crowdbake.formats.pc2 (header only read)."""
    with open(path, "rb") as handle:
        header = handle.read(32)
        point_count = struct.unpack("<i", header[12 + 4 : 12 + 8])[0]
        return np.frombuffer(handle.read(12 * point_count), dtype="<f4").reshape(point_count, 3)


def animation_summaries(path: Path, character) -> list[dict[str, Any]]:
    """[{name, seconds, rest_bounds [[x, y, z] low, [x, y, z] high]}] of the first MAX_ANIMATION_SUMMARIES
    animations: the body the cloth's first frame is checked against, per animation."""
    from crowdbake.formats.gltf import load_character
    from crowdbake.ingest.garment import body_at_rest

    summaries = []
    names = list(getattr(character, "animation_names", []) or [])
    for index in range(min(len(names), MAX_ANIMATION_SUMMARIES)):
        try:
            loaded = character if index == 0 else load_character(path, animation=index)
        except ValueError as error:  # that animation is broken: a bake that picks it is refused by validate
            summaries.append({"name": names[index], "error": str(error).splitlines()[0].replace(str(path), "the file")})
            continue
        body = body_at_rest(loaded)
        summaries.append({
            "name": names[index], "seconds": float(loaded.animation_duration),
            "rest_bounds": [[float(v) for v in body.min(axis=0)], [float(v) for v in body.max(axis=0)]],
        })
    return summaries


def _with_suffix(path: Path, suffix: str, scratch: Path) -> Path:
    """The staged upload under a name with its extension (the readers pick the format by extension)."""
    target = scratch / f"upload{suffix}"
    try:
        os.link(path, target)
    except OSError:
        shutil.copyfile(path, target)
    return target


def check_point_cache(
    cache_path: Path, cache_name: str, mesh_path: Path | None, mesh_name: str | None, cycle_frames: int | None = None,
    cache_field: str = "cache", mesh_field: str = "mesh", cancel: threading.Event | None = None,
) -> dict[str, Any]:
    """Validate an MDD (with its OBJ rest mesh) or an Alembic (alone) cloth upload. `cancel`, set from
    another thread (the request's client left), ends an Alembic's Blender child: alembic.ReadCancelled.

    Returns {format, frame_count, vertex_count, triangle_count, start_frame, sample_rate, fps,
    placement_sample}; raises UploadRejected naming the field and file."""
    from crowdbake.formats.alembic import alembic_available
    from crowdbake.formats.cloth_cache import read_cloth_cache

    file_format = expect_format(cache_path, cache_name, cache_field, POINT_CACHE_EXTENSIONS)
    if file_format == "abc":
        if mesh_path is not None:
            raise UploadRejected(INVALID_FILE, "an Alembic cache carries its own mesh", [FieldError(mesh_field, "leave out the mesh with an .abc cache", mesh_name)])
        if not alembic_available():
            raise UploadRejected(UNSUPPORTED_FORMAT, "this server reads no Alembic: install the crowdbake[alembic] extra on the API host",
                                 [FieldError(cache_field, "Alembic (.abc) needs the crowdbake[alembic] extra (bpy) on the API host; "
                                             "upload a PC2 or MDD with its OBJ instead", cache_name)])
    elif mesh_path is None:
        raise UploadRejected(INVALID_FILE, "an MDD cache needs its rest mesh", [FieldError(mesh_field, "missing: an .mdd cache needs its .obj rest mesh")])
    else:
        expect_format(mesh_path, mesh_name or "mesh.obj", mesh_field, {".obj": "obj"})
    scratch = Path(tempfile.mkdtemp(prefix="cloth-upload-"))
    try:
        cache_file = _with_suffix(cache_path, "." + ("abc" if file_format == "abc" else "mdd"), scratch)
        mesh_file = _with_suffix(mesh_path, ".obj", scratch) if mesh_path is not None else None
        try:
            cache = read_cloth_cache(cache_file, mesh_file, cancel=cancel)
        except (ValueError, OSError) as error:
            message = clean_message(clean_message(str(error).splitlines()[0], cache_file, cache_name), mesh_file or cache_file, mesh_name or cache_name)
            field = mesh_field if mesh_name and mesh_name in message and "points per frame" not in message else cache_field
            raise UploadRejected(INVALID_FILE, "the cloth cache does not parse", [FieldError(field, message, mesh_name if field == mesh_field else cache_name)]) from None
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    errors = []
    if len(cache.faces) == 0:
        errors.append(FieldError(mesh_field if mesh_path is not None else cache_field, "the mesh has no faces", mesh_name or cache_name))
    if not np.isfinite(cache.frames).all():
        errors.append(FieldError(cache_field, "NaN or infinite point positions", cache_name))
    rate_problem = fps_problem(cache.fps) if cache.fps is not None else None
    if rate_problem is not None:
        errors.append(FieldError(cache_field, f"the cache's frame rate: {rate_problem}", cache_name))
    needed = min_cloth_frames(cycle_frames)
    if cache.frame_count < needed:
        errors.append(FieldError(cache_field, f"too few frames for two cycles: the cache has {cache.frame_count}, two cycles need {needed}", cache_name))
    if errors:
        raise UploadRejected(INVALID_FILE, "the cloth cache cannot be baked", errors)
    return {
        "format": file_format,
        "frame_count": cache.frame_count,
        "vertex_count": cache.point_count,
        "triangle_count": int(len(cache.faces)),
        "start_frame": 0.0,
        "sample_rate": float(cache.frame_step),
        "fps": cache.fps,
        "placement_sample": placement_sample(cache.frames[0]),
    }


def check_jpeg_texture(path: Path, filename: str, max_pixels: int, field: str = "file") -> dict[str, Any]:
    """Validate a JPEG diffuse variation: the size from its header (decompression-bomb guard) before
    decoding, then every pixel decodes. Returns {format, width, height, mode, has_region_codes, note}."""
    from PIL import Image

    expect_format(path, filename, field, JPEG_EXTENSIONS)
    with open(path, "rb") as handle:
        if not handle.read(3) == b"\xff\xd8\xff":
            raise UploadRejected(INVALID_FILE, "not a JPEG image", [FieldError(field, "the JPEG start-of-image marker is missing", filename, "byte 0")])
    try:
        with Image.open(path) as image:
            width, height = image.size
            if width * height > max_pixels:
                raise UploadRejected(INVALID_FILE, "the image is too large", [FieldError(field, f"{width}x{height} pixels, at most {max_pixels} are accepted", filename)])
            image.load()
            mode = image.mode
    except UploadRejected:
        raise
    except Exception as error:  # Pillow raises OSError, SyntaxError, ValueError... for broken JPEGs
        message = clean_message(str(error), path, filename) or type(error).__name__
        raise UploadRejected(INVALID_FILE, f"the JPEG does not decode: {message}", [FieldError(field, message, filename)]) from None
    return {"format": "jpeg", "width": int(width), "height": int(height), "mode": mode, "has_region_codes": False, "note": JPEG_REGION_NOTE}
