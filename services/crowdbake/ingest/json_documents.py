"""JSON documents users hand the bake (timeline.json, cycle.json), parsed strictly.

Python's json keeps the last of two equal keys in an object without a word, so `{"clip": "Idle",
"clip": "Walk"}` would mean whatever the last writer chose while another reader (a browser, jq) may take
the first; such a document is refused instead.
"""
from __future__ import annotations

import json
from typing import Any


def refuse_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """json object_pairs_hook: ValueError when an object names a key twice."""
    document = dict(pairs)
    if len(document) != len(pairs):
        seen: set[str] = set()
        twice = next(key for key, _ in pairs if key in seen or seen.add(key))
        raise ValueError(f"the key {twice[:40]!r} appears twice in one object")
    return document


def loads_strict(text: str) -> Any:
    """json.loads refusing duplicate keys (ValueError, as json's own errors)."""
    return json.loads(text, object_pairs_hook=refuse_duplicate_keys)
