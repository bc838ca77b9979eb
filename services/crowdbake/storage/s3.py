"""Blobs in an S3-compatible bucket (AWS S3, MinIO, Ceph RGW, ...), through boto3.

Keys: `<prefix>blobs/sha256/ab/cd/<digest>`. An upload is staged and hashed on local disk first
(crowdbake.storage.blobs.IncomingBlob: validation reads files), then `commit` sends it in parts of
`part_bytes` (multipart upload above one part), so one upload holds at most one part in memory. Every
write is a conditional put (`If-None-Match: *`): an object, once written, is never replaced, and a
concurrent commit of the same digest simply loses the race to identical bytes. Workers read through a
local cache (crowdbake.storage.cache.ReadCache) that checks each download against its digest.
"""
from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterator

from crowdbake.storage.blobs import STAGING_DIRNAME, BlobStore, IncomingBlob, check_digest, link_read_only
from crowdbake.storage.cache import ReadCache

logger = logging.getLogger(__name__)

# Error codes meaning "the object (or the bucket) is not there"; S3 answers a HEAD with a bare 404.
_MISSING = frozenset({"NoSuchKey", "NotFound", "404", "NoSuchBucket"})
# A conditional put found the key taken (412), or raced another conditional put of it (409).
_TAKEN = frozenset({"PreconditionFailed", "412", "ConditionalRequestConflict", "409"})


def error_code(error: Exception) -> str | None:
    """The S3 error code of a botocore ClientError, else None."""
    response = getattr(error, "response", None)
    return str(response.get("Error", {}).get("Code")) if isinstance(response, dict) else None


def is_missing(error: Exception) -> bool:
    return error_code(error) in _MISSING


def is_taken(error: Exception) -> bool:
    return error_code(error) in _TAKEN


def make_client(endpoint_url: str | None, region: str, access_key_id: str | None = None, secret_access_key: str | None = None,
                addressing_style: str = "path"):
    """A boto3 S3 client; credentials None means boto3's own chain (environment, instance role...)."""
    import boto3
    from botocore.config import Config

    config = Config(
        signature_version="s3v4",  # presigned URLs too; SigV2 is refused by newer stores
        s3={"addressing_style": addressing_style},
        retries={"max_attempts": 5, "mode": "standard"},
        # Checksums only where S3 requires them: the stores this targets differ in which trailing
        # checksums they accept, and every read is verified against its sha256 anyway.
        request_checksum_calculation="when_required",
        response_checksum_validation="when_required",
    )
    credentials = {}
    if access_key_id is not None:
        credentials = {"aws_access_key_id": access_key_id, "aws_secret_access_key": secret_access_key}
    return boto3.session.Session().client("s3", endpoint_url=endpoint_url, region_name=region, config=config, **credentials)


def s3_client(settings):
    """The client crowdbake.settings.Settings describes (CROWDBAKE_S3_*)."""
    secret = settings.s3_secret_access_key
    key_id = settings.s3_access_key_id
    return make_client(settings.s3_endpoint_url, settings.s3_region,
                       key_id.get_secret_value() if key_id else None, secret.get_secret_value() if secret else None,
                       settings.s3_addressing_style)


def ensure_bucket(client, bucket: str) -> None:
    """Create `bucket` unless it exists (development and tests; production buckets are provisioned)."""
    try:
        client.head_bucket(Bucket=bucket)
    except Exception as error:
        if not is_missing(error):
            raise
        client.create_bucket(Bucket=bucket)


def put_file_once(client, bucket: str, key: str, source: Path, part_bytes: int, content_type: str | None = None,
                  metadata: dict[str, str] | None = None) -> bool:
    """Upload `source` to `key` unless the key exists; True if this call created it.

    Files above `part_bytes` go as a multipart upload read one part at a time (memory: one part).
    The put (or the multipart completion) is conditional, so an existing object is never replaced.
    """
    extra: dict[str, Any] = {"Metadata": metadata or {}}
    if content_type:
        extra["ContentType"] = content_type
    size = Path(source).stat().st_size
    with open(source, "rb") as handle:
        if size <= part_bytes:
            try:
                client.put_object(Bucket=bucket, Key=key, Body=handle, ContentLength=size, IfNoneMatch="*", **extra)
            except Exception as error:
                if is_taken(error):
                    return False
                raise
            return True
        upload_id = client.create_multipart_upload(Bucket=bucket, Key=key, **extra)["UploadId"]
        try:
            parts = []
            number = 1
            while chunk := handle.read(part_bytes):
                etag = client.upload_part(Bucket=bucket, Key=key, UploadId=upload_id, PartNumber=number, Body=chunk)["ETag"]
                parts.append({"ETag": etag, "PartNumber": number})
                number += 1
                del chunk  # drop the part before reading the next: one part in memory at a time
            client.complete_multipart_upload(Bucket=bucket, Key=key, UploadId=upload_id, MultipartUpload={"Parts": parts}, IfNoneMatch="*")
        except Exception as error:
            _abort_multipart(client, bucket, key, upload_id)
            if is_taken(error):
                return False
            raise
        except BaseException:
            _abort_multipart(client, bucket, key, upload_id)
            raise
    return True


def _abort_multipart(client, bucket: str, key: str, upload_id: str) -> None:
    try:
        client.abort_multipart_upload(Bucket=bucket, Key=key, UploadId=upload_id)
    except Exception:  # the bucket's lifecycle rule for incomplete uploads is the backstop
        logger.warning("could not abort the multipart upload of %s/%s", bucket, key, exc_info=True)


def get_stream(client, bucket: str, key: str, byte_range: tuple[int, int] | None = None) -> BinaryIO:
    """The object's bytes (or bytes [start, end) of it) as a stream; FileNotFoundError if absent."""
    kwargs = {} if byte_range is None else {"Range": f"bytes={byte_range[0]}-{byte_range[1] - 1}"}
    try:
        return client.get_object(Bucket=bucket, Key=key, **kwargs)["Body"]
    except Exception as error:
        if is_missing(error):
            raise FileNotFoundError(f"s3://{bucket}/{key} does not exist") from None
        raise


def head(client, bucket: str, key: str) -> dict[str, Any] | None:
    """The object's HEAD response, or None if it does not exist."""
    try:
        return client.head_object(Bucket=bucket, Key=key)
    except Exception as error:
        if is_missing(error):
            return None
        raise


def presigned_get(client, bucket: str, key: str, expires_s: int, media_type: str | None = None, cache_control: str | None = None) -> str:
    """A presigned GET of the object, answering with `media_type` and `cache_control` when given."""
    params = {"Bucket": bucket, "Key": key}
    if media_type:
        params["ResponseContentType"] = media_type
    if cache_control:
        params["ResponseCacheControl"] = cache_control
    return client.generate_presigned_url("get_object", Params=params, ExpiresIn=int(expires_s))


class RevalidatedObjects:
    """Small objects (manifests, export indexes) read and parsed once, then revalidated by ETag on every
    read: one round trip, a 304 keeps the parsed copy, and an object an operator deleted is noticed.
    Keeps the `size` most recently read; safe across threads (the API serves from a thread pool)."""

    def __init__(self, client, bucket: str, size: int):
        self.client, self.bucket, self.size = client, bucket, int(size)
        self._parsed: OrderedDict[str, tuple[str, Any]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: str, parse: Callable[[bytes], Any], missing: str) -> Any:
        """parse(the object's bytes), cached; FileNotFoundError(missing) when the object is absent."""
        with self._lock:
            cached = self._parsed.get(key)
        try:
            kwargs = {"IfNoneMatch": cached[0]} if cached else {}
            response = self.client.get_object(Bucket=self.bucket, Key=key, **kwargs)
        except Exception as error:
            if cached and error_code(error) in {"304", "NotModified"}:
                return cached[1]
            if is_missing(error):
                with self._lock:
                    self._parsed.pop(key, None)
                raise FileNotFoundError(missing) from None
            raise
        with response["Body"] as body:
            parsed = parse(body.read())
        with self._lock:
            self._parsed[key] = (response["ETag"], parsed)
            self._parsed.move_to_end(key)
            while len(self._parsed) > self.size:
                self._parsed.popitem(last=False)
        return parsed


class S3BlobStore(BlobStore):
    """Blobs under `<prefix>blobs/sha256/` of a bucket; staging and the read cache under `cache_dir`."""

    def __init__(self, client, bucket: str, prefix: str, cache_dir: Path, cache_max_bytes: int, part_bytes: int):
        self.client, self.bucket, self.prefix, self.part_bytes = client, bucket, prefix, int(part_bytes)
        self.cache = ReadCache(Path(cache_dir), cache_max_bytes)
        super().__init__(Path(cache_dir) / STAGING_DIRNAME)

    def key(self, digest: str) -> str:
        digest = check_digest(digest)
        return f"{self.prefix}blobs/sha256/{digest[:2]}/{digest[2:4]}/{digest}"

    def commit(self, blob: IncomingBlob) -> bool:
        blob.close()
        try:
            if self.exists(blob.sha256):
                return False  # same bytes already stored: deduplicated without sending them
            return put_file_once(self.client, self.bucket, self.key(blob.sha256), blob.path, self.part_bytes,
                                 metadata={"sha256": blob.sha256})
        finally:
            blob.discard()

    def exists(self, digest: str) -> bool:
        return head(self.client, self.bucket, self.key(digest)) is not None

    def size(self, digest: str) -> int:
        found = head(self.client, self.bucket, self.key(digest))
        if found is None:
            raise FileNotFoundError(f"blob {digest} is not in s3://{self.bucket}/{self.prefix}")
        return int(found["ContentLength"])

    def open(self, digest: str) -> BinaryIO:
        return get_stream(self.client, self.bucket, self.key(digest))

    def materialize(self, digest: str, destination: Path) -> Path:
        cached = self.cache.get(digest, lambda: self.open(digest))
        return link_read_only(cached, destination)

    def delete(self, digest: str) -> None:
        self.client.delete_object(Bucket=self.bucket, Key=self.key(digest))
        self.cache.path(digest).unlink(missing_ok=True)

    def digests(self) -> Iterator[str]:
        paginator = self.client.get_paginator("list_objects_v2")
        for page in paginator.paginate(Bucket=self.bucket, Prefix=f"{self.prefix}blobs/sha256/"):
            for item in page.get("Contents", []):
                name = item["Key"].rsplit("/", 1)[-1]
                try:
                    yield check_digest(name)
                except ValueError:  # a stray object that is not a blob
                    continue

    def presigned_url(self, digest: str, expires_s: int) -> str:
        return self.client.generate_presigned_url("get_object", Params={"Bucket": self.bucket, "Key": self.key(digest)}, ExpiresIn=int(expires_s))
