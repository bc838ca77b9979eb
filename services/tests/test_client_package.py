"""The client distribution: what pyproject.toml declares, that the client imports without the bake
stack, and the forward-only progress it shows."""
from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

from crowdbake.client.download import safe_relative_path
from crowdbake.client.progress import ForwardProgress, advance, describe

import pytest

SERVICES = Path(__file__).resolve().parents[1]
CLIENT_ONLY = Path(__file__).resolve().parent / "client_only.py"


def requirement_lines(name: str) -> list[str]:
    return [line.strip() for line in (SERVICES / name).read_text().splitlines() if line.strip() and not line.startswith("#")]


def test_pyproject_declares_the_client_alone_and_the_server_stack_as_it_is_pinned():
    project = tomllib.loads((SERVICES / "pyproject.toml").read_text())["project"]
    assert {line.split(">")[0] for line in project["dependencies"]} == {"httpx", "tqdm"}
    extras = project["optional-dependencies"]
    # The server extra is requirements-pyrender.txt + requirements.txt, less PyOpenGL (see the comment there).
    pinned = [line for line in requirement_lines("requirements-pyrender.txt") + requirement_lines("requirements.txt") if not line.startswith("PyOpenGL")]
    assert extras["server"] == pinned
    assert extras["test"] == requirement_lines("requirements-test.txt")
    assert project["scripts"]["crowdbake-submit"] == "crowdbake.client.submit:main"


def test_the_client_imports_and_runs_without_the_bake_stack():
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); import client_only; client_only.install()\n"
        "import crowdbake.client.submit, crowdbake.client.download as download\n"
        "assert download.full_verifier() is None  # the format readers need numpy: blocked\n"
        "try:\n    import numpy\nexcept ImportError:\n    pass\nelse:\n    raise SystemExit('numpy imported through the blocker')\n"
        "sys.exit(crowdbake.client.submit.main(['--help']))\n"
    )
    result = subprocess.run([sys.executable, "-c", code, str(CLIENT_ONLY.parent)], capture_output=True, text=True, timeout=60,
                            env={"PYTHONPATH": str(SERVICES), "PATH": "/usr/bin:/bin"})
    assert result.returncode == 0, result.stderr
    assert "exit codes:" in result.stdout and "6  timed out" in result.stdout


def stage(name: str, state: str, done: int, total: int) -> dict:
    return {"stage": name, "state": state, "done": done, "total": total}


def bake(progress: float, *stages: dict, state: str = "running", attempt: int = 0) -> dict:
    return {"id": "bk_1", "state": state, "progress": progress, "attempt": attempt, "stages": list(stages)}


def test_progress_never_goes_back_within_an_attempt():
    """The cycle stage counts its candidates (5/5), then its report (1/1); shown raw, 100% fell to 0%
    and then rose again. The overall figure from the server may also dip when a stage is retried."""
    sequence = [
        bake(0.10, stage("cycle", "running", 2, 5)),
        bake(0.20, stage("cycle", "running", 5, 5)),
        bake(0.18, stage("cycle", "running", 0, 1)),
        bake(0.19, stage("cycle", "retrying", 0, 0)),
        bake(0.30, stage("cycle", "succeeded", 1, 1), stage("poses", "running", 1, 4)),
    ]
    progress, overall, cycle = ForwardProgress(), [], []
    for record in sequence:
        progress = advance(progress, record)
        overall.append(progress.overall)
        cycle.append(progress.stages["cycle"])
    assert overall == sorted(overall) and overall[-1] == 0.30
    assert cycle == [0.4, 1.0, 1.0, 1.0, 1.0]
    assert describe(sequence[2], advance(ForwardProgress(attempt=0, overall=0.2, stages={"cycle": 1.0}), sequence[2])) == "bake bk_1: running 20% (cycle 100%)"


def test_a_new_attempt_starts_progress_again():
    first = advance(ForwardProgress(), bake(0.8, stage("pack", "running", 1, 2), state="running"))
    again = advance(first, bake(0.05, stage("validate", "running", 0, 1), attempt=1))
    assert again.attempt == 1 and again.overall == 0.05 and "pack" not in again.stages


@pytest.mark.parametrize("path", ["../x", "/etc/passwd", "a//b", "a/./b", "a\\b", "", "a/.."])
def test_manifest_paths_that_leave_the_bundle_are_refused(path):
    with pytest.raises(ValueError):
        safe_relative_path(path)


def test_manifest_paths_inside_the_bundle_are_kept():
    assert str(safe_relative_path("impostor/uv.cbtx")) == "impostor/uv.cbtx"
