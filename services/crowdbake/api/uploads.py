"""Streaming multipart uploads: each file part goes straight into a blob-store staging file, hashed as
it is written, with the body's size limit enforced as bytes arrive.

The limit is checked twice: against Content-Length before the first byte is read (an honest client
learns at once), and against the bytes actually received (a client that lies or streams without a
length is cut off at the limit). On any error every staging file of the request is discarded.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from fastapi import Request
from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header

from crowdbake.api.problems import Problem
from crowdbake.storage.blobs import BlobStore, IncomingBlob

# Text fields (ids, small numbers) are tiny; anything longer is a malformed request, not an upload.
MAX_TEXT_FIELD_BYTES = 1024
MAX_PARTS = 16
MAX_FILENAME_CHARS = 200


@dataclass
class UploadedFile:
    field: str
    filename: str
    content_type: str
    blob: IncomingBlob


@dataclass
class MultipartUpload:
    files: dict[str, UploadedFile] = field(default_factory=dict)
    fields: dict[str, str] = field(default_factory=dict)

    def discard(self) -> None:
        for uploaded in self.files.values():
            uploaded.blob.discard()


def check_declared_length(request: Request, max_bytes: int) -> None:
    """413 before reading anything when Content-Length already exceeds the limit."""
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            length = int(declared)
        except ValueError:
            raise Problem("malformed-request", f"Content-Length {declared!r} is not a number") from None
        if length > max_bytes:
            raise Problem("payload-too-large", f"the body is {length} bytes; at most {max_bytes} are accepted")


class _PartCollector:
    """python-multipart callbacks that route each part to a staging file or a small text buffer."""

    def __init__(self, blobs: BlobStore, upload: MultipartUpload, file_fields: set[str], text_fields: set[str]):
        self.blobs, self.upload = blobs, upload
        self.file_fields, self.text_fields = file_fields, text_fields
        self.parts = 0
        self._header_name = b""
        self._header_value = b""
        self._headers: dict[bytes, bytes] = {}
        self._name = ""
        self._file: UploadedFile | None = None
        self._text = bytearray()

    def on_part_begin(self) -> None:
        self.parts += 1
        if self.parts > MAX_PARTS:
            raise Problem("malformed-request", f"more than {MAX_PARTS} parts in one request")
        self._headers, self._file, self._text = {}, None, bytearray()

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def on_header_end(self) -> None:
        self._headers[self._header_name.lower()] = self._header_value
        self._header_name, self._header_value = b"", b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        name = options.get(b"name")
        if name is None:
            raise Problem("malformed-request", "a part has no Content-Disposition name")
        self._name = name.decode("utf-8", "replace")
        if self._name in self.upload.files or self._name in self.upload.fields:
            raise Problem("malformed-request", f"the field {self._name!r} is given twice", [{"field": self._name, "message": "given twice"}])
        if b"filename" in options:
            if self._name not in self.file_fields:
                raise Problem("malformed-request", f"unexpected file field {self._name!r}; this endpoint takes {', '.join(sorted(self.file_fields))}",
                              [{"field": self._name, "message": "unexpected file field"}])
            # Only the base name, without control characters (PostgreSQL text cannot hold NUL) and short
            # enough for any database column; it is only ever a label.
            filename = options[b"filename"].decode("utf-8", "replace").replace("\\", "/").rsplit("/", 1)[-1]
            filename = "".join(char for char in filename if char.isprintable())[-MAX_FILENAME_CHARS:]
            content_type = self._headers.get(b"content-type", b"application/octet-stream").decode("latin-1")
            self._file = UploadedFile(self._name, filename or self._name, content_type, self.blobs.incoming())
            self.upload.files[self._name] = self._file
        elif self._name not in self.text_fields:
            raise Problem("malformed-request", f"unexpected field {self._name!r}", [{"field": self._name, "message": "unexpected field"}])

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self._file is not None:
            self._file.blob.write(data[start:end])
        else:
            self._text += data[start:end]
            if len(self._text) > MAX_TEXT_FIELD_BYTES:
                raise Problem("malformed-request", f"the field {self._name!r} is longer than {MAX_TEXT_FIELD_BYTES} bytes")

    def on_part_end(self) -> None:
        if self._file is not None:
            self._file.blob.close()
        else:
            self.upload.fields[self._name] = self._text.decode("utf-8", "replace")


async def read_multipart(request: Request, blobs: BlobStore, max_bytes: int, file_fields: set[str], text_fields: set[str] = frozenset()) -> MultipartUpload:
    """Stream a multipart/form-data body into staging files; the caller must commit or discard them."""
    media_type, params = parse_options_header(request.headers.get("content-type", ""))
    if media_type != b"multipart/form-data":
        raise Problem("unsupported-format", "send the files as multipart/form-data")
    boundary = params.get(b"boundary")
    if not boundary:
        raise Problem("malformed-request", "the multipart Content-Type has no boundary")
    check_declared_length(request, max_bytes)

    upload = MultipartUpload()
    collector = _PartCollector(blobs, upload, set(file_fields), set(text_fields))
    parser = MultipartParser(boundary, {
        "on_part_begin": collector.on_part_begin, "on_part_data": collector.on_part_data,
        "on_part_end": collector.on_part_end, "on_header_field": collector.on_header_field,
        "on_header_value": collector.on_header_value, "on_header_end": collector.on_header_end,
        "on_headers_finished": collector.on_headers_finished,
    })
    received = 0
    try:
        async for chunk in request.stream():
            received += len(chunk)
            if received > max_bytes:
                raise Problem("payload-too-large", f"the body exceeds {max_bytes} bytes")
            parser.write(chunk)
        parser.finalize()
        unfinished = [name for name, uploaded in upload.files.items() if not uploaded.blob.finished]
        if unfinished:
            raise Problem("malformed-request", f"the multipart body ends inside the field {unfinished[0]!r}")
    except FormParserError as error:
        upload.discard()
        raise Problem("malformed-request", f"the multipart body does not parse: {error}") from None
    except BaseException:  # a disconnect, the size limit, a bad part: nothing of the request stays
        upload.discard()
        raise
    return upload
