"""Published bundles: where they live, their manifests, and their records.

A bundle is published once, atomically, to `<bundles_dir>/<name>/<version>/` (by crowdbake.stages.publish,
with crowdbake.formats.bundle.write_bundle, or by a crowdbake.storage.bundle_store.BundleStore, which may
keep it in an object store) and then recorded here. Published folders never change, so a parsed manifest
can be cached for the life of the process.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from crowdbake.formats.bundle import check_path
from crowdbake.storage.models import Bundle

LATEST = "latest"  # the alias; refused as a real version name


class BundleConflict(Exception):
    """<name>/<version> is already published with other bytes."""


@dataclass(frozen=True)
class PublishedManifest:
    """A published manifest: its bytes and digest, and its files by path."""

    data: bytes
    sha256: str
    manifest: dict[str, Any]
    files: dict[str, dict[str, Any]]

    @property
    def total_size(self) -> int:
        return len(self.data) + sum(int(entry["size"]) for entry in self.files.values())


def bundle_dir(bundles_dir: Path, name: str, version: str) -> Path:
    return Path(bundles_dir) / name / version


def parse_manifest(data: bytes) -> PublishedManifest:
    """A published manifest from its bytes (FormatError on a file path the bundle rules forbid)."""
    manifest = json.loads(data)
    files = {}
    for entry in manifest.get("files", []):
        check_path(entry["path"])
        files[entry["path"]] = entry
    return PublishedManifest(data, hashlib.sha256(data).hexdigest(), manifest, files)


@lru_cache(maxsize=256)
def _load_manifest(folder: str, _mtime_ns: int) -> PublishedManifest:
    return parse_manifest((Path(folder) / "manifest.json").read_bytes())


def read_manifest(bundles_dir: Path, name: str, version: str) -> PublishedManifest:
    """The manifest of a published bundle (cached; keyed by its mtime too, in case of a re-publish
    after a deleted folder). FileNotFoundError if the folder has none."""
    folder = bundle_dir(bundles_dir, name, version)
    stat = (folder / "manifest.json").stat()
    return _load_manifest(str(folder), stat.st_mtime_ns)


def find_bundle(session: Session, name: str, version: str) -> Bundle | None:
    """The record of name/version; version 'latest' is the most recently published one."""
    if version == LATEST:
        return session.scalars(
            select(Bundle).where(Bundle.name == name).order_by(Bundle.published_at.desc(), Bundle.id.desc())
        ).first()
    return session.scalars(select(Bundle).where(Bundle.name == name, Bundle.version == version)).first()


def register_bundle(session: Session, bundles_dir, name: str, version: str, public: bool, bake_id: str | None) -> Bundle:
    """Record the published bundle name/version (idempotent: the same manifest again is a no-op).

    bundles_dir: the bundles folder (Path), or a crowdbake.storage.bundle_store.BundleStore.
    Raises BundleConflict when a record of name/version names another manifest.
    """
    if hasattr(bundles_dir, "manifest"):  # a BundleStore; checked by duck type to keep this module import-light
        published = bundles_dir.manifest(name, version)
    else:
        published = read_manifest(bundles_dir, name, version)
    existing = find_bundle(session, name, version)
    if existing is not None:
        if existing.manifest_sha256 != published.sha256:
            raise BundleConflict(f"{name}/{version} is already published with other bytes")
        return existing
    record = Bundle(
        name=name, version=version, manifest_sha256=published.sha256, size=published.total_size,
        file_count=len(published.files), public=public, bake_id=bake_id,
    )
    session.add(record)
    session.flush()
    return record
