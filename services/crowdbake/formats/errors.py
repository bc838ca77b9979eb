"""The bundle format's named errors (shared_formats/SPEC.md, "Error codes")."""
from __future__ import annotations

ERROR_CODES = frozenset(
    {
        "manifest_invalid",
        "unsupported_format_version",
        "unsafe_path",
        "missing_file",
        "size_mismatch",
        "sha256_mismatch",
        "truncated",
        "bad_magic",
        "unsupported_version",
        "invalid_header",
        "invalid_data",
    }
)


def printable(text: str) -> str:
    """`text` with every control character written out: C0 and DEL as \\xNN, C1 (U+0080..U+009F) as
    \\u00NN, the rest unchanged; as crowdview's printable() (runtime/src/bundle.h) writes it. A path
    from a hostile manifest may hold NUL (which cut crowdview's message short) or a terminal escape."""
    return "".join(
        f"\\x{ord(c):02x}" if ord(c) < 0x20 or ord(c) == 0x7F else f"\\u{ord(c):04x}" if 0x80 <= ord(c) <= 0x9F else c
        for c in text
    )


class FormatError(ValueError):
    """A file or bundle breaks the spec. `code` is one of ERROR_CODES; `file` names what broke it.
    Both `file` and the message are printable(): whole and on one line whatever a manifest holds."""

    def __init__(self, code: str, message: str, file: str | None = None):
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        file = printable(file) if file is not None else None
        message = printable(message)
        self.code = code
        self.file = file
        self.detail = message
        super().__init__(f"{code}: {file}: {message}" if file else f"{code}: {message}")
