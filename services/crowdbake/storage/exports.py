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

import json
import queue
import shutil
import tempfile
import threading
import zipfile
from functools import lru_cache
from pathlib import Path
from typing import Any

from crowdbake.files import sha256_file

EXPORTS_FOLDER = "exports"
FILES_FOLDER = "export"
ZIP_NAME = "export.zip"
INDEX_NAME = "index.json"
INDEX_FORMAT = "crowdbake-export-index"
# Every zip entry gets zip's epoch, so an export's zip is the same bytes every time.
ZIP_DATE = (1980, 1, 1, 0, 0, 0)
# zlib levels of the zip's entries: files already compressed (zstd-supercompressed KTX2, PNG, JPEG) gain little
# past level 1; the .glb files' quantized buffers and the JSON and text deflate further at 6 (on the demo's
# robot: character_lod0.glb 4.45 MB at 1, 4.20 MB at 6 in 0.5 s, 4.17 MB at 9 in 1.9 s).
ZIP_LEVEL = 1
ZIP_LEVEL_UNCOMPRESSED = 6
COMPRESSED_SUFFIXES = (".ktx2", ".png", ".jpg")


def zip_level(path: str) -> int:
    """The zlib level of the zip entry of the export file at `path`."""
    return ZIP_LEVEL if path.endswith(COMPRESSED_SUFFIXES) else ZIP_LEVEL_UNCOMPRESSED
MEDIA_TYPES = {
    ".json": "application/json", ".glb": "model/gltf-binary", ".ktx2": "image/ktx2", ".png": "image/png", ".jpg": "image/jpeg",
    ".gdshader": "text/plain; charset=utf-8", ".md": "text/markdown; charset=utf-8",
    ".glsl": "text/plain; charset=utf-8", ".hlsl": "text/plain; charset=utf-8", ".zip": "application/zip",
    ".gd": "text/plain; charset=utf-8", ".cs": "text/plain; charset=utf-8", ".py": "text/plain; charset=utf-8",
}


def exports_root(bundles_dir: Path) -> Path:
    """The exports folder: a sibling of the bundles folder (data/bundles -> data/exports)."""
    return Path(bundles_dir).parent / EXPORTS_FOLDER


def export_home(bundles_dir: Path, name: str, version: str) -> Path:
    return exports_root(bundles_dir) / name / version


def media_type(path: str) -> str:
    return MEDIA_TYPES.get(Path(path).suffix, "application/octet-stream")


def _zip_entry(prefix: str, path: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(f"{prefix}/{path}", date_time=ZIP_DATE)
    info.external_attr = 0o644 << 16
    info.compress_type = zipfile.ZIP_DEFLATED
    return info


class ZipAsWritten:
    """The export's zip, deflated in a thread of its own while the export is still being written: add(path,
    bytes) queues a file as soon as it is written (crowdbake.export.export_bundle's on_write, always in the
    same order, so the zip is the same bytes every time), close() waits for the zip and re-raises its error.
    zlib lets go of the interpreter lock while it deflates, so the zip (0.6 s of the sample's 1.6 s export)
    runs on a second core beside the export's own work.

    Entries lie under `prefix`/, deflated at zip_level: level 1 for the KTX2 files and images, already
    compressed (deflating them at 6 took the sample's export 1.7 s against 0.7 s, for a few kilobytes), level
    6 for the .glb files and the text."""

    def __init__(self, target: Path, prefix: str):
        self._target, self._prefix = Path(target), prefix
        self._queue: queue.Queue[tuple[str, bytes] | None] = queue.Queue()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="export-zip", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            with zipfile.ZipFile(self._target, "w", zipfile.ZIP_DEFLATED, compresslevel=ZIP_LEVEL) as archive:
                while (item := self._queue.get()) is not None:
                    archive.writestr(_zip_entry(self._prefix, item[0]), item[1], compresslevel=zip_level(item[0]))
        except BaseException as error:  # noqa: BLE001 - handed to close()
            self._error = error
            while self._queue.get() is not None:  # drain, so that add() never blocks on a dead thread
                pass

    def add(self, path: str, data: bytes) -> None:
        self._queue.put((path, data))

    def close(self) -> None:
        """Wait for the zip; re-raise its error."""
        self.finish()
        if self._error is not None:
            raise self._error

    def finish(self) -> None:
        """Wait for the zip, keeping quiet about its error (the caller has one of its own to raise)."""
        self._queue.put(None)
        self._thread.join()


def build_export(bundle_folder: Path, staging: Path, ktx2_mode: str = "bc", prepared=None) -> dict[str, Any]:
    """Write the export of the bundle at `bundle_folder` into the empty folder `staging` (export/,
    export.zip, index.json) and return the index. prepared: crowdbake.export.textures.PreparedLayers or None."""
    from crowdbake.export.writer import export_bundle
    from crowdbake.export.textures import NOTHING_PREPARED

    manifest = json.loads((Path(bundle_folder) / "manifest.json").read_text())
    name, version = manifest["name"], manifest["version"]
    # The zip is deflated as the files are written (entries in the order export_bundle writes them).
    zipper = ZipAsWritten(staging / ZIP_NAME, f"{name}-{version}")
    try:
        summary = export_bundle(bundle_folder, staging / FILES_FOLDER, ktx2_mode, NOTHING_PREPARED if prepared is None else prepared,
                                on_write=zipper.add)
    except BaseException:
        zipper.finish()
        raise
    zipper.close()
    paths = sorted(summary.files)
    index = {
        "format": INDEX_FORMAT,
        "bundle": {"name": name, "version": version, "manifest_sha256": sha256_file(Path(bundle_folder) / "manifest.json")},
        "ktx2": ktx2_mode,
        "files": {path: {"size": summary.files[path], "sha256": sha256_file(staging / FILES_FOLDER / path), "media_type": media_type(path)} for path in paths},
        "zip": {"size": (staging / ZIP_NAME).stat().st_size, "sha256": sha256_file(staging / ZIP_NAME), "media_type": MEDIA_TYPES[".zip"]},
    }
    (staging / INDEX_NAME).write_text(json.dumps(index, indent=2) + "\n")
    return index


def check_export_home(bundle_folder: Path, bundles_dir: Path) -> bool:
    """True when the export home of the bundle at `bundle_folder` holds its export already, False when it
    holds none. ExportConflict when it holds the export of other bytes under the same name and version:
    bundles folders with the same parent share one exports folder (the layout above), so a bake into a
    sibling folder must not keep, or serve, the other bundle's export."""
    manifest_path = Path(bundle_folder) / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    home = export_home(bundles_dir, manifest["name"], manifest["version"])
    try:
        index = json.loads((home / INDEX_NAME).read_text())
    except FileNotFoundError:
        return False
    refuse_other_export(str(home), manifest, index, sha256_file(manifest_path))
    return True


def refuse_other_export(where: str, manifest: dict[str, Any], index: dict[str, Any], manifest_sha256: str) -> None:
    """ExportConflict when the export `index` found at `where` was made from other manifest bytes than the
    bundle's (`manifest`, whose bytes hash to `manifest_sha256`)."""
    from crowdbake.errors import ExportConflict

    theirs = index.get("bundle", {}).get("manifest_sha256")
    if theirs != manifest_sha256:
        raise ExportConflict(
            f"{where} holds the export of other bytes published as {manifest['name']}/{manifest['version']} "
            f"(manifest sha256 {str(theirs)[:12]}…, this bundle's {manifest_sha256[:12]}…): bundles folders with the "
            "same parent share their exports folder; publish into a folder of its own, or without the export")


def publish_export(bundle_folder: Path, bundles_dir: Path, ktx2_mode: str = "bc", prepared=None) -> Path:
    """Export the published bundle at `bundle_folder` (= bundles_dir/<name>/<version>) once, into its
    export home; returns that folder. Its export already there is kept (the bundle cannot have changed);
    another bundle's is refused (check_export_home)."""
    staging = build_export_beside_home(bundle_folder, bundles_dir, ktx2_mode, prepared)
    manifest = json.loads((Path(bundle_folder) / "manifest.json").read_text())
    home = export_home(bundles_dir, manifest["name"], manifest["version"])
    return home if staging is None else commit_export(staging, home)


def build_export_beside_home(bundle_folder: Path, bundles_dir: Path, ktx2_mode: str = "bc", prepared=None) -> Path | None:
    """Build the export of the bundle at `bundle_folder` in a staging folder of its own beside its export
    home, and return it (commit_export puts it in place); None when the home already holds its export,
    ExportConflict when it holds another bundle's (check_export_home). Built from a bundle before it is
    published, it is committed only once publishing has succeeded. prepared: as in build_export."""
    if check_export_home(bundle_folder, bundles_dir):
        return None
    manifest = json.loads((Path(bundle_folder) / "manifest.json").read_text())
    name, version = manifest["name"], manifest["version"]
    home = export_home(bundles_dir, name, version)
    home.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{version}.", suffix=".partial", dir=home.parent))
    try:
        build_export(bundle_folder, staging, ktx2_mode, prepared)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return staging


def commit_export(staging: Path, home: Path) -> Path:
    """Rename a built export (build_export_beside_home) into its home, once: where another publisher renamed one
    there first, that one is kept and `staging` removed. Returns `home`."""
    try:
        staging.rename(home)
    except OSError:
        shutil.rmtree(staging, ignore_errors=True)
        if not (home / INDEX_NAME).is_file():
            raise
    return home


def discard_export(staging: Path | None) -> None:
    """Remove a built export that is not to be committed (publishing failed)."""
    if staging is not None:
        shutil.rmtree(staging, ignore_errors=True)


def read_export_index(bundles_dir: Path, name: str, version: str) -> dict[str, Any]:
    """The index of a published export (cached by mtime). FileNotFoundError when there is none."""
    path = export_home(bundles_dir, name, version) / INDEX_NAME
    return _load_index(str(path), path.stat().st_mtime_ns)


@lru_cache(maxsize=256)
def _load_index(path: str, _mtime_ns: int) -> dict[str, Any]:
    return json.loads(Path(path).read_text())


class ExportStore:
    """Where published exports live, for the publish stage and the REST routes; a file is named by its
    path in the export's home: `export/<path>` (a path of index.json's "files") or `export.zip`.
    LocalExportStore keeps them in folders beside the bundles, crowdbake.storage.s3_exports in the bucket."""

    def publish(self, bundle_folder: Path, ktx2_mode: str = "bc", prepared=None) -> None:
        """Export the bundle at `bundle_folder` once (a second publish keeps the first export). prepared:
        impostor layers already converted (crowdbake.export.textures.PreparedLayers) or None."""
        raise NotImplementedError

    def index(self, name: str, version: str) -> dict[str, Any]:
        """The export's index.json; FileNotFoundError when the bundle has no export."""
        raise NotImplementedError

    def has(self, name: str, version: str) -> bool:
        try:
            self.index(name, version)
        except FileNotFoundError:
            return False
        return True

    def local_path(self, name: str, version: str, path: str) -> Path | None:
        """The file in a local folder, or None when the store is remote (then open_file streams it)."""
        return None

    def open_file(self, name: str, version: str, path: str, byte_range: tuple[int, int] | None = None):
        raise NotImplementedError

    def presigned_url(self, name: str, version: str, path: str, expires_s: int, media_type: str | None = None,
                      cache_control: str | None = None) -> str | None:
        return None


class LocalExportStore(ExportStore):
    """Exports in `<bundles_dir>/../exports/<name>/<version>/` (the layout at the top of this module)."""

    def __init__(self, bundles_dir: Path):
        self.bundles_dir = Path(bundles_dir)

    def publish(self, bundle_folder: Path, ktx2_mode: str = "bc", prepared=None) -> None:
        publish_export(bundle_folder, self.bundles_dir, ktx2_mode, prepared)

    def index(self, name: str, version: str) -> dict[str, Any]:
        return read_export_index(self.bundles_dir, name, version)

    def has(self, name: str, version: str) -> bool:
        return (export_home(self.bundles_dir, name, version) / INDEX_NAME).is_file()

    def local_path(self, name: str, version: str, path: str) -> Path:
        return export_home(self.bundles_dir, name, version) / path
