"""Published bundles in an S3-compatible bucket.

Keys, for a bundle whose manifest bytes hash to M:

    <prefix>bundles/<name>/<version>/M/<path>        every file the manifest lists
    <prefix>bundles/<name>/<version>/manifest.json   the manifest: written last, and only if absent

The manifest is the version pointer: readers find a version through it and its digest names the
prefix of the files, so a version is visible only once every file is in place, and a publisher that
dies between two files leaves objects under a prefix nobody points to (`unreferenced` lists them).
Publishers of different bytes write under different prefixes and race only for the manifest, whose
put is conditional (`If-None-Match: *`): the winner's version is final, the loser gets BundleConflict.
No object is ever overwritten, so a published version cannot change under a reader.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, BinaryIO, Iterator

from crowdbake.storage.bundle_store import MANIFEST, BundleStore, check_name_version
from crowdbake.storage.bundles import PublishedManifest, parse_manifest
from crowdbake.storage.cache import ReadCache
from crowdbake.storage.s3 import RevalidatedObjects, get_stream, is_taken, presigned_get, put_file_once

MANIFEST_MEDIA_TYPE = "application/json"
MANIFEST_CACHE_SIZE = 256  # parsed manifests kept per process (each revalidated by its ETag)


class S3BundleStore(BundleStore):
    """Bundles under `<prefix>bundles/` of a bucket; `cache` holds downloads for `materialize`."""

    def __init__(self, client, bucket: str, prefix: str, cache: ReadCache, part_bytes: int):
        self.client, self.bucket, self.prefix, self.cache, self.part_bytes = client, bucket, prefix, cache, int(part_bytes)
        self._manifests = RevalidatedObjects(client, bucket, MANIFEST_CACHE_SIZE)

    def version_prefix(self, name: str, version: str) -> str:
        check_name_version(name, version)
        return f"{self.prefix}bundles/{name}/{version}/"

    def manifest_key(self, name: str, version: str) -> str:
        return self.version_prefix(name, version) + MANIFEST

    def file_key(self, name: str, version: str, manifest_sha256: str, path: str) -> str:
        return f"{self.version_prefix(name, version)}{manifest_sha256}/{path}"

    # ---------------------------------------------------------------------------------- publishing

    def _begin(self, name: str, version: str, manifest_data: bytes) -> dict[str, Any]:
        return {"name": name, "version": version, "sha256": hashlib.sha256(manifest_data).hexdigest()}

    def _stage_file(self, staging: dict[str, Any], entry: dict[str, Any], source: Path) -> None:
        key = self.file_key(staging["name"], staging["version"], staging["sha256"], entry["path"])
        # False means a crashed or concurrent publish of these same manifest bytes put it already;
        # the key names the manifest digest, which names this file's sha256, so its bytes are these.
        put_file_once(self.client, self.bucket, key, source, self.part_bytes, entry["media_type"], {"sha256": entry["sha256"]})

    def _commit(self, staging: dict[str, Any], manifest_data: bytes) -> bool:
        try:
            self.client.put_object(
                Bucket=self.bucket, Key=self.manifest_key(staging["name"], staging["version"]), Body=manifest_data,
                ContentType=MANIFEST_MEDIA_TYPE, Metadata={"sha256": staging["sha256"]}, IfNoneMatch="*",
            )
        except Exception as error:
            if is_taken(error):
                return False
            raise
        return True

    def _abort(self, staging: dict[str, Any]) -> None:
        """Nothing to remove eagerly: a same-bytes publisher may be using the prefix right now."""

    def unreferenced(self, name: str, version: str) -> Iterator[str]:
        """Keys under name/version that its manifest does not point to (left by failed publishes);
        deleting them is safe once no publish of this version is running."""
        try:
            current = self.manifest(name, version).sha256
        except FileNotFoundError:
            current = None
        root = self.version_prefix(name, version)
        for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=root):
            for item in page.get("Contents", []):
                rest = item["Key"][len(root):]
                if rest != MANIFEST and rest.split("/", 1)[0] != current:
                    yield item["Key"]

    # ------------------------------------------------------------------------------------- reading

    def manifest(self, name: str, version: str) -> PublishedManifest:
        return self._manifests.get(self.manifest_key(name, version), parse_manifest,
                                   f"{name}/{version} is not published in s3://{self.bucket}/{self.prefix}")

    def _key_of(self, name: str, version: str, path: str) -> str:
        entry = self._entry(name, version, path)
        if entry is None:
            return self.manifest_key(name, version)
        return self.file_key(name, version, self.manifest(name, version).sha256, path)

    def open_file(self, name: str, version: str, path: str, byte_range: tuple[int, int] | None = None) -> BinaryIO:
        return get_stream(self.client, self.bucket, self._key_of(name, version, path), byte_range)

    def materialize(self, name: str, version: str, path: str) -> Path:
        entry = self._entry(name, version, path)
        digest = entry["sha256"] if entry else self.manifest(name, version).sha256
        # Named by its sha256 in the cache (no suffix): readers of bundle files go by the manifest's media type.
        return self.cache.get(digest, lambda: self.open_file(name, version, path))

    def presigned_url(self, name: str, version: str, path: str, expires_s: int, media_type: str | None = None,
                      cache_control: str | None = None) -> str:
        return presigned_get(self.client, self.bucket, self._key_of(name, version, path), expires_s, media_type, cache_control)
