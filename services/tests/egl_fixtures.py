"""A process of its own per GL platform: PYOPENGL_PLATFORM is read when OpenGL is first imported, so a
test that draws under EGL while the suite runs under OSMesa (or the other way) starts a Python for it."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from repo_paths import REPO_ROOT

TESTS = Path(__file__).resolve().parent


def platform_env(platform: str, **variables: str) -> dict[str, str]:
    """This process's environment with PYOPENGL_PLATFORM=platform, crowdbake and the test helpers
    importable, and `variables` set (a value of "" removes the variable)."""
    env = dict(os.environ, PYOPENGL_PLATFORM=platform, PYTHONPATH=os.pathsep.join([str(REPO_ROOT / "services"), str(TESTS)]))
    for name, value in variables.items():
        if value:
            env[name] = value
        else:
            env.pop(name, None)
    return env


@pytest.fixture(scope="session")
def egl_or_skip():
    probe = "import pyrender; r = pyrender.OffscreenRenderer(8, 8); r.delete()"
    done = subprocess.run([sys.executable, "-c", probe], env=platform_env("egl"), capture_output=True, text=True, timeout=120)
    if done.returncode != 0:
        pytest.skip(f"no EGL context here (Mesa's libEGL and a render node or its surfaceless platform): {done.stderr.strip()[-300:]}")
