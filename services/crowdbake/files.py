"""Two file-system steps every layer takes (stages, storage, formats, the client): a file's sha256, and an
fsync of a file or folder. Standard library only, and importing nothing of crowdbake, so any module may use it."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

READ_CHUNK = 1 << 20  # bytes read at a time: files may be larger than memory


def sha256_file(path: Path) -> str:
    """The sha256 (lowercase hex) of the file at `path`, read in READ_CHUNK pieces."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(READ_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def fsync_path(path: Path) -> None:
    """Flush a file, or a folder's entries (the names of what was created or renamed in it), to disk.
    Opened read-only: a folder cannot be opened for writing, and fsync needs no write access on Linux."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
