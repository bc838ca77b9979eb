"""Published exports: the engine-ready files of a published bundle (crowdbake.export), beside it.

    <bundles_dir>/../exports/<name>/<version>/
        export/       what `crowdbake export` writes (export.json, character_lod<k>.glb, textures/, ...)
        export.zip    the same files in one zip, under <name>-<version>/
        index.json    size, sha256 and media type of every file of export/ and of export.zip

A bundle never changes once published, so neither does its export: the folder is written once, built
in a staging folder of its own and renamed into place, and a second publisher finding it there keeps
it. The REST API serves these files with the sha256 of index.json as their ETag.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import zipfile
from functools import lru_cache
from pathlib import Path
from typing import Any

EXPORTS_FOLDER = "exports"
FILES_FOLDER = "export"
ZIP_NAME = "export.zip"
INDEX_NAME = "index.json"
INDEX_FORMAT = "crowdbake-export-index"
# Every zip entry gets zip's epoch, so an export's zip is the same bytes every time.
ZIP_DATE = (1980, 1, 1, 0, 0, 0)
MEDIA_TYPES = {
    ".json": "application/json", ".glb": "model/gltf-binary", ".ktx2": "image/ktx2", ".png": "image/png",
    ".glsl": "text/plain; charset=utf-8", ".hlsl": "text/plain; charset=utf-8", ".zip": "application/zip",
}


def exports_root(bundles_dir: Path) -> Path:
    """The exports folder: a sibling of the bundles folder (data/bundles -> data/exports)."""
    return Path(bundles_dir).parent / EXPORTS_FOLDER


def export_home(bundles_dir: Path, name: str, version: str) -> Path:
    return exports_root(bundles_dir) / name / version


def media_type(path: str) -> str:
    return MEDIA_TYPES.get(Path(path).suffix, "application/octet-stream")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as source:
        while chunk := source.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def write_export_zip(files_dir: Path, paths: list[str], prefix: str, target: Path) -> None:
    """The files `paths` (relative to files_dir) into the zip `target` under prefix/, deflated (the glTF
    buffers and VATs shrink; BC blocks a little), with fixed dates so the bytes are reproducible."""
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in paths:
            info = zipfile.ZipInfo(f"{prefix}/{path}", date_time=ZIP_DATE)
            info.external_attr = 0o644 << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, (files_dir / path).read_bytes())


def publish_export(bundle_folder: Path, bundles_dir: Path, ktx2_mode: str = "bc") -> Path:
    """Export the published bundle at `bundle_folder` (= bundles_dir/<name>/<version>) once, into its
    export home; returns that folder. An export already there is kept (the bundle cannot have changed)."""
    from crowdbake.export import export_bundle

    manifest = json.loads((Path(bundle_folder) / "manifest.json").read_text())
    name, version = manifest["name"], manifest["version"]
    home = export_home(bundles_dir, name, version)
    if (home / INDEX_NAME).is_file():
        return home
    home.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{version}.", suffix=".partial", dir=home.parent))
    try:
        summary = export_bundle(bundle_folder, staging / FILES_FOLDER, ktx2_mode)
        paths = sorted(summary.files)
        write_export_zip(staging / FILES_FOLDER, paths, f"{name}-{version}", staging / ZIP_NAME)
        index = {
            "format": INDEX_FORMAT,
            "bundle": {"name": name, "version": version, "manifest_sha256": _sha256(Path(bundle_folder) / "manifest.json")},
            "ktx2": ktx2_mode,
            "files": {path: {"size": summary.files[path], "sha256": _sha256(staging / FILES_FOLDER / path), "media_type": media_type(path)} for path in paths},
            "zip": {"size": (staging / ZIP_NAME).stat().st_size, "sha256": _sha256(staging / ZIP_NAME), "media_type": MEDIA_TYPES[".zip"]},
        }
        (staging / INDEX_NAME).write_text(json.dumps(index, indent=2) + "\n")
        try:
            staging.rename(home)
        except OSError:
            if (home / INDEX_NAME).is_file():  # another publisher renamed the same export into place first
                shutil.rmtree(staging, ignore_errors=True)
                return home
            raise
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return home


def read_export_index(bundles_dir: Path, name: str, version: str) -> dict[str, Any]:
    """The index of a published export (cached by mtime). FileNotFoundError when there is none."""
    path = export_home(bundles_dir, name, version) / INDEX_NAME
    return _load_index(str(path), path.stat().st_mtime_ns)


@lru_cache(maxsize=256)
def _load_index(path: str, _mtime_ns: int) -> dict[str, Any]:
    return json.loads(Path(path).read_text())
