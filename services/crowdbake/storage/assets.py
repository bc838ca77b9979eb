"""Asset records: content-addressed, so uploading the same bytes again returns the existing asset."""
from __future__ import annotations

import hashlib
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from crowdbake.storage.blobs import BlobStore, IncomingBlob
from crowdbake.storage.models import Asset
from crowdbake.storage.records import new_id


def stored_file(blob: IncomingBlob, filename: str, media_type: str) -> dict[str, Any]:
    return {"sha256": blob.sha256, "size": blob.size, "filename": filename, "media_type": media_type}


def asset_digest(files: dict[str, dict[str, Any]]) -> str:
    """An asset's identity: its one file's sha256, or a sha256 over "role:sha256" lines of its files."""
    if set(files) == {"file"}:
        return files["file"]["sha256"]
    return hashlib.sha256("\n".join(f"{role}:{files[role]['sha256']}" for role in sorted(files)).encode()).hexdigest()


def find_asset(session: Session, kind: str, digest: str, created_by: str | None) -> Asset | None:
    """The asset of this content that `created_by` uploaded (assets are unique per owner)."""
    return session.scalars(select(Asset).where(Asset.kind == kind, Asset.digest == digest, _owner_is(created_by))).first()


def _owner_is(created_by: str | None):
    return Asset.created_by.is_(None) if created_by is None else Asset.created_by == created_by


def store_asset(
    session: Session, blobs: BlobStore, kind: str, staged: dict[str, tuple[IncomingBlob, str, str]],
    info: dict[str, Any], created_by: str | None,
) -> tuple[Asset, bool]:
    """Commit the staged blobs and record the asset, or return the existing asset with this content.

    staged: role -> (blob, filename, media type). Returns (asset, created). Commits the session.
    """
    files = {role: stored_file(blob, filename, media_type) for role, (blob, filename, media_type) in staged.items()}
    digest = asset_digest(files)
    existing = find_asset(session, kind, digest, created_by)
    if existing is None:
        for blob, _, _ in staged.values():
            blobs.commit(blob)
        primary = files.get("file") or files["cache"]
        asset = Asset(
            id=new_id("as"), kind=kind, digest=digest, filename=primary["filename"],
            size=sum(entry["size"] for entry in files.values()), files=files, info=info, created_by=created_by,
        )
        session.add(asset)
        try:
            session.commit()
            return asset, True
        except IntegrityError:  # the same content arrived concurrently; theirs was recorded first
            session.rollback()
            existing = session.scalars(select(Asset).where(Asset.kind == kind, Asset.digest == digest, _owner_is(created_by))).one()
    for blob, _, _ in staged.values():
        blob.discard()
    return existing, False
