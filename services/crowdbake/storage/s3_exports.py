"""Published exports in an S3-compatible bucket, with the guarantees of the bundles beside them.

Keys, for an export whose index.json bytes hash to X:

    <prefix>exports/<name>/<version>/X/export/<path>   every file index.json lists
    <prefix>exports/<name>/<version>/X/export.zip      the same files in one zip
    <prefix>exports/<name>/<version>/index.json        the index: written last, and only if absent

As for bundles (crowdbake.storage.s3_bundles), the index is the pointer: it is visible only once every
file is in place, its digest names the prefix of the files, its put is conditional, and no object is
ever overwritten. An export is made from a published bundle, which never changes, so a second
publisher finding an index there keeps it.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

from crowdbake.storage.bundle_store import check_name_version
from crowdbake.storage.exports import FILES_FOLDER, INDEX_NAME, ZIP_NAME, ExportStore, build_export, refuse_other_export
from crowdbake.storage.s3 import RevalidatedObjects, get_stream, is_taken, presigned_get, put_file_once

INDEX_CACHE_SIZE = 256  # parsed indexes kept per process (each revalidated by its ETag)


class S3ExportStore(ExportStore):
    """Exports under `<prefix>exports/` of a bucket; `scratch` is a local folder to build them in."""

    def __init__(self, client, bucket: str, prefix: str, part_bytes: int, scratch: Path):
        self.client, self.bucket, self.prefix, self.part_bytes, self.scratch = client, bucket, prefix, int(part_bytes), Path(scratch)
        self._indexes = RevalidatedObjects(client, bucket, INDEX_CACHE_SIZE)

    def home(self, name: str, version: str) -> str:
        check_name_version(name, version)
        return f"{self.prefix}exports/{name}/{version}/"

    def publish(self, bundle_folder: Path, ktx2_mode: str = "bc", prepared=None) -> None:
        manifest_data = (Path(bundle_folder) / "manifest.json").read_bytes()
        manifest = json.loads(manifest_data)
        name, version = manifest["name"], manifest["version"]
        try:
            index = self.index(name, version)
        except FileNotFoundError:
            index = None
        if index is not None:  # kept when it is this bundle's export; another bundle's is refused
            refuse_other_export(f"s3://{self.bucket}/{self.home(name, version)}", manifest, index, hashlib.sha256(manifest_data).hexdigest())
            return
        self.scratch.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".export-{version}.", dir=self.scratch))
        try:
            index = build_export(Path(bundle_folder), staging, ktx2_mode, prepared)
            index_data = (staging / INDEX_NAME).read_bytes()
            digest = hashlib.sha256(index_data).hexdigest()
            objects = [(f"{FILES_FOLDER}/{path}", entry) for path, entry in index["files"].items()] + [(ZIP_NAME, index["zip"])]
            for path, entry in objects:
                # False: a crashed or concurrent publish of the same index put it already (same bytes: the
                # prefix names the index, which names every file's sha256).
                put_file_once(self.client, self.bucket, self._file_key(name, version, digest, path), staging / path,
                              self.part_bytes, entry["media_type"], {"sha256": entry["sha256"]})
            try:
                self.client.put_object(Bucket=self.bucket, Key=self.home(name, version) + INDEX_NAME, Body=index_data,
                                       ContentType="application/json", Metadata={"sha256": digest}, IfNoneMatch="*")
            except Exception as error:
                if not is_taken(error):  # taken: another publisher's export of the same bundle is the one
                    raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    def _file_key(self, name: str, version: str, digest: str, path: str) -> str:
        return f"{self.home(name, version)}{digest}/{path}"

    def _index(self, name: str, version: str) -> tuple[str, dict[str, Any]]:
        """(digest of index.json, its content), revalidated by ETag; FileNotFoundError when absent."""
        return self._indexes.get(self.home(name, version) + INDEX_NAME, lambda data: (hashlib.sha256(data).hexdigest(), json.loads(data)),
                                 f"{name}/{version} has no export in s3://{self.bucket}/{self.prefix}")

    def index(self, name: str, version: str) -> dict[str, Any]:
        return self._index(name, version)[1]

    def _key_of(self, name: str, version: str, path: str) -> str:
        return self._file_key(name, version, self._index(name, version)[0], path)

    def open_file(self, name: str, version: str, path: str, byte_range: tuple[int, int] | None = None) -> BinaryIO:
        return get_stream(self.client, self.bucket, self._key_of(name, version, path), byte_range)

    def presigned_url(self, name: str, version: str, path: str, expires_s: int, media_type: str | None = None,
                      cache_control: str | None = None) -> str:
        return presigned_get(self.client, self.bucket, self._key_of(name, version, path), expires_s, media_type, cache_control)
