"""Stage 6, publish: work/bundle → bundles_root/<name>/<version>, atomically, once; then, unless the
bake's `export` parameter is false, its engine export beside it (crowdbake.storage.exports).

The same bytes already published: nothing to do. Other bytes under that version: VersionConflict
(a published bundle never changes).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crowdbake.errors import StageOrderError, VersionConflict
from crowdbake.formats.bundle import BundleFile, verify_bundle, write_bundle
from crowdbake.stages.validate import load_job
from crowdbake.stages.workdir import WorkDir, read_json, write_json_atomic
from crowdbake.storage.exports import (
    ExportStore, LocalExportStore, build_export_beside_home, check_export_home, commit_export, discard_export, export_home,
)


def same_tree(a: Path, b: Path) -> bool:
    """True when the two folders hold the same files with the same bytes."""

    def listing(root: Path) -> dict[str, Path]:
        return {p.relative_to(root).as_posix(): p for p in root.rglob("*") if p.is_file()}

    left, right = listing(a), listing(b)
    if set(left) != set(right):
        return False
    return all(left[name].stat().st_size == right[name].stat().st_size and left[name].read_bytes() == right[name].read_bytes() for name in left)


def stage_publish(work: Path, bundles_root: Path) -> Path:
    """Publish work/bundle atomically as bundles_root/<name>/<version> and return that path."""
    job = load_job(work)
    source = WorkDir(work).bundle
    if not (source / "manifest.json").is_file():
        raise StageOrderError(f"{work}: stage 'pack' has not run yet")
    bundle = verify_bundle(source)
    target = Path(bundles_root) / job.name / job.version
    if target.exists():
        if same_tree(source, target):
            return target
        raise VersionConflict(f"{job.name}/{job.version} is already published with other bytes")
    files = [BundleFile(entry["path"], (source / entry["path"]).read_bytes(), entry["role"], entry["media_type"]) for entry in bundle.manifest["files"]]
    try:
        write_bundle(target, bundle.manifest, files)
    except (FileExistsError, OSError):
        # Another publisher got there first (the final rename found the folder): same bytes or a conflict.
        if target.exists() and same_tree(source, target):
            return target
        if target.exists():
            raise VersionConflict(f"{job.name}/{job.version} was published concurrently with other bytes") from None
        raise
    if not same_tree(source, target):
        raise VersionConflict(f"{target} differs from the packed bundle after publishing")
    return target


def _bundle_to_export(work: Path) -> Path | None:
    """work/bundle when the bake's `export` parameter is true, else None; StageOrderError before the pack stage."""
    if not load_job(work).bake_params.export:
        return None
    bundle = WorkDir(work).bundle
    if not (bundle / "manifest.json").is_file():
        raise StageOrderError(f"{work}: stage 'pack' has not run yet")
    return bundle


def check_export_before_publishing(work: Path, bundles_root: Path) -> None:
    """ExportConflict, before anything is published, when the export home of work/bundle in the exports
    folder of `bundles_root` holds the export of another bundle under the same name and version
    (crowdbake.storage.exports.check_export_home); nothing when the bake makes no export."""
    bundle = _bundle_to_export(work)
    if bundle is not None:
        check_export_home(bundle, Path(bundles_root))


def stage_export(work: Path, exports: ExportStore | Path) -> bool:
    """Publish the engine export of the bundle the bake packed (once; a second call keeps the first)
    into `exports` (a store, or a bundles folder for the exports beside it). False when the bake's
    `export` parameter is false. The export is made from work/bundle, the bytes `stage_publish` published,
    with the impostor layers the pack stage already converted for it (pack.prepared_export_layers)."""
    from crowdbake.stages.pack import prepared_export_layers

    bundle = _bundle_to_export(work)
    if bundle is None:
        return False
    store = exports if isinstance(exports, ExportStore) else LocalExportStore(Path(exports))
    store.publish(bundle, prepared=prepared_export_layers(work))
    return True


def stage_export_ahead(work: Path, bundles_root: Path) -> Path | None:
    """The engine export of work/bundle built beside its home in the exports folder of `bundles_root`, not
    yet in place: the bake runner builds it while stage_publish publishes, and puts it in place
    (crowdbake.storage.exports.commit_export) only once that succeeded, or discards it. The impostor layers
    the pack stage already converted for it (pack.prepared_export_layers) are not converted again. None when
    the bake's `export` parameter is false or the export is already there."""
    from crowdbake.stages.pack import prepared_export_layers

    bundle = _bundle_to_export(work)
    if bundle is None:
        return None
    return build_export_beside_home(bundle, Path(bundles_root), prepared=prepared_export_layers(work))


STAGING_FILE = "export/staging.json"  # where the export node leaves the folder it built, for commit_export


@dataclass
class LocalDestination:
    """Publishing into a bundles folder: the bundle under out_root/<name>/<version>, its engine export
    built beside its home while the bundle is published, and put in place only once that succeeded."""

    out_root: Path

    def publish(self, work: Path) -> dict[str, Any]:
        check_export_before_publishing(work, self.out_root)
        return {"path": str(stage_publish(work, self.out_root))}

    def export(self, work: Path) -> str | None:
        staging = stage_export_ahead(work, self.out_root)
        write_json_atomic(Path(work) / STAGING_FILE, {"path": None if staging is None else str(staging)})
        return None if staging is None else str(staging)

    def commit_export(self, work: Path) -> str | None:
        staging = self._staging(work)
        if staging is None:
            return None
        manifest = read_json(Path(work) / "bundle" / "manifest.json")
        home = commit_export(staging, export_home(self.out_root, manifest["name"], manifest["version"]))
        (Path(work) / STAGING_FILE).unlink(missing_ok=True)
        return str(home)

    def abort(self, work: Path) -> None:
        """Remove an export built for a bundle that was not published."""
        discard_export(self._staging(work))
        (Path(work) / STAGING_FILE).unlink(missing_ok=True)

    @staticmethod
    def _staging(work: Path) -> Path | None:
        try:
            path = read_json(Path(work) / STAGING_FILE)["path"]
        except (OSError, ValueError, KeyError):
            return None
        return Path(path) if path else None
