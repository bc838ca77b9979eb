"""A bake's work folder carried between machines through the blob store.

The stages hand each other files in the bake's work folder (crowdbake.stages.workdir): validate's
inputs/ and record, cycle/looped.pc2 and cycle.json, poses/*.cbpc and textures.npz, one impostor part
per fan-out task, pack's bundle/. On one machine, or with the data folder on a shared file system,
the next stage finds them where the last one wrote them. With private data folders (an object store,
`CROWDBAKE_STORE=s3`) a stage may run on another machine, so:

- `push` uploads what a stage wrote (every file under the given folders or files of the work folder)
  as blobs, each under its sha256 (bytes already stored are not sent again), then a listing
  {path: {sha256, size}} as one more blob, and returns the listing's digest for the database;
- `pull` makes a work folder hold every file of a listing: files already there with the listed
  digest are kept, others are fetched (through the worker's verified read cache) and put in place
  atomically. The copies are ordinary writable files: a rerun of a stage may rewrite them.

Paths in a listing are POSIX paths relative to the work folder; one that is absolute or climbs out
is refused (ValueError), so a listing cannot make a worker write outside its work folder.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path, PurePosixPath
from typing import Iterable

from crowdbake.files import sha256_file
from crowdbake.storage.blobs import BlobStore, check_digest

LISTING_VERSION = 1
CHUNK = 1 << 20


def check_relative(path: str) -> str:
    """`path` if it is a plain relative POSIX path inside the work folder, else ValueError."""
    pure = PurePosixPath(path)
    if not path or pure.is_absolute() or any(part in ("", ".", "..") for part in pure.parts) or "\\" in path:
        raise ValueError(f"not a path inside a work folder: {path!r}")
    return path


def output_files(work: Path, roots: Iterable[str]) -> list[str]:
    """The files under `roots` (folders or files, relative to `work`) as sorted relative POSIX paths.

    Hidden names (a leading dot: atomic-write temporaries, staging) are skipped; a missing root is
    simply empty, so a stage that wrote nothing there pushes nothing."""
    work = Path(work)
    found: set[str] = set()
    for root in roots:
        top = work / check_relative(root)
        candidates = [top] if top.is_file() else (sorted(top.rglob("*")) if top.is_dir() else [])
        for path in candidates:
            relative = path.relative_to(work)
            if path.is_file() and not any(part.startswith(".") for part in relative.parts):
                found.add(relative.as_posix())
    return sorted(found)


def _store_file(blobs: BlobStore, path: Path) -> tuple[str, int]:
    incoming = blobs.incoming()
    try:
        with open(path, "rb") as source:
            while chunk := source.read(CHUNK):
                incoming.write(chunk)
        incoming.close()
        blobs.commit(incoming)
        return incoming.sha256, incoming.size
    finally:
        incoming.discard()


def push(blobs: BlobStore, work: Path, roots: Iterable[str]) -> str:
    """Store every file under `roots` of `work` and a listing of them; returns the listing's sha256."""
    files = {}
    for relative in output_files(work, roots):
        digest, size = _store_file(blobs, Path(work) / relative)
        files[relative] = {"sha256": digest, "size": size}
    listing = json.dumps({"listing_version": LISTING_VERSION, "files": files}, sort_keys=True, separators=(",", ":")).encode()
    incoming = blobs.incoming()
    try:
        incoming.write(listing)
        incoming.close()
        blobs.commit(incoming)
        return incoming.sha256
    finally:
        incoming.discard()


def read_listing(blobs: BlobStore, digest: str) -> dict[str, dict]:
    """The files {path: {sha256, size}} of the listing blob `digest` (ValueError if it is not one)."""
    with blobs.open(check_digest(digest)) as handle:
        document = json.loads(handle.read())
    if not isinstance(document, dict) or document.get("listing_version") != LISTING_VERSION or not isinstance(document.get("files"), dict):
        raise ValueError(f"blob {digest} is not a work-folder listing of version {LISTING_VERSION}")
    files = document["files"]
    for path, entry in files.items():
        check_relative(path)
        check_digest(entry["sha256"])
    return files


def pull(blobs: BlobStore, work: Path, digest: str) -> int:
    """Make `work` hold every file of the listing `digest`; returns how many files were fetched."""
    work = Path(work)
    fetched = 0
    for relative, entry in sorted(read_listing(blobs, digest).items()):
        target = work / relative
        if target.is_file() and target.stat().st_size == entry["size"] and sha256_file(target) == entry["sha256"]:
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
        os.close(handle)
        try:
            # materialize links (or copies) the store's read-only bytes; the work folder gets its own
            # writable copy, so a stage rewriting the file can never touch the cache or the store.
            linked = blobs.materialize(entry["sha256"], Path(temporary + ".blob"))
            try:
                shutil.copyfile(linked, temporary)
            finally:
                linked.unlink(missing_ok=True)
            os.replace(temporary, target)
        except BaseException:
            Path(temporary).unlink(missing_ok=True)
            raise
        fetched += 1
    return fetched
