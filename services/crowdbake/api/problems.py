"""RFC 9457 problem details: every error the API returns is `application/problem+json`.

A problem has `type` (a URI naming the kind of problem; `/problems/<slug>` here, and the API serves
a description at that address), `title` (the same for every occurrence of the type), `status`,
`detail` (this occurrence), `instance` (the request path), and, for validation problems, `errors`: one
entry per problem with the `field` concerned, the `file` (or archive entry) and `where` in it.
"""
from __future__ import annotations

import errno
import logging
import os
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from crowdbake.redact import path_replacements, redact_text, redact_value
from crowdbake.ingest.uploads import FieldError, UploadRejected

logger = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"
# OS errors that mean "the disk (or the quota) is full".
STORAGE_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})

# slug -> (status, title, when it happens). docs/service.md lists the same table.
PROBLEM_TYPES: dict[str, tuple[int, str, str]] = {
    "malformed-request": (400, "Malformed request", "The request could not be read: bad multipart, a missing or unexpected form field."),
    "unauthorized": (401, "Missing or invalid API key", "Send a key as `Authorization: Bearer <key>` or `X-API-Key: <key>`."),
    "forbidden": (403, "The API key lacks a scope", "The key is valid but has none of the scopes the operation needs."),
    "not-found": (404, "Not found", "No such resource, or it is not visible to this key."),
    "method-not-allowed": (405, "Method not allowed", "The resource does not support this method."),
    "request-timeout": (408, "Request body too slow", "The body arrived slower than CROWDBAKE_BODY_MIN_BYTES_PER_S after a grace period, "
                        "or took longer than CROWDBAKE_BODY_MAX_SECONDS; nothing of it was kept."),
    "conflict": (409, "Conflict", "The request contradicts the resource's state (e.g. a published version with other bytes)."),
    "invalid-state": (409, "Not possible in the bake's state", "E.g. cancelling a finished bake, retrying one that succeeded."),
    "payload-too-large": (413, "Request body too large", "The body exceeds its operation's limit (CROWDBAKE_MAX_UPLOAD_BYTES for an upload, "
                          "1 MiB for a JSON body): refused before it is read when Content-Length says so, else when the limit is passed."),
    "unsupported-format": (415, "Unsupported file format", "The field does not take this kind of file."),
    "range-not-satisfiable": (416, "Range not satisfiable", "The requested byte range lies outside the file."),
    "invalid-file": (422, "Invalid file", "A file breaks its format or cannot be baked (truncated, NaN, counts disagree, too few frames)."),
    "format-mismatch": (422, "File content does not match its name", "The name promises one format and the bytes are another."),
    "unsafe-archive": (422, "Unsafe archive", "A zip entry escapes its folder, or the archive expands too far (zip bomb)."),
    "validation-error": (422, "Invalid request parameters", "A JSON body, path or query parameter breaks its schema."),
    "internal-error": (500, "Internal server error", "An unexpected error; the server log has the details."),
    "not-ready": (503, "Service not ready", "A dependency (database, blob store, broker) is not usable."),
}
_STATUS_SLUGS = {400: "malformed-request", 401: "unauthorized", 403: "forbidden", 404: "not-found", 405: "method-not-allowed", 408: "request-timeout", 409: "conflict", 413: "payload-too-large", 415: "unsupported-format", 416: "range-not-satisfiable", 422: "validation-error", 503: "not-ready"}


def problem_type_uri(slug: str) -> str:
    return f"/problems/{slug}"


class Problem(Exception):
    """Raise from a route or dependency to answer with a problem document."""

    def __init__(self, slug: str, detail: str, errors: list[dict[str, Any]] | None = None,
                 status: int | None = None, headers: dict[str, str] | None = None, title: str | None = None):
        if slug not in PROBLEM_TYPES:
            raise ValueError(f"unknown problem type {slug!r}")
        super().__init__(detail)
        self.slug = slug
        self.status = status or PROBLEM_TYPES[slug][0]
        self.title = title or PROBLEM_TYPES[slug][1]
        self.detail = detail
        self.errors = errors
        self.headers = headers or {}


def problem_response(request: Request | None, problem: Problem) -> JSONResponse:
    # Whatever a reader or a stage put in the message, the client never sees a server path.
    services = getattr(getattr(request, "app", None), "state", None)
    settings = getattr(getattr(services, "services", None), "settings", None)
    replacements = path_replacements(settings) if settings is not None else []
    body: dict[str, Any] = {
        "type": problem_type_uri(problem.slug),
        "title": problem.title,
        "status": problem.status,
        "detail": redact_text(problem.detail, replacements),
        "instance": request.url.path if request is not None else None,
    }
    if problem.errors is not None:
        body["errors"] = redact_value(problem.errors, replacements)
    return JSONResponse(body, status_code=problem.status, media_type=PROBLEM_MEDIA_TYPE, headers=problem.headers)


def from_upload_rejected(rejected: UploadRejected) -> Problem:
    return Problem(rejected.kind, rejected.detail, [error.to_dict() for error in rejected.errors])


def _field_name(location: tuple[Any, ...]) -> str:
    parts = [str(part) for part in location if part not in ("body", DICT_KEY_MARK)]
    return ".".join(parts) or "body"


# Pydantic ends the location of an error in a dict's key with this (the key itself comes before it).
DICT_KEY_MARK = "[key]"


def json_pointer(location: tuple[Any, ...]) -> str:
    """RFC 6901 pointer into the JSON body of a validation error's location ("body", "inputs", "bogus",
    "[key]") -> "/inputs/bogus": what a client follows to the key or value at fault."""
    parts = [str(part) for part in location[1:] if part != DICT_KEY_MARK]
    return "".join("/" + part.replace("~", "~0").replace("/", "~1") for part in parts)


def _where(item: dict[str, Any]) -> str:
    """errors[].where of a pydantic error: the JSON pointer of the key or value at fault in a body; else
    the part of the request ("query", "path", or "body" for a body that is not JSON or is missing)."""
    location = tuple(item.get("loc", ())) or ("body",)
    # An unreadable body's location holds the character offset, not a key.
    pointer = json_pointer(location) if location[0] == "body" and item.get("type") != "json_invalid" else ""
    return pointer or str(location[0])


# nginx's status for a request whose client left before the answer; never seen by that client.
CLIENT_CLOSED_REQUEST = 499


def install(app: FastAPI) -> None:
    """Answer every error, including FastAPI's own validation and routing errors, as a problem."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, problem: Problem) -> JSONResponse:
        return problem_response(request, problem)

    @app.exception_handler(UploadRejected)
    async def _rejected(request: Request, rejected: UploadRejected) -> JSONResponse:
        return problem_response(request, from_upload_rejected(rejected))

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, error: RequestValidationError) -> JSONResponse:
        errors = [
            FieldError(_field_name(tuple(item.get("loc", ()))), item.get("msg", "invalid"), where=_where(item)).to_dict()
            for item in error.errors()
        ]
        count = len(errors)
        places = ", ".join(dict.fromkeys(entry["where"] for entry in errors))
        return problem_response(request, Problem("validation-error", f"{count} parameter{'s' if count != 1 else ''} failed validation ({places})", errors))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, error: StarletteHTTPException) -> JSONResponse:
        slug = _STATUS_SLUGS.get(error.status_code, "malformed-request" if error.status_code < 500 else "internal-error")
        detail = error.detail if isinstance(error.detail, str) else PROBLEM_TYPES[slug][2]
        return problem_response(request, Problem(slug, detail, status=error.status_code, headers=dict(error.headers or {})))

    @app.exception_handler(ClientDisconnect)
    async def _client_left(request: Request, error: ClientDisconnect) -> Response:
        # The client closed its connection during the body or the work after it (crowdbake.api.disconnects):
        # nobody reads an answer; 499 (nginx's "client closed request") is for the logs and metrics.
        logger.info("%s %s: the client closed the connection before the answer", request.method, request.url.path)
        return Response(status_code=CLIENT_CLOSED_REQUEST)

    @app.exception_handler(OSError)
    async def _storage(request: Request, error: OSError) -> JSONResponse:
        # A full disk (or quota) under the blob store is the server's condition, not a bug, and it
        # passes: say so with 503 instead of a 500. The upload's staging files are already discarded.
        if error.errno in STORAGE_FULL_ERRNOS:
            logger.error("storage full on %s %s: %s", request.method, request.url.path, error)
            return problem_response(request, Problem("not-ready", f"the server has no room to store this: {os.strerror(error.errno)}; try again later"))
        return await _unexpected(request, error)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, error: Exception) -> JSONResponse:
        logger.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=error)
        return problem_response(request, Problem("internal-error", "an unexpected error occurred; it has been logged"))
