"""Where published bundles live: a local folder, or an S3-compatible bucket (crowdbake.storage.s3_bundles).

Publishing is one template for every backend (`BundleStore.publish`): verify the packed folder, refuse
or accept an existing version, write every file where no reader looks yet, then make the version
visible in one atomic step (a folder rename here, a conditional put of the manifest in S3). A process
that dies between two files leaves no visible version, and a published version is never overwritten:
the same bytes again are a no-op, other bytes raise BundleConflict. A local publish killed midway leaves
its hidden staging folder (`staging_folders` finds them; the sweeper removes those no live bake owns).

Readers ask for the manifest (`manifest`), a file or a byte range of it (`open_file`), a local path
(`materialize`, through a cache when the store is remote), or a presigned URL (`presigned_url`, None
when the store has no such thing and the caller must stream `open_file`).
"""
from __future__ import annotations

import io
import os
import re
import shutil
import tempfile
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, BinaryIO, Iterator

from crowdbake.files import fsync_path
from crowdbake.formats.bundle import check_path, verify_bundle
from crowdbake.storage.bundles import LATEST, BundleConflict, PublishedManifest, bundle_dir, read_manifest

MANIFEST = "manifest.json"
# The API's name and version rules (crowdbake.api.schemas); both become path segments and object keys.
_NAME = re.compile(r"^[a-z0-9][a-z0-9._-]{0,63}$")
_VERSION = re.compile(r"^[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}$")
# A local publish stages in `<root>/<name>/.<version>.<8 random characters of tempfile.mkdtemp>`.
_STAGING = re.compile(r"^\.(?P<version>.+)\.[a-z0-9_]{8}$")


def check_name_version(name: str, version: str) -> None:
    """Raise ValueError unless name/version are a bundle name and a concrete version (not 'latest')."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"not a bundle name: {name!r}")
    if not isinstance(version, str) or not _VERSION.match(version) or version == LATEST:
        raise ValueError(f"not a bundle version: {version!r}")


class BundleStore(ABC):
    """Published bundles by name and version; subclasses supply staging, the commit and reading."""

    def publish(self, source: Path, name: str, version: str) -> PublishedManifest:
        """Publish the packed bundle folder `source` as name/version and return its manifest.

        The folder is verified first (crowdbake.formats.bundle.verify_bundle: FormatError). Only the
        manifest and the files it lists are published. Raises BundleConflict when name/version is
        already published, or is published concurrently, with another manifest.
        """
        check_name_version(name, version)
        source = Path(source)
        bundle = verify_bundle(source)
        data = (source / MANIFEST).read_bytes()
        existing = self._published_or_none(name, version)
        if existing is not None:
            return self._same_or_conflict(existing, data, name, version)
        staging = self._begin(name, version, data)
        try:
            for entry in bundle.manifest["files"]:
                self._stage_file(staging, entry, source / entry["path"])
            committed = self._commit(staging, data)
        except BaseException:
            self._abort(staging)
            raise
        published = self.manifest(name, version)
        if not committed:  # another publisher made the version visible first
            return self._same_or_conflict(published, data, name, version)
        return published

    def _published_or_none(self, name: str, version: str) -> PublishedManifest | None:
        try:
            return self.manifest(name, version)
        except FileNotFoundError:
            return None

    @staticmethod
    def _same_or_conflict(published: PublishedManifest, data: bytes, name: str, version: str) -> PublishedManifest:
        if published.data != data:
            raise BundleConflict(f"{name}/{version} is already published with other bytes")
        return published

    def exists(self, name: str, version: str) -> bool:
        return self._published_or_none(name, version) is not None

    # ----------------------------------------------------------------------------- for subclasses

    @abstractmethod
    def _begin(self, name: str, version: str, manifest_data: bytes) -> Any:
        """Start a publish; returns a handle for _stage_file, _commit and _abort."""

    @abstractmethod
    def _stage_file(self, staging: Any, entry: dict[str, Any], source: Path) -> None:
        """Copy one listed file (a manifest entry: path, size, sha256, media_type) where no reader looks."""

    @abstractmethod
    def _commit(self, staging: Any, manifest_data: bytes) -> bool:
        """Make the staged version visible in one atomic step; False if another publisher already did."""

    @abstractmethod
    def _abort(self, staging: Any) -> None:
        """Best-effort removal of what a failed publish staged (a killed process never gets here)."""

    # ------------------------------------------------------------------------------------ reading

    @abstractmethod
    def manifest(self, name: str, version: str) -> PublishedManifest:
        """The published manifest of name/version; FileNotFoundError if it is not published."""

    @abstractmethod
    def open_file(self, name: str, version: str, path: str, byte_range: tuple[int, int] | None = None) -> BinaryIO:
        """A published file (MANIFEST or a listed path) as a readable binary stream.

        byte_range: (start, end) with end exclusive, within the file's size; None reads all of it.
        FileNotFoundError if the version or the path is not published.
        """

    @abstractmethod
    def materialize(self, name: str, version: str, path: str) -> Path:
        """A local read-only file with the bytes of a published file (the folder itself, or a cache)."""

    def local_path(self, name: str, version: str, path: str) -> Path | None:
        """The published file's own path when the store is a local folder, else None."""
        return None

    def presigned_url(self, name: str, version: str, path: str, expires_s: int, media_type: str | None = None,
                      cache_control: str | None = None) -> str | None:
        """A URL that GETs the published file without credentials for `expires_s` seconds (with these
        response headers), or None when the store cannot make one: then stream `open_file`."""
        return None

    def _entry(self, name: str, version: str, path: str) -> dict[str, Any] | None:
        """The manifest entry of `path` (None for the manifest itself); FileNotFoundError if unlisted."""
        check_name_version(name, version)
        if path == MANIFEST:
            return None
        check_path(path)
        entry = self.manifest(name, version).files.get(path)
        if entry is None:
            raise FileNotFoundError(f"{name}/{version} has no file {path!r}")
        return entry


class _Slice(io.RawIOBase):
    """At most `length` bytes of an open file from where it stands (a byte range of a local file)."""

    def __init__(self, handle: BinaryIO, length: int):
        self._handle, self._left = handle, length

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        if self._left <= 0:
            return 0
        view = memoryview(buffer)[: self._left]
        count = self._handle.readinto(view)
        self._left -= count
        return count

    def close(self) -> None:
        self._handle.close()
        super().close()


def open_range(path: Path, byte_range: tuple[int, int] | None) -> BinaryIO:
    """`path` opened for reading, limited to byte_range (start, end exclusive) when given."""
    handle = open(path, "rb")
    if byte_range is None:
        return handle
    start, end = byte_range
    handle.seek(start)
    return io.BufferedReader(_Slice(handle, max(0, end - start)))


def staging_folders(root: Path) -> Iterator[tuple[Path, str, str]]:
    """(folder, name, version) of every staging folder of a publish under a local store's `root`: the
    publish is under way, or was cut short (SIGKILL, a lost machine) and left it."""
    root = Path(root)
    if not root.is_dir():
        return
    for name_folder in sorted(root.iterdir()):
        if not name_folder.is_dir() or not _NAME.match(name_folder.name):
            continue
        for folder in sorted(name_folder.iterdir()):
            match = _STAGING.match(folder.name)
            if match and _VERSION.match(match["version"]) and folder.is_dir() and not folder.is_symlink():
                yield folder, name_folder.name, match["version"]


class LocalBundleStore(BundleStore):
    """Bundles as folders `<root>/<name>/<version>/`: staged in a hidden folder beside, then renamed."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def folder(self, name: str, version: str) -> Path:
        check_name_version(name, version)
        return bundle_dir(self.root, name, version)

    def _begin(self, name: str, version: str, manifest_data: bytes) -> tuple[Path, Path]:
        target = self.folder(name, version)
        target.parent.mkdir(parents=True, exist_ok=True)
        # A dot name is never a version (check_name_version), so readers never see the staging folder.
        return Path(tempfile.mkdtemp(prefix=f".{version}.", dir=target.parent)), target  # see _STAGING

    def _stage_file(self, staging: tuple[Path, Path], entry: dict[str, Any], source: Path) -> None:
        destination = staging[0] / entry["path"]
        destination.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, destination)
        fsync_path(destination)

    def _commit(self, staging: tuple[Path, Path], manifest_data: bytes) -> bool:
        folder, target = staging
        with open(folder / MANIFEST, "wb") as handle:
            handle.write(manifest_data)
            handle.flush()
            os.fsync(handle.fileno())
        for sub in sorted({path.parent for path in folder.rglob("*")}, key=lambda path: len(path.parts), reverse=True):
            fsync_path(sub)
        try:
            os.rename(folder, target)  # fails if target exists (non-empty): published folders are never replaced
        except OSError:
            if not target.exists():
                raise
            shutil.rmtree(folder, ignore_errors=True)
            return False
        fsync_path(target.parent)
        return True

    def _abort(self, staging: tuple[Path, Path]) -> None:
        shutil.rmtree(staging[0], ignore_errors=True)

    def manifest(self, name: str, version: str) -> PublishedManifest:
        check_name_version(name, version)
        return read_manifest(self.root, name, version)

    def local_path(self, name: str, version: str, path: str) -> Path:
        self._entry(name, version, path)
        return self.folder(name, version) / path

    def open_file(self, name: str, version: str, path: str, byte_range: tuple[int, int] | None = None) -> BinaryIO:
        return open_range(self.local_path(name, version, path), byte_range)

    def materialize(self, name: str, version: str, path: str) -> Path:
        return self.local_path(name, version, path)
