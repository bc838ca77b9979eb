"""Fixtures of the cross-cutting tests in tests/: the service test helpers (services/tests) on the
import path, the markers, and the procedural sample shared by the fault and load tests."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
for folder in (REPO / "services", REPO / "services" / "tests"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from sample_fixtures import small_bake, small_sample  # noqa: E402,F401  (generated once per session, shared with services/tests)

# Offscreen GL in every process these tests start (OSMesa unless the caller chose EGL).
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


def pytest_configure(config) -> None:
    # The same markers as services/pyproject.toml, for runs whose rootdir does not read that file.
    config.addinivalue_line("markers", "slow: long-running tests (run by .ci/run; scripts/test.sh runs them with CROWDBAKE_SLOW_TESTS=1)")
    config.addinivalue_line("markers", "integration: needs Redis and real worker processes (started by the tests themselves)")


@pytest.fixture(scope="session")
def sample(tmp_path_factory) -> Path:
    """The procedural sample character (crowdbake sample: 3 walk cycles, 64² textures)."""
    from reliability_fixtures import run_sample_command

    return run_sample_command(tmp_path_factory.mktemp("sample"))
