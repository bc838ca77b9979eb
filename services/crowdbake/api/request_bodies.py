"""Request bodies are bounded before they are read, and read only for a caller whose key verifies.

FastAPI reads a JSON body whole, and validates it, before it runs any dependency, the API key's
included: without this guard a client with no key could send hundreds of megabytes to POST /v1/bakes
and be told 401 only once the server had held them all. `BodyGate`, an ASGI middleware around the app,
decides before the first byte of a body is read:

* the body's limit comes from the route: an upload (a POST under /v1/assets, which
  crowdbake.api.uploads streams to a staging file) may send CROWDBAKE_MAX_UPLOAD_BYTES, every other
  body MAX_JSON_BODY_BYTES;
* a Content-Length over the limit is a 413 at once;
* a body without a key, or with a key that does not verify, is a 401 at once (every operation that
  takes a body needs a key: tests/test_security.py checks each write operation of the OpenAPI document);
* a body that arrives without a Content-Length (chunked) is cut off with a 413 when the bytes received
  pass the limit.

A refusal before the body is read closes the connection, so the unread bytes are never waited for.
The route still checks the key's scopes (403) once the bounded body is in.
"""
from __future__ import annotations

import logging
from typing import Callable

from starlette.concurrency import run_in_threadpool
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.requests import Request

from crowdbake.api.problems import Problem, problem_response
from crowdbake.storage.keys import verify_api_key

logger = logging.getLogger(__name__)

# A bake request, a check or a bundle update is a few kilobytes of ids, names and parameters; a megabyte
# leaves room for any texture list a bake may name and is still nothing to hold in memory.
MAX_JSON_BODY_BYTES = 1 << 20
CLOSE = {"Connection": "close"}


def declared_length(headers: Headers) -> int | None:
    """The Content-Length as a number, None when absent; a Problem (400) when it is no number."""
    declared = headers.get("content-length")
    if declared is None:
        return None
    if not declared.strip().isdigit():
        raise Problem("malformed-request", f"Content-Length {declared[:40]!r} is not a number", headers=CLOSE)
    return int(declared)


def carries_body(headers: Headers) -> bool:
    """Whether the request announces a body: a Content-Length other than 0, or a Transfer-Encoding (chunked)."""
    return "transfer-encoding" in headers or headers.get("content-length", "0").strip() != "0"


def sent_key(headers: Headers) -> str | None:
    """The API key of the request, as crowdbake.api.deps reads it (X-API-Key, or a bearer token)."""
    if headers.get("x-api-key"):
        return headers["x-api-key"]
    scheme, _, credentials = headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer":
        return None
    return credentials.strip() or None


class BodyGate:
    """ASGI middleware: a request body gets its route's size limit and is read only after its key verifies."""

    def __init__(self, app, sessions, upload_prefix: str, max_upload_bytes: int, max_json_bytes: int = MAX_JSON_BODY_BYTES):
        self.app = app
        self.sessions = sessions
        self.upload_prefix = upload_prefix.rstrip("/") + "/"
        self.max_upload_bytes, self.max_json_bytes = max_upload_bytes, max_json_bytes

    def limit(self, scope) -> int:
        """The most bytes this request's body may have: an upload's or a JSON body's."""
        if scope["method"] == "POST" and scope["path"].startswith(self.upload_prefix):
            return self.max_upload_bytes
        return self.max_json_bytes

    def key_verifies(self, raw_key: str) -> bool:
        session = self.sessions()
        try:
            return verify_api_key(session, raw_key) is not None
        finally:
            session.close()

    async def refusal(self, headers: Headers, limit: int) -> Problem | None:
        """Why the body must not be read at all, or None."""
        length = declared_length(headers)
        if length is not None and length > limit:
            return Problem("payload-too-large", f"the body is {length} bytes; this operation accepts at most {limit}", headers=CLOSE)
        raw_key = sent_key(headers)
        if raw_key is None:
            return Problem("unauthorized", "a request with a body needs an API key", headers={"WWW-Authenticate": "Bearer", **CLOSE})
        if not await run_in_threadpool(self.key_verifies, raw_key):
            return Problem("unauthorized", "the API key is unknown or revoked", headers={"WWW-Authenticate": "Bearer", **CLOSE})
        return None

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or not carries_body(headers := Headers(scope=scope)):
            return await self.app(scope, receive, send)
        limit = self.limit(scope)
        try:
            problem = await self.refusal(headers, limit)
        except Problem as malformed:
            problem = malformed
        if problem is not None:
            logger.info("%s %s: body refused before reading: %s", scope["method"], scope["path"], problem.detail)
            return await problem_response(Request(scope), problem)(scope, receive, send)
        return await self.app(scope, bounded_receive(receive, limit), send)


def bounded_receive(receive, limit: int) -> Callable:
    """`receive` that raises a 413 once the body's bytes pass `limit`. An HTTPException, so that FastAPI
    passes it on while reading a JSON body (any other error there becomes a 400 "error parsing the body")."""
    received = 0

    async def guarded():
        nonlocal received
        message = await receive()
        if message["type"] == "http.request":
            received += len(message.get("body", b""))
            if received > limit:
                raise HTTPException(413, f"the body exceeds {limit} bytes, the most this operation accepts", headers=CLOSE)
        return message

    return guarded
