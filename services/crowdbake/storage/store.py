"""One factory for the API and the workers: the blob store and the bundle store the settings name.

    stores = open_store(settings)
    stores.blobs     # crowdbake.storage.blobs.BlobStore (what make_blob_store returned)
    stores.bundles   # crowdbake.storage.bundle_store.BundleStore
    stores.exports   # crowdbake.storage.exports.ExportStore (engine exports of published bundles)

`CROWDBAKE_STORE=local` (the default) keeps both in folders (blob_dir, bundles_dir); `s3` keeps both in
one bucket (CROWDBAKE_S3_*), with a local read cache in cache_dir that blobs and bundle files share.
"""
from __future__ import annotations

from dataclasses import dataclass

from crowdbake.storage.blobs import BlobStore, make_blob_store, with_staging_swept
from crowdbake.storage.bundle_store import BundleStore, LocalBundleStore
from crowdbake.storage.exports import ExportStore, LocalExportStore


@dataclass(frozen=True)
class Stores:
    blobs: BlobStore
    bundles: BundleStore
    exports: ExportStore


def open_store(settings) -> Stores:
    """The stores of crowdbake.settings.Settings; staging files left by dead processes are swept."""
    if settings.store == "s3":
        from crowdbake.storage.s3 import S3BlobStore, s3_client
        from crowdbake.storage.s3_bundles import S3BundleStore
        from crowdbake.storage.s3_exports import S3ExportStore

        client = s3_client(settings)  # thread-safe; one per process is enough
        blobs = S3BlobStore(client, settings.s3_bucket, settings.s3_prefix, settings.cache_dir, settings.cache_max_bytes, settings.s3_part_bytes)
        # Exports are built in a folder of the work directory (same file system as the bake's), then uploaded.
        exports = S3ExportStore(client, settings.s3_bucket, settings.s3_prefix, settings.s3_part_bytes, settings.work_dir / ".exports")
        return Stores(with_staging_swept(blobs), S3BundleStore(client, settings.s3_bucket, settings.s3_prefix, blobs.cache, settings.s3_part_bytes), exports)
    return Stores(make_blob_store(settings.blob_dir), LocalBundleStore(settings.bundles_dir), LocalExportStore(settings.bundles_dir))
