"""Download a published bundle: manifest.json, then every file it lists, each size and sha256 checked
while it streams, into DEST/NAME/VERSION (a temporary folder renamed at the end, so a folder there is
always a whole bundle).

With the full crowdbake package installed the bundle is also checked as the runtime would
(crowdbake.formats.bundle.verify_bundle: schema, binary headers, cross-checks); the client alone checks
what guards against corrupt or tampered transfers, the sizes and hashes, and says which it did.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path, PurePosixPath
from typing import Callable

import httpx

from crowdbake.client.http import BACKOFF_FIRST_S, ClientError, Exit, Server

CHUNK = 1 << 20


def safe_relative_path(path: str) -> PurePosixPath:
    """A manifest path as a relative POSIX path that stays inside the bundle folder; ValueError otherwise."""
    pure = PurePosixPath(path)
    if not path or "\\" in path or "\0" in path or pure.is_absolute() or any(part in ("", ".", "..") for part in path.split("/")):
        raise ValueError(f"unsafe path {path!r} in the manifest")
    return pure


def fetch_file(server: Server, url: str, target: Path, size: int | None, sha256: str | None, what: str) -> None:
    """Stream `url` into `target`; ClientError (BAKE_FAILED) when its size or sha256 differ from the
    manifest's. A connection lost in the middle starts the file again, within the server's retry time."""
    target.parent.mkdir(parents=True, exist_ok=True)
    deadline = server.clock() + server.retry_for
    while True:
        digest, written = hashlib.sha256(), 0
        response = server.request("GET", url, f"downloading {what}", stream=True)
        try:
            with open(target, "wb") as handle:
                for chunk in response.iter_bytes(CHUNK):
                    digest.update(chunk)
                    handle.write(chunk)
                    written += len(chunk)
            break
        except httpx.TransportError as error:
            if server.clock() > deadline:
                raise ClientError(f"downloading {what}: {type(error).__name__}: {error}", Exit.UNREACHABLE) from None
            server.say(f"downloading {what}: {type(error).__name__}: {error}; starting the file again")
            server.sleep(BACKOFF_FIRST_S)
        finally:
            response.close()
    if size is not None and written != size:
        raise ClientError(f"downloading {what}: {written} bytes, the manifest says {size}", Exit.BAKE_FAILED)
    if sha256 is not None and digest.hexdigest() != sha256:
        raise ClientError(f"downloading {what}: sha256 {digest.hexdigest()} differs from the manifest's {sha256}", Exit.BAKE_FAILED)


def full_verifier() -> Callable[[Path], object] | None:
    """crowdbake.formats.bundle.verify_bundle when the full package is installed, else None."""
    try:
        from crowdbake.formats.bundle import verify_bundle
    except ImportError:  # the client alone: numpy and the format readers are not installed
        return None
    return verify_bundle


def download_bundle(server: Server, name: str, version: str, out_root: Path, on_file: Callable[[str], None] = lambda path: None) -> tuple[Path, str]:
    """Download name/version into out_root/name/version; returns (folder, what was verified).

    An identical bundle already there (same manifest bytes) is kept; another one is refused."""
    destination = out_root / name / version
    destination.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{version}.", dir=destination.parent))
    try:
        base = f"/v1/bundles/{name}/{version}"
        fetch_file(server, f"{base}/manifest.json", staging / "manifest.json", None, None, "manifest.json")
        manifest = json.loads((staging / "manifest.json").read_bytes())
        entries = manifest.get("files", [])
        for entry in entries:
            try:
                path = safe_relative_path(entry["path"])
            except ValueError as error:
                raise ClientError(f"the manifest of {name}/{version}: {error}", Exit.BAKE_FAILED) from None
            fetch_file(server, f"{base}/files/{path}", staging / path, entry.get("size"), entry["sha256"], str(path))
            on_file(str(path))
        verified = f"size and sha256 of {len(entries)} files"
        verify = full_verifier()
        if verify is not None:
            try:
                verify(staging)
            except Exception as error:  # FormatError and friends: the bundle is not what the runtime accepts
                raise ClientError(f"the downloaded bundle does not verify: {error}", Exit.BAKE_FAILED) from None
            verified += ", schema and binary formats"
        if destination.exists():
            if (destination / "manifest.json").is_file() and (destination / "manifest.json").read_bytes() == (staging / "manifest.json").read_bytes():
                shutil.rmtree(staging)
                return destination, verified
            raise ClientError(f"{destination} already holds another bundle; remove it or choose another --download folder", Exit.USAGE)
        os.rename(staging, destination)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return destination, verified


def download_export(server: Server, name: str, version: str, out_root: Path) -> Path:
    """Fetch name/version's engine export (GET /v1/bundles/{name}/{version}/export.zip, docs/export.md) and
    unpack its NAME-VERSION folder into out_root/name/version; returns the folder. Every member's CRC is checked and its path
    must stay inside the folder; an identical export already there is kept, another one refused."""
    import zipfile

    bundle = server.request("GET", f"/v1/bundles/{name}/{version}", f"reading bundle {name}/{version}").json()
    if not bundle.get("export_url"):
        raise ClientError(f"{name}/{version} was published without an engine export (params export false)", Exit.BAKE_FAILED)
    destination = out_root / name / version
    destination.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{version}.export.", dir=destination.parent))
    try:
        archive = staging / "export.zip"
        fetch_file(server, f"/v1/bundles/{name}/{version}/export.zip", archive, None, None, "export.zip")
        unpacked = staging / "export"
        try:
            with zipfile.ZipFile(archive) as zipped:
                broken = zipped.testzip()
                if broken is not None:
                    raise ClientError(f"the export of {name}/{version}: {broken} fails its CRC check", Exit.BAKE_FAILED)
                top = f"{name}-{version}/"  # the zip holds one folder, NAME-VERSION (api/routes/exports.py)
                for member in zipped.infolist():
                    if member.is_dir():
                        continue
                    target = unpacked / safe_relative_path(member.filename.removeprefix(top))
                    target.parent.mkdir(parents=True, exist_ok=True)
                    with zipped.open(member) as source, open(target, "wb") as handle:
                        shutil.copyfileobj(source, handle)
        except (zipfile.BadZipFile, ValueError) as error:
            raise ClientError(f"the export of {name}/{version} is not a usable zip: {error}", Exit.BAKE_FAILED) from None
        if not (unpacked / "export.json").is_file():
            raise ClientError(f"the export of {name}/{version} has no export.json", Exit.BAKE_FAILED)
        if destination.exists():
            if (destination / "export.json").is_file() and (destination / "export.json").read_bytes() == (unpacked / "export.json").read_bytes():
                return destination
            raise ClientError(f"{destination} already holds another export; remove it or choose another --export-out folder", Exit.USAGE)
        os.rename(unpacked, destination)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return destination
