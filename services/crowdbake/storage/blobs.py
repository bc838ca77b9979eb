"""A content-addressed blob store: every upload is kept once, under its sha256.

Uploads are streamed into a staging file while they are hashed (`BlobStore.incoming()`), validated
there, and only then committed under their digest; a rejected upload is discarded and leaves nothing
behind. Committing bytes that are already stored is a no-op (deduplication).

`LocalBlobStore` keeps blobs in a folder (`<root>/sha256/ab/cd/abcd...`). `crowdbake.storage.s3.S3BlobStore`
implements the same abstract methods on an S3-compatible bucket: staging stays on local disk because
validation reads files, `commit` uploads the staged file under its digest in parts with a conditional
put, `open` streams it back, and `materialize` goes through a local read cache on the workers.
`crowdbake.storage.store.open_store(settings)` picks one, with its bundle store.
"""
from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import tempfile
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import BinaryIO, Iterator

from crowdbake.files import fsync_path

_DIGEST = re.compile(r"^[0-9a-f]{64}$")
STAGING_DIRNAME = ".incoming"
STAGING_PREFIX = "upload-"
# An upload in flight writes its staging file continuously; one untouched for a day was left by a
# process that died mid-upload (SIGKILL, power loss) and will never be committed or discarded.
STALE_STAGING_S = 24 * 3600

logger = logging.getLogger(__name__)


def check_digest(digest: str) -> str:
    """Return `digest` if it is 64 lowercase hex digits, else raise ValueError (it becomes a path)."""
    if not isinstance(digest, str) or not _DIGEST.match(digest):
        raise ValueError(f"not a sha256 digest: {digest!r}")
    return digest


class IncomingBlob:
    """A staging file being written: hashes and counts every chunk as it goes to disk."""

    def __init__(self, staging_dir: Path):
        staging_dir.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=STAGING_PREFIX, dir=staging_dir)
        self.path = Path(name)
        self._handle = os.fdopen(fd, "wb")
        self._hash = hashlib.sha256()
        self.size = 0
        self._sha256: str | None = None
        self._released = False  # committed or discarded: the staging name may belong to another upload now

    def write(self, chunk: bytes) -> None:
        self._hash.update(chunk)
        self._handle.write(chunk)
        self.size += len(chunk)

    def close(self) -> None:
        """Finish writing (flush and fsync); the digest is known from here on."""
        if not self._handle.closed:
            self._handle.flush()
            os.fsync(self._handle.fileno())
            self._handle.close()
            self._sha256 = self._hash.hexdigest()

    @property
    def finished(self) -> bool:
        return self._sha256 is not None

    @property
    def sha256(self) -> str:
        if self._sha256 is None:
            raise RuntimeError("close() the incoming blob before asking for its digest")
        return self._sha256

    def discard(self) -> None:
        """Forget the staged bytes (safe to call twice, and after commit)."""
        if not self._handle.closed:
            self._handle.close()
        if not self._released:
            self._released = True
            self.path.unlink(missing_ok=True)

    def mark_released(self) -> None:
        """Called by a store that moved the staging file away (commit)."""
        self._released = True

    @classmethod
    def from_bytes(cls, staging_dir: Path, data: bytes) -> "IncomingBlob":
        blob = cls(staging_dir)
        blob.write(data)
        blob.close()
        return blob


class BlobStore(ABC):
    """Where uploads live, by sha256. Staging is always a local folder (validation reads files)."""

    def __init__(self, staging_dir: Path):
        self.staging_dir = Path(staging_dir)
        self.staging_dir.mkdir(parents=True, exist_ok=True)

    def incoming(self) -> IncomingBlob:
        """A new staging file to stream an upload into."""
        return IncomingBlob(self.staging_dir)

    def sweep_staging(self, older_than_s: float = STALE_STAGING_S) -> int:
        """Delete staging files not written for `older_than_s` seconds (left by a process killed in the
        middle of an upload); returns how many. Younger ones may belong to a live upload and stay."""
        cutoff = time.time() - older_than_s
        swept = 0
        for path in self.staging_dir.glob(f"{STAGING_PREFIX}*"):
            try:
                if path.stat().st_mtime < cutoff:
                    path.unlink()
                    swept += 1
            except FileNotFoundError:  # committed or discarded meanwhile
                pass
        return swept

    @abstractmethod
    def commit(self, blob: IncomingBlob) -> bool:
        """Store a closed staging file under its digest; True if the bytes were new. The staging file is gone after."""

    @abstractmethod
    def exists(self, digest: str) -> bool: ...

    @abstractmethod
    def size(self, digest: str) -> int: ...

    @abstractmethod
    def open(self, digest: str) -> BinaryIO:
        """The blob's bytes as a readable binary file; FileNotFoundError if absent."""

    @abstractmethod
    def materialize(self, digest: str, destination: Path) -> Path:
        """Make `destination` a local read-only file with the blob's bytes (for the workers)."""

    @abstractmethod
    def delete(self, digest: str) -> None: ...

    @abstractmethod
    def digests(self) -> Iterator[str]:
        """Every stored digest."""

    def presigned_url(self, digest: str, expires_s: int) -> str | None:
        """A URL anyone holding it may GET the blob from for `expires_s` seconds, or None when the
        store cannot make one (a local folder): then serve `open(digest)` instead."""
        return None


def link_read_only(source: Path, destination: Path) -> Path:
    """Make `destination` a read-only file with `source`'s bytes: a hard link where the file system
    allows (the source is read-only, so sharing the inode is safe), else a copy."""
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    if destination.exists():
        destination.unlink()
    try:
        os.link(source, destination)
    except OSError:
        shutil.copy2(source, destination)  # keeps the modification time, as a link would
        os.chmod(destination, 0o444)
    return destination


class LocalBlobStore(BlobStore):
    """Blobs in a local folder: <root>/sha256/<2 hex>/<2 hex>/<digest>, written once, read-only."""

    def __init__(self, root: Path):
        self.root = Path(root)
        super().__init__(self.root / STAGING_DIRNAME)

    def path(self, digest: str) -> Path:
        digest = check_digest(digest)
        return self.root / "sha256" / digest[:2] / digest[2:4] / digest

    def commit(self, blob: IncomingBlob) -> bool:
        blob.close()
        target = self.path(blob.sha256)
        if target.is_file():
            blob.discard()  # same bytes already stored: deduplicated
            return False
        target.parent.mkdir(parents=True, exist_ok=True)
        os.chmod(blob.path, 0o444)
        # os.replace is atomic on one file system; a concurrent commit of the same digest writes the same bytes.
        os.replace(blob.path, target)
        blob.mark_released()
        fsync_path(target.parent)
        return True

    def exists(self, digest: str) -> bool:
        return self.path(digest).is_file()

    def size(self, digest: str) -> int:
        return self.path(digest).stat().st_size

    def open(self, digest: str) -> BinaryIO:
        return open(self.path(digest), "rb")

    def materialize(self, digest: str, destination: Path) -> Path:
        source = self.path(digest)
        if not source.is_file():
            raise FileNotFoundError(f"blob {digest} is not in the store {self.root}")
        return link_read_only(source, destination)

    def delete(self, digest: str) -> None:
        self.path(digest).unlink(missing_ok=True)

    def digests(self) -> Iterator[str]:
        base = self.root / "sha256"
        if not base.is_dir():
            return
        for path in sorted(base.glob("*/*/*")):
            if _DIGEST.match(path.name):
                yield path.name


def make_blob_store(blob_dir: Path) -> BlobStore:
    """A local-folder blob store with staging files that dead processes left behind swept away."""
    return with_staging_swept(LocalBlobStore(blob_dir))


def with_staging_swept(store: BlobStore) -> BlobStore:
    """`store`, after deleting the staging files that dead processes left behind (BlobStore.sweep_staging)."""
    swept = store.sweep_staging()
    if swept:
        logger.warning("removed %d staging files older than %d s left by interrupted uploads in %s", swept, STALE_STAGING_S, store.staging_dir)
    return store
