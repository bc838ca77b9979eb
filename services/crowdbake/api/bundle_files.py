"""Answering GET/HEAD for a published bundle file from any BundleStore: streamed, or by presigned redirect.

The bundle routes build the ETag and Cache-Control headers and answer If-None-Match with 304 first
(a published file's ETag is its sha256, whichever store holds it). Then either

- `bundle_file_response` sends the bytes: a local store's file as a FileResponse, an object store's
  file streamed from it, both with single Range requests answered 206 (several ranges: the whole file,
  which RFC 9110 §14.2 allows) and a range outside the file answered with a 416 problem; or
- `bundle_file_redirect` answers 307 to a presigned URL of the object store, which then serves the
  bytes, Range included, with the same Content-Type and Cache-Control; None for a local store.
"""
from __future__ import annotations

import os
from typing import BinaryIO, Iterator

from fastapi import Request
from fastapi.responses import FileResponse, RedirectResponse, Response, StreamingResponse
from starlette.responses import MalformedRangeHeader, RangeNotSatisfiable

from crowdbake.api.problems import Problem
from crowdbake.storage.bundle_store import BundleStore

CHUNK = 256 * 1024  # bytes per chunk of a streamed response
# A redirect may be cached a little less long than its URL lives, so nobody follows a dead link.
REDIRECT_MARGIN_S = 30


def stream_chunks(body: BinaryIO) -> Iterator[bytes]:
    try:
        while chunk := body.read(CHUNK):
            yield chunk
    finally:
        body.close()


def requested_range(request: Request, size: int, etag: str) -> tuple[int, int] | None:
    """The one byte range (start, end exclusive) to send, or None for the whole file.

    A Range that If-Range does not match, that cannot be parsed, or that asks for several ranges is
    ignored (RFC 9110 §13.1.5, §14.2); one starting past the end raises the 416 problem.
    """
    range_header = request.headers.get("range")
    if_range = request.headers.get("if-range")
    if not range_header or (if_range is not None and if_range.strip() != etag):
        return None
    try:
        ranges = FileResponse._parse_range_header(range_header, size)
    except MalformedRangeHeader:
        return None
    except RangeNotSatisfiable:
        raise Problem("range-not-satisfiable", f"the file has {size} bytes", headers={"Content-Range": f"bytes */{size}", "ETag": etag}) from None
    return ranges[0] if len(ranges) == 1 else None


def bundle_file_response(request: Request, store: BundleStore, name: str, version: str, path: str, size: int,
                         media_type: str, headers: dict[str, str]) -> Response:
    """The bytes of a published file (path 'manifest.json' or a manifest path), whole or one range.

    size: the file's size from the manifest (for the manifest itself, len(PublishedManifest.data)).
    headers: sent on every answer; must hold the ETag the If-Range header is compared with.
    """
    try:
        byte_range = requested_range(request, size, headers["ETag"])
    except Problem as problem:
        problem.headers = {**headers, **(problem.headers or {})}
        raise
    local = store.local_path(name, version, path)
    if local is not None:
        if byte_range is None:  # an ignored Range must not reach FileResponse, which would honour it
            request.scope["headers"] = [(k, v) for k, v in request.scope["headers"] if k != b"range"]
        try:
            stat_result = os.stat(local)
        except FileNotFoundError:
            raise Problem("internal-error", "a published file is missing from the bundle store", status=500) from None
        return FileResponse(local, media_type=media_type, headers=headers, stat_result=stat_result)
    out = {**headers, "Accept-Ranges": "bytes"}
    start, end = byte_range if byte_range else (0, size)
    out["Content-Length"] = str(end - start)
    status = 200
    if byte_range:
        status = 206
        out["Content-Range"] = f"bytes {start}-{end - 1}/{size}"
    if request.method == "HEAD":
        return Response(status_code=status, headers=out, media_type=media_type)
    try:
        body = store.open_file(name, version, path, byte_range)
    except FileNotFoundError:
        raise Problem("internal-error", "a published file is missing from the bundle store", status=500) from None
    return StreamingResponse(stream_chunks(body), status_code=status, headers=out, media_type=media_type)


def bundle_file_redirect(store: BundleStore, name: str, version: str, path: str, media_type: str,
                         headers: dict[str, str], expires_s: int) -> Response | None:
    """307 to a presigned URL of the file (valid `expires_s` seconds), or None if the store has none.

    The object store's answer carries `media_type` and the Cache-Control of `headers`; the redirect
    itself keeps the ETag (so If-None-Match still gets 304 from the API) and is cached no longer than
    its URL lives.
    """
    url = store.presigned_url(name, version, path, expires_s, media_type, headers.get("Cache-Control"))
    if url is None:
        return None
    out = {key: value for key, value in headers.items() if key != "Cache-Control"}
    latest = "no-cache" in headers.get("Cache-Control", "")
    out["Cache-Control"] = "no-cache" if latest else f"private, max-age={max(0, int(expires_s) - REDIRECT_MARGIN_S)}"
    return RedirectResponse(url, status_code=307, headers=out)
