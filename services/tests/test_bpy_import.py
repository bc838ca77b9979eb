"""`import bpy` beside NumPy 2 (bpy 5.0.1 installed with --no-deps) printed NumPy's "compiled using NumPy
1.x" warning and two tracebacks, then worked: `crowdbake.export.blender_round_trip` looked broken when it was
not. crowdbake.export.bpy_import imports bpy with that block kept off stderr, and a failed import still
raises with everything it printed.
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest

from repo_paths import REPO_ROOT
from crowdbake.export.bpy_import import NUMPY_ABI_FIRST_LINE, NUMPY_ABI_LAST_LINE, without_numpy_abi_warning


def run_python(code: str, *paths: str) -> subprocess.CompletedProcess:
    path = os.pathsep.join([*paths, str(REPO_ROOT / "services")])
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO_ROOT,
                          env={**os.environ, "PYTHONPATH": path})


def test_only_the_numpy_block_is_dropped():
    block = f"{NUMPY_ABI_FIRST_LINE}\nNumPy 2.4.6 as it may crash.\nTraceback (most recent call last):\n{NUMPY_ABI_LAST_LINE}\n"
    assert without_numpy_abi_warning(f"before\n{block}after\n") == "before\nafter\n"
    assert without_numpy_abi_warning(block) == ""
    assert without_numpy_abi_warning("Traceback (most recent call last):\nOSError: boom\n") == "Traceback (most recent call last):\nOSError: boom\n"


def test_a_failed_import_raises_with_what_it_printed(tmp_path):
    fake = tmp_path / "bpy"
    fake.mkdir()
    (fake / "__init__.py").write_text("import os\nos.write(2, b'libblender.so: cannot open shared object file\\n')\nraise ImportError('no Blender')\n")
    run = run_python("from crowdbake.export.bpy_import import import_bpy\nimport_bpy()", str(tmp_path))
    assert run.returncode != 0
    assert "import bpy failed: no Blender" in run.stderr and "libblender.so: cannot open shared object file" in run.stderr, run.stderr


def test_importing_bpy_prints_no_numpy_warning():
    if importlib.util.find_spec("bpy") is None:
        pytest.skip("Blender's bpy module is not installed (pip install -r services/requirements-alembic.txt)")
    run = run_python("from crowdbake.export.bpy_import import import_bpy\nprint(import_bpy().app.version_string)")
    assert run.returncode == 0 and run.stdout.strip(), run.stderr
    assert "NumPy 1.x" not in run.stderr and "Traceback" not in run.stderr, run.stderr


def test_the_blender_round_trip_prints_no_numpy_warning(tmp_path):
    """The command the user ran: the round trip of a tiny character, its stderr free of the warning."""
    if importlib.util.find_spec("bpy") is None:
        pytest.skip("Blender's bpy module is not installed (pip install -r services/requirements-alembic.txt)")
    from service_fixtures import tiny_character_glb

    glb = tmp_path / "tiny.glb"
    glb.write_bytes(tiny_character_glb())
    run = subprocess.run([sys.executable, "-m", "crowdbake.export.blender_round_trip", str(glb), str(tmp_path / "seen.npz")],
                         capture_output=True, text=True, timeout=300, cwd=REPO_ROOT, env={**os.environ, "PYTHONPATH": str(REPO_ROOT / "services")})
    assert run.returncode == 0 and (tmp_path / "seen.npz").is_file(), run.stderr[-2000:]
    assert "NumPy 1.x" not in run.stderr and "Traceback" not in run.stderr, run.stderr
