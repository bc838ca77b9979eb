"""A local read-through cache of content-addressed files, for processes whose store is remote.

A worker that bakes from an object store downloads each input once per machine: files are kept under
`<root>/sha256/ab/cd/<digest>`, read-only, and a download is checked against its digest while it
streams, so a cached file is always the bytes its name promises. When the cache grows past its
budget the least recently used files go (by access time, refreshed on every hit); a file already
hard-linked into a work folder keeps its bytes there, because eviction only unlinks the cache's name.
"""
from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

from crowdbake.storage.blobs import check_digest

logger = logging.getLogger(__name__)

CHUNK = 1 << 20  # bytes per read while copying a download into the cache


class DigestMismatch(IOError):
    """A download's bytes do not hash to the digest they were stored under."""


class ReadCache:
    """Files by sha256 under `root`, filled by a caller-supplied download, bounded by `max_bytes`."""

    def __init__(self, root: Path, max_bytes: int):
        self.root = Path(root)
        self.max_bytes = int(max_bytes)
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, digest: str) -> Path:
        digest = check_digest(digest)
        return self.root / "sha256" / digest[:2] / digest[2:4] / digest

    def get(self, digest: str, download: Callable[[], BinaryIO]) -> Path:
        """The cached file of `digest`; on a miss, stream `download()` into it, verifying the digest.

        download: opens the remote bytes (FileNotFoundError when they do not exist); called at most once.
        Raises DigestMismatch (and caches nothing) when the bytes hash to something else.
        """
        target = self.path(digest)
        if target.is_file():
            os.utime(target)  # a hit makes the file recently used (noatime mounts never update atime)
            return target
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=".download-", dir=target.parent)
        hasher = hashlib.sha256()
        try:
            with os.fdopen(fd, "wb") as out, download() as source:
                while chunk := source.read(CHUNK):
                    hasher.update(chunk)
                    out.write(chunk)
            if hasher.hexdigest() != digest:
                raise DigestMismatch(f"downloaded bytes hash to {hasher.hexdigest()}, not {digest}")
            os.chmod(name, 0o444)
            os.replace(name, target)  # a concurrent download of the same digest wrote the same bytes
        except BaseException:
            Path(name).unlink(missing_ok=True)
            raise
        self.evict()
        return target

    def size(self) -> int:
        return sum(path.stat().st_size for path in self._files())

    def evict(self) -> int:
        """Delete least recently used files until the cache fits `max_bytes`; returns how many went."""
        entries = []
        for path in self._files():
            try:
                stat = path.stat()
            except FileNotFoundError:  # evicted by another process meanwhile
                continue
            entries.append((max(stat.st_atime, stat.st_mtime), stat.st_size, path))
        total = sum(size for _, size, _ in entries)
        removed = 0
        for _, size, path in sorted(entries, key=lambda entry: entry[0]):
            if total <= self.max_bytes:
                break
            path.unlink(missing_ok=True)
            total -= size
            removed += 1
        if removed:
            logger.info("evicted %d files from the cache %s", removed, self.root)
        return removed

    def _files(self):
        base = self.root / "sha256"
        return (path for path in base.glob("*/*/*") if not path.name.startswith(".")) if base.is_dir() else iter(())
