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


class FormatError(ValueError):
    """A file or bundle breaks the spec. `code` is one of ERROR_CODES; `file` names what broke it."""

    def __init__(self, code: str, message: str, file: str | None = None):
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        self.code = code
        self.file = file
        self.detail = message
        super().__init__(f"{code}: {file}: {message}" if file else f"{code}: {message}")
