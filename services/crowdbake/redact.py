"""Server paths out of what clients read: bake logs, bake errors and problem details.

Workers log and fail with messages that name files where they lie (`/srv/crowdbake/work/<key>/cycle`,
a blob's path, a scratch folder). A client needs the name, not the server's layout, so every folder of
the settings is replaced by its relative name (`work/<key>/cycle`, `blobs/ab/...`) and the temporary
folder by `tmp`, at the API's edge: the database keeps what the worker wrote, for operators.
"""
from __future__ import annotations

import re
import tempfile
from typing import Any


def path_replacements(settings) -> list[tuple[str, str]]:
    """(absolute folder, relative name) pairs, longest first so nested folders win over data_dir."""
    named = {
        "blobs": settings.blob_dir, "bundles": settings.bundles_dir, "work": settings.work_dir,
        "broker": settings.broker_dir, "cache": settings.cache_dir, "": settings.data_dir,
    }
    pairs = [(str(folder).rstrip("/"), name) for name, folder in named.items() if folder]
    pairs.append((tempfile.gettempdir().rstrip("/"), "tmp"))
    return sorted({pair for pair in pairs if pair[0] not in ("", "/")}, key=lambda pair: -len(pair[0]))


def redact_text(text: str, replacements: list[tuple[str, str]]) -> str:
    """`text` with each absolute folder replaced by its name where it stands as a whole path (not
    inside a longer one: "/tmp" is not replaced in "blobs/tmp1")."""
    for folder, name in replacements:
        if folder in text:
            whole = re.compile(r"(?<![\w./-])" + re.escape(folder) + r"(/|(?![\w.-]))")
            text = whole.sub(lambda match: (f"{name}/" if name else "") if match.group(1) else (name or "."), text)
    return text


def redact_value(value: Any, replacements: list[tuple[str, str]]) -> Any:
    """Strings anywhere inside dicts and lists redacted (a bake's error document, a problem's errors)."""
    if isinstance(value, str):
        return redact_text(value, replacements)
    if isinstance(value, dict):
        return {key: redact_value(item, replacements) for key, item in value.items()}
    if isinstance(value, list):
        return [redact_value(item, replacements) for item in value]
    return value
