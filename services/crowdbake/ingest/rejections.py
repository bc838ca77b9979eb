"""What an upload check answers when it refuses a file, and the format sniffing every check starts with.

UploadRejected carries one FieldError per problem: the form field, the file (or zip entry), where in it
(a byte offset or a line) and the problem type; the API turns it into an RFC 9457 problem. Formats are
recognised by their content, never by the name alone.
"""
from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from pathlib import Path, PurePosixPath
from typing import Any

COPY_CHUNK = 1 << 20
_SNIFF_BYTES = 4096

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
GLB_MAGIC = b"glTF"
PC2_MAGIC = b"POINTCACHE2\0"
ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")

# Extension -> the content format it promises.
CHARACTER_EXTENSIONS = {".glb": "glb", ".gltf": "gltf"}
CACHE_EXTENSIONS = {".pc2": "pc2"}
MESH_EXTENSIONS = {".obj": "obj"}
SEQUENCE_EXTENSIONS = {".zip": "zip"}
TEXTURE_EXTENSIONS = {".png": "png"}

FORMAT_NAMES = {
    "glb": "a binary glTF (GLB)",
    "gltf": "a glTF JSON document",
    "png": "a PNG image",
    "pc2": "a PC2 point cache",
    "zip": "a zip archive",
    "obj": "a Wavefront OBJ mesh",
}
_OBJ_KEYWORDS = re.compile(rb"^\s*(v|vt|vn|vp|f|o|g|s|l|p|mtllib|usemtl|#)(\s|$)")


@dataclass(frozen=True)
class FieldError:
    """One problem: the request field, the file (or archive entry) and where in it, e.g. 'byte 48'."""

    field: str
    message: str
    file: str | None = None
    where: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {key: value for key, value in asdict(self).items() if value is not None}


# Problem kinds (the API maps each to an RFC 9457 problem type and status).
INVALID_FILE = "invalid-file"            # 422: the bytes break their format or the bake's needs
FORMAT_MISMATCH = "format-mismatch"      # 422: the name promises one format, the bytes are another
UNSUPPORTED_FORMAT = "unsupported-format"  # 415: a kind of file the service does not take
UNSAFE_ARCHIVE = "unsafe-archive"        # 422: a zip that escapes its folder or expands too far


class UploadRejected(Exception):
    """An upload fails validation; nothing of it may be stored."""

    def __init__(self, kind: str, detail: str, errors: list[FieldError]):
        super().__init__(detail)
        self.kind = kind
        self.detail = detail
        self.errors = errors


# ----------------------------------------------------------------------------------------- formats


def sniff_format(path: Path) -> str | None:
    """The format the bytes are (a key of FORMAT_NAMES), or None when they are none of them."""
    with open(path, "rb") as handle:
        head = handle.read(_SNIFF_BYTES)
    if head.startswith(GLB_MAGIC):
        return "glb"
    if head.startswith(PNG_SIGNATURE):
        return "png"
    if head.startswith(PC2_MAGIC):
        return "pc2"
    if head.startswith(ZIP_MAGICS):
        return "zip"
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if text.startswith(b"{"):
        return "gltf"
    if b"\0" not in head and any(_OBJ_KEYWORDS.match(line) for line in head.splitlines()[:50]):
        return "obj"
    return None


def _extension(filename: str) -> str:
    return PurePosixPath(filename.replace("\\", "/")).suffix.lower()


def expect_format(path: Path, filename: str, field: str, allowed: dict[str, str]) -> str:
    """Check that `filename` has an allowed extension and the bytes do not claim another format.

    Returns the format the extension promises. Raises UploadRejected: unsupported-format for an
    extension the field does not take, invalid-file for an empty file, format-mismatch when the bytes
    are recognisably another format. Bytes that are no known format go on to the reader, whose
    message (bad magic, parse error) is the more precise one.
    """
    extension = _extension(filename)
    if extension not in allowed:
        expected = " or ".join(sorted(allowed))
        raise UploadRejected(
            UNSUPPORTED_FORMAT,
            f"'{field}' takes {expected} files",
            [FieldError(field, f"{filename!r} is not a {expected} file", filename)],
        )
    promised = allowed[extension]
    size = path.stat().st_size
    if size == 0:
        raise UploadRejected(INVALID_FILE, "an uploaded file is empty", [FieldError(field, "the file is empty", filename, "byte 0")])
    actual = sniff_format(path)
    if actual is not None and actual != promised:
        raise UploadRejected(
            FORMAT_MISMATCH,
            "a file's content is not the format its name says",
            [FieldError(field, f"named {extension} but the content is {FORMAT_NAMES[actual]}", filename, "byte 0")],
        )
    return promised


def clean_message(message: str, path: Path, filename: str) -> str:
    """A reader's message with the staging path replaced by the name the client uploaded."""
    return message.replace(str(path), filename)


_BYTE = re.compile(r"\bbyte (\d+)")


def where_from_message(message: str, path: Path) -> str | None:
    line = re.search(re.escape(str(path)) + r":(\d+):", message)
    if line:
        return f"line {line.group(1)}"
    byte = _BYTE.search(message)
    return f"byte {byte.group(1)}" if byte else None
