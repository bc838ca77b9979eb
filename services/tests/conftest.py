"""Fixtures shared by the crowdbake tests."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_ASSETS = Path(os.environ.get("CROWDBAKE_SHARED_ASSETS", REPO_ROOT.parent / "shared" / "assets"))
VECTORS = REPO_ROOT / "shared_formats" / "vectors"

# Offscreen GL: OSMesa unless the caller chose another platform (EGL on a GPU machine).
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


@pytest.fixture(scope="session")
def shared_asset():
    """Path to a third-party asset in ../shared/assets; skips the test when it is absent."""

    def find(name: str) -> Path:
        path = SHARED_ASSETS / name
        if not path.is_file():
            pytest.skip(f"third-party asset {name} not found under {SHARED_ASSETS} (set CROWDBAKE_SHARED_ASSETS)")
        return path

    return find
