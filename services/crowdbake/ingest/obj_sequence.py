"""OBJ sequence zips: a zip of OBJ frames turned into a PC2 cloth cache and its rest mesh, safely.

The archive is checked from its central directory before anything inflates (entry count, paths that
escape the folder, encryption, compression methods, declared sizes and ratios: the zip-bomb guard),
then each frame is extracted within a byte budget, parsed with crowdbake.formats.obj and streamed into
the PC2. Problems raise crowdbake.ingest.uploads.UploadRejected naming the form field and the entry.
"""
from __future__ import annotations

import re
import shutil
import stat
import tempfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Protocol

import numpy as np

from crowdbake.ingest.rejections import (
    COPY_CHUNK, INVALID_FILE, SEQUENCE_EXTENSIONS, UNSAFE_ARCHIVE, FieldError, UploadRejected, clean_message, expect_format,
    where_from_message,
)
from crowdbake.params import min_cloth_frames

# Entries smaller than this may compress extremely well for innocent reasons (a run of zeros); the
# ratio check of the zip-bomb guard applies above it.
ZIP_RATIO_MIN_BYTES = 1 << 20
# Compression methods Python's zipfile reads (store, deflate, bzip2, lzma); others raise NotImplementedError.
READABLE_ZIP_METHODS = frozenset({zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA})


@dataclass(frozen=True)
class ZipLimits:
    max_entries: int
    max_uncompressed_bytes: int
    max_ratio: float


class Writable(Protocol):
    def write(self, chunk: bytes) -> Any: ...


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
                chunk = source.read(COPY_CHUNK)
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
                # zipfile raises NotImplementedError for these only when the entry is opened: refuse them by name here.
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
                    message = clean_message(str(error), frame_path, info.filename)
                    where = where_from_message(str(error), frame_path)
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
