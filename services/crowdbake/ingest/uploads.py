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
import re
import shutil
import stat
import struct
import tempfile
import zipfile
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Protocol

import numpy as np

from crowdbake.params import min_cloth_frames

logger = logging.getLogger(__name__)

# Entries smaller than this may compress extremely well for innocent reasons (a run of zeros); the
# ratio check of the zip-bomb guard applies above it.
ZIP_RATIO_MIN_BYTES = 1 << 20
_COPY_CHUNK = 1 << 20
_SNIFF_BYTES = 4096

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
GLB_MAGIC = b"glTF"
PC2_MAGIC = b"POINTCACHE2\0"
ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")
# Compression methods Python's zipfile reads (store, deflate, bzip2, lzma); others raise NotImplementedError.
READABLE_ZIP_METHODS = frozenset({zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA})

# Extension -> the content format it promises.
CHARACTER_EXTENSIONS = {".glb": "glb", ".gltf": "gltf"}
CACHE_EXTENSIONS = {".pc2": "pc2"}
MESH_EXTENSIONS = {".obj": "obj"}
SEQUENCE_EXTENSIONS = {".zip": "zip"}
TEXTURE_EXTENSIONS = {".png": "png"}

FORMAT_NAMES = {
    "glb": "a binary glTF (GLB)",
    "gltf": "a glTF JSON document",
    "png": "a PNG image",
    "pc2": "a PC2 point cache",
    "zip": "a zip archive",
    "obj": "a Wavefront OBJ mesh",
}
_OBJ_KEYWORDS = re.compile(rb"^\s*(v|vt|vn|vp|f|o|g|s|l|p|mtllib|usemtl|#)(\s|$)")


@dataclass(frozen=True)
class FieldError:
    """One problem: the request field, the file (or archive entry) and where in it, e.g. 'byte 48'."""

    field: str
    message: str
    file: str | None = None
    where: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {key: value for key, value in asdict(self).items() if value is not None}


# Problem kinds (the API maps each to an RFC 9457 problem type and status).
INVALID_FILE = "invalid-file"            # 422: the bytes break their format or the bake's needs
FORMAT_MISMATCH = "format-mismatch"      # 422: the name promises one format, the bytes are another
UNSUPPORTED_FORMAT = "unsupported-format"  # 415: a kind of file the service does not take
UNSAFE_ARCHIVE = "unsafe-archive"        # 422: a zip that escapes its folder or expands too far


class UploadRejected(Exception):
    """An upload fails validation; nothing of it may be stored."""

    def __init__(self, kind: str, detail: str, errors: list[FieldError]):
        super().__init__(detail)
        self.kind = kind
        self.detail = detail
        self.errors = errors


@dataclass(frozen=True)
class ZipLimits:
    max_entries: int
    max_uncompressed_bytes: int
    max_ratio: float


class Writable(Protocol):
    def write(self, chunk: bytes) -> Any: ...


# ----------------------------------------------------------------------------------------- formats


def sniff_format(path: Path) -> str | None:
    """The format the bytes are (a key of FORMAT_NAMES), or None when they are none of them."""
    with open(path, "rb") as handle:
        head = handle.read(_SNIFF_BYTES)
    if head.startswith(GLB_MAGIC):
        return "glb"
    if head.startswith(PNG_SIGNATURE):
        return "png"
    if head.startswith(PC2_MAGIC):
        return "pc2"
    if head.startswith(ZIP_MAGICS):
        return "zip"
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if text.startswith(b"{"):
        return "gltf"
    if b"\0" not in head and any(_OBJ_KEYWORDS.match(line) for line in head.splitlines()[:50]):
        return "obj"
    return None


def _extension(filename: str) -> str:
    return PurePosixPath(filename.replace("\\", "/")).suffix.lower()


def expect_format(path: Path, filename: str, field: str, allowed: dict[str, str]) -> str:
    """Check that `filename` has an allowed extension and the bytes do not claim another format.

    Returns the format the extension promises. Raises UploadRejected: unsupported-format for an
    extension the field does not take, invalid-file for an empty file, format-mismatch when the bytes
    are recognisably another format. Bytes that are no known format go on to the reader, whose
    message (bad magic, parse error) is the more precise one.
    """
    extension = _extension(filename)
    if extension not in allowed:
        expected = " or ".join(sorted(allowed))
        raise UploadRejected(
            UNSUPPORTED_FORMAT,
            f"'{field}' takes {expected} files",
            [FieldError(field, f"{filename!r} is not a {expected} file", filename)],
        )
    promised = allowed[extension]
    size = path.stat().st_size
    if size == 0:
        raise UploadRejected(INVALID_FILE, "an uploaded file is empty", [FieldError(field, "the file is empty", filename, "byte 0")])
    actual = sniff_format(path)
    if actual is not None and actual != promised:
        raise UploadRejected(
            FORMAT_MISMATCH,
            "a file's content is not the format its name says",
            [FieldError(field, f"named {extension} but the content is {FORMAT_NAMES[actual]}", filename, "byte 0")],
        )
    return promised


def _clean(message: str, path: Path, filename: str) -> str:
    """A reader's message with the staging path replaced by the name the client uploaded."""
    return message.replace(str(path), filename)


_BYTE = re.compile(r"\bbyte (\d+)")


def _where_from_message(message: str, path: Path) -> str | None:
    line = re.search(re.escape(str(path)) + r":(\d+):", message)
    if line:
        return f"line {line.group(1)}"
    byte = _BYTE.search(message)
    return f"byte {byte.group(1)}" if byte else None


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
        return _where_from_message(message, path)  # a .gltf JSON document: the reader names the place
    if len(header) < 12:
        return f"byte {size}"
    _magic, version, length = struct.unpack("<4sII", header)
    if version != 2:
        return "byte 4"
    if length != size:
        return "byte 8"
    return _where_from_message(message, path)


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
        message = _clean(str(error), path, filename)
        raise UploadRejected(INVALID_FILE, f"the character is not a usable glTF: {message}", [FieldError(field, message, filename, _glb_where(path, str(error)))]) from None
    positions = np.asarray(character.positions)
    if positions.size == 0 or len(character.faces) == 0:
        raise UploadRejected(INVALID_FILE, "the character has no triangles", [FieldError(field, "no skinned triangles", filename)])
    if not np.isfinite(positions).all():
        raise UploadRejected(INVALID_FILE, "the character has NaN or infinite positions", [FieldError(field, "NaN or infinite vertex position", filename)])
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
            chunk = handle.read(_COPY_CHUNK)
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
        errors.append(FieldError(cache_field, _clean(str(error), cache_path, cache_name), cache_name, _pc2_where(cache_path)))
    try:
        mesh = read_obj(mesh_path)
    except ValueError as error:
        errors.append(FieldError(mesh_field, _clean(str(error), mesh_path, mesh_name), mesh_name, _where_from_message(str(error), mesh_path)))
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


# ------------------------------------------------------------------------------- OBJ sequence zips


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _unsafe_entry_reason(info: zipfile.ZipInfo) -> str | None:
    name = info.filename
    if not name:  # (zipfile's own ZipInfo.is_dir() fails with IndexError on one)
        return "has an empty name"
    if "\\" in name:
        return "uses a backslash (a Windows path that could escape the folder)"
    if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        return "is an absolute path"
    if any(part == ".." for part in name.split("/")):
        return "escapes the archive's folder with '..'"
    mode = info.external_attr >> 16
    if stat.S_ISLNK(mode):
        return "is a symbolic link"
    return None


# What reading a damaged or unusual entry raises: a bad CRC or header (BadZipFile), a broken deflate
# stream (zlib.error), data cut short (EOFError), zip features zipfile lacks (NotImplementedError:
# patched data, strong encryption) and offsets outside the file (OSError EINVAL from seek). Only the
# reads are guarded: an OSError writing the extracted frame is the server's disk, not the upload.
_ENTRY_READ_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, OSError)


def _corrupt_entry(info: zipfile.ZipInfo, error: BaseException, zip_name: str, field: str) -> UploadRejected:
    return UploadRejected(INVALID_FILE, "an archive entry is corrupt", [FieldError(field, f"cannot be decompressed: {error}", zip_name, f"entry {info.filename}")])


def _extract_bounded(archive: zipfile.ZipFile, info: zipfile.ZipInfo, destination: Path, budget: int, zip_name: str, field: str) -> int:
    """Copy one entry to `destination`, refusing to write more than its declared size or `budget`."""
    written = 0
    limit = min(info.file_size, budget)
    try:
        source = archive.open(info)
    except _ENTRY_READ_ERRORS as error:
        raise _corrupt_entry(info, error, zip_name, field) from None
    with source, open(destination, "wb") as target:
        while True:
            try:
                chunk = source.read(_COPY_CHUNK)
            except _ENTRY_READ_ERRORS as error:
                raise _corrupt_entry(info, error, zip_name, field) from None
            if not chunk:
                break
            written += len(chunk)
            if written > limit:
                reason = "expands beyond its declared size" if written > info.file_size else "expands beyond the upload's limit"
                raise UploadRejected(UNSAFE_ARCHIVE, "the archive expands too far (zip bomb guard)", [FieldError(field, f"entry {reason}", zip_name, f"entry {info.filename}")])
            target.write(chunk)
    return written


def convert_obj_sequence(
    zip_path: Path, zip_name: str, limits: ZipLimits, cache_out: Writable, mesh_out: Writable,
    cycle_frames: int | None = None, field: str = "sequence",
) -> dict[str, Any]:
    """Turn a zip of OBJ frames (one topology) into a PC2 cache and its rest mesh.

    The OBJ files (any folder, natural name order: frame2 before frame10) are the frames; every one must
    have the first one's positions count and faces. Writes the PC2 bytes to `cache_out` and the first
    OBJ's bytes to `mesh_out`. Refuses entries that escape the folder (absolute, '..', backslashes,
    symbolic links), encrypted entries, more than `limits.max_entries` entries, and archives that expand
    beyond `limits.max_uncompressed_bytes` or whose entries compress by more than `limits.max_ratio`.
    Returns check_cloth's dict plus {"frames_from": "obj-sequence"}.
    """
    from crowdbake.formats.obj import read_obj
    from crowdbake.formats.pc2 import pc2_header

    expect_format(zip_path, zip_name, field, SEQUENCE_EXTENSIONS)
    try:
        archive = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError, NotImplementedError) as error:  # NotImplementedError: a zip version zipfile cannot read
        raise UploadRejected(INVALID_FILE, "the archive is not a readable zip", [FieldError(field, f"not a readable zip: {error}", zip_name)]) from None
    with archive:
        infos = archive.infolist()
        if len(infos) > limits.max_entries:
            raise UploadRejected(UNSAFE_ARCHIVE, "the archive has too many entries", [FieldError(field, f"{len(infos)} entries, at most {limits.max_entries} are accepted", zip_name)])
        unsafe = [FieldError(field, f"entry {reason}", zip_name, f"entry {info.filename}") for info in infos if (reason := _unsafe_entry_reason(info))]
        if unsafe:
            raise UploadRejected(UNSAFE_ARCHIVE, "archive entries escape their folder", unsafe)
        declared = sum(info.file_size for info in infos)
        if declared > limits.max_uncompressed_bytes:
            raise UploadRejected(UNSAFE_ARCHIVE, "the archive expands too far (zip bomb guard)", [FieldError(field, f"entries expand to {declared} bytes, at most {limits.max_uncompressed_bytes} are accepted", zip_name)])
        for info in infos:
            if info.file_size > ZIP_RATIO_MIN_BYTES and info.file_size > limits.max_ratio * max(info.compress_size, 1):
                raise UploadRejected(
                    UNSAFE_ARCHIVE, "the archive expands too far (zip bomb guard)",
                    [FieldError(field, f"entry compresses {info.file_size / max(info.compress_size, 1):.0f}:1, at most {limits.max_ratio:.0f}:1 is accepted", zip_name, f"entry {info.filename}")],
                )
            if info.flag_bits & 0x1:
                raise UploadRejected(INVALID_FILE, "encrypted archive entries cannot be read", [FieldError(field, "entry is encrypted", zip_name, f"entry {info.filename}")])
            if info.compress_type not in READABLE_ZIP_METHODS:
                # zipfile raises NotImplementedError for these when the entry is opened (a 500 before).
                raise UploadRejected(INVALID_FILE, "an archive entry uses a compression method that cannot be read",
                                     [FieldError(field, f"entry uses compression method {info.compress_type}; use deflate or store", zip_name, f"entry {info.filename}")])
        # After the per-entry checks (they name the entry): the whole archive's ratio, from the central
        # directory before anything inflates. Many entries just under ZIP_RATIO_MIN_BYTES each (200 x 1 MiB
        # of "v 0 0 0" in 324 KB) pass every per-entry check, yet together expand 600:1.
        archive_bytes = max(zip_path.stat().st_size, 1)
        if declared > ZIP_RATIO_MIN_BYTES and declared > limits.max_ratio * archive_bytes:
            raise UploadRejected(
                UNSAFE_ARCHIVE, "the archive expands too far (zip bomb guard)",
                [FieldError(field, f"the archive expands {declared / archive_bytes:.0f}:1 ({declared} bytes from {archive_bytes}), at most {limits.max_ratio:.0f}:1 is accepted", zip_name)],
            )
        frames = sorted(
            (info for info in infos if not info.is_dir() and info.filename.lower().endswith(".obj")
             and not info.filename.startswith("__MACOSX/") and not PurePosixPath(info.filename).name.startswith("._")),
            key=lambda info: _natural_key(info.filename),
        )
        needed = min_cloth_frames(cycle_frames)
        if len(frames) < needed:
            raise UploadRejected(INVALID_FILE, "too few frames for two cycles", [FieldError(field, f"too few frames for two cycles: {len(frames)} OBJ files, two cycles need {needed}", zip_name)])

        budget = limits.max_uncompressed_bytes
        reference_faces = None
        reference_count = 0
        first_bytes = b""
        scratch = Path(tempfile.mkdtemp(prefix="obj-sequence-"))
        # Frames stream into the PC2 one at a time (header first: the frame count is the entry count),
        # so memory holds one frame, never the whole sequence.
        try:
            for index, info in enumerate(frames):
                frame_path = scratch / f"frame{index}.obj"
                budget -= _extract_bounded(archive, info, frame_path, budget, zip_name, field)
                try:
                    mesh = read_obj(frame_path)
                except ValueError as error:
                    message = _clean(str(error), frame_path, info.filename)
                    where = _where_from_message(str(error), frame_path)
                    raise UploadRejected(INVALID_FILE, f"a frame of the sequence does not parse: {message}", [FieldError(field, message, info.filename, where)]) from None
                corners = mesh.source_index[mesh.faces.astype(np.int64)]  # faces in OBJ position indices
                if reference_faces is None:
                    if len(corners) == 0:
                        raise UploadRejected(INVALID_FILE, "the first frame has no faces", [FieldError(field, "the mesh has no faces", info.filename)])
                    reference_faces, reference_count = corners, mesh.position_count
                    first_bytes = frame_path.read_bytes()
                    cache_out.write(pc2_header(reference_count, len(frames)))
                elif mesh.position_count != reference_count or not np.array_equal(corners, reference_faces):
                    what = (f"{mesh.position_count} vertex positions, the first frame has {reference_count}"
                            if mesh.position_count != reference_count else "faces differ from the first frame's")
                    raise UploadRejected(INVALID_FILE, "the sequence's topology changes", [FieldError(field, f"topology changes: {what}", info.filename)])
                cache_out.write(np.ascontiguousarray(mesh.positions[: mesh.position_count], dtype="<f4").tobytes())
                del mesh
                frame_path.unlink()
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
    mesh_out.write(first_bytes)
    return {
        "frame_count": len(frames),
        "vertex_count": reference_count,
        "triangle_count": int(len(reference_faces)),
        "start_frame": 0.0,
        "sample_rate": 1.0,
        "frames_from": "obj-sequence",
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
        message = _clean(str(error), path, filename) or type(error).__name__
        where = f"byte {size}" if "truncated" in message.lower() else None
        raise UploadRejected(INVALID_FILE, f"the PNG does not decode: {message}", [FieldError(field, message, filename, where)]) from None
    return {"width": int(width), "height": int(height), "mode": mode}
