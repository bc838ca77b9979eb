"""The per-job work folder: atomic writes, stage stamps and the keys that make stages idempotent.

Layout (see docs/bake.md):

    validate/record.json     the checked job: inputs (copied into inputs/), their sha256, parameters, created
    inputs/                  character.glb|gltf, cloth.pc2, cloth.obj, textures/, cycle.json (+ looped.pc2)
    cycle/                   cycle.json, looped.pc2, report.html (crowdbake.stages.cycle_report), record.json
    poses/                   <part>_lod<k>.cbpc (or .cbsk: a skinned body), textures.npz, record.json
    textures/record.json     the poses stage's textures (in poses/), made from the job alone
    impostor/parts/<id>.npz  one impostor task's views (+ <id>.json: its key and statistics)
    pack/record.json         what the pack stage measured; bundle/ the packed bundle, not yet published

Every stage folder also holds stage.json: {"key", "record_version", "seconds"}. The key is a hash of
the stage's inputs; a rerun whose key matches and whose outputs exist returns the recorded record.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Generic, TypeVar

import numpy as np

from crowdbake.errors import StageOrderError

Progress = Callable[[str, int, int], None]
R = TypeVar("R")


def stage_key(*parts: Any) -> str:
    """A stable hash of JSON-able parts: the identity of a stage's inputs."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def write_bytes_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(data)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def write_json_atomic(path: Path, document: Any) -> None:
    write_bytes_atomic(path, (json.dumps(document, indent=2, sort_keys=True) + "\n").encode())


def read_json(path: Path) -> Any:
    return json.loads(Path(path).read_text(encoding="utf-8"))


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def json_bytes(document: Any) -> bytes:
    """Canonical JSON bytes; non-finite floats become null (JSON has no infinity)."""

    def clean(value: Any) -> Any:
        if isinstance(value, float) and not np.isfinite(value):
            return None
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v) for v in value]
        return value

    return (json.dumps(clean(document), indent=2, sort_keys=True, allow_nan=False) + "\n").encode()


def report(progress: Progress | None, stage: str, done: int, total: int) -> None:
    if progress is not None:
        progress(stage, done, total)


@dataclass
class StageOutcome(Generic[R]):
    """What a stage function returns: its record, whether it was already there, and the seconds spent."""

    record: R
    cached: bool
    seconds: float

    def to_json(self) -> dict[str, Any]:
        return {"record": self.record.to_json(), "cached": self.cached, "seconds": self.seconds}


class WorkDir:
    """Paths and stamps of one job's work folder."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def stamp_path(self, stage: str) -> Path:
        return self.root / stage / "stage.json"

    def record_path(self, stage: str) -> Path:
        return self.root / stage / "record.json"

    @property
    def inputs(self) -> Path:
        return self.root / "inputs"

    @property
    def bundle(self) -> Path:
        return self.root / "bundle"

    def part_path(self, task_id: str) -> Path:
        return self.root / "impostor" / "parts" / f"{task_id}.npz"

    def key_of(self, stage: str) -> str:
        """The key the stage ran with; StageOrderError when it has not run here."""
        stamp = self.stamp_path(stage)
        if not stamp.is_file():
            raise StageOrderError(f"{self.root}: stage {stage!r} has not run yet")
        return read_json(stamp)["key"]

    def cached(self, stage: str, key: str, record_type, outputs: list[Path]):
        """The stage's record if it ran with `key` (and this record version) and its outputs all exist."""
        stamp = self.stamp_path(stage)
        if not stamp.is_file():
            return None
        try:
            recorded = read_json(stamp)
            if recorded.get("key") != key or recorded.get("record_version") != record_type.RECORD_VERSION:
                return None
            if not all(Path(p).exists() for p in outputs):
                return None
            return record_type.from_json(read_json(self.record_path(stage)))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def save(self, stage: str, key: str, record, seconds: float) -> None:
        """Write the stage's record, then its stamp (the stamp last: a stamp means the record is whole)."""
        write_json_atomic(self.record_path(stage), record.to_json())
        write_json_atomic(self.stamp_path(stage), {"key": key, "record_version": record.RECORD_VERSION, "seconds": seconds})

    def load(self, stage: str, record_type):
        """The record a stage wrote; StageOrderError when it has not run here."""
        path = self.record_path(stage)
        if not self.stamp_path(stage).is_file() or not path.is_file():
            raise StageOrderError(f"{self.root}: stage {stage!r} has not run yet")
        return record_type.from_json(read_json(path))
