"""Fixtures shared by the crowdbake tests."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from repo_paths import REPO_ROOT, SHARED_ASSETS, VECTORS  # noqa: F401  (tests import them from repo_paths)
from sample_fixtures import small_bake, small_sample  # noqa: F401  (a session fixture shared with tests/)
from clips_fixtures import clips_bake, clips_sample  # noqa: F401  (the clips sample and its bake, shared by the sample's and the service's tests)
from robot_fixtures import robot_bake  # noqa: F401  (the robot's v2 bundle, shared by the bake's and the export's tests)
from egl_fixtures import egl_or_skip  # noqa: F401  (skips where no EGL context can be made)


def pytest_configure(config) -> None:
    # scripts/test.sh leaves slow tests out unless CROWDBAKE_SLOW_TESTS=1 (which .ci/run sets).
    config.addinivalue_line("markers", "slow: long-running tests (run by .ci/run; scripts/test.sh runs them with CROWDBAKE_SLOW_TESTS=1)")


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
