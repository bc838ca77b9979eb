"""`crowdbake submit --json` through every exit code, against a real server: uvicorn and a Celery
worker as subprocesses on the filesystem broker (no Redis needed), the procedural sample character.

The command runs as the client distribution would (client_only.py: numpy, fastapi, pydantic and the
rest of the server's stack cannot be imported), so these tests also show the client needs none of it.

    0 done            a bake followed across a restart of the API, downloaded, every sha256 checked
    1 bake failed     a parameter the API accepts and the worker's validate stage refuses
    2 usage           --download with --no-publish; refused before any upload
    3 input rejected  a bad --name (refused before any upload), a truncated cloth cache
    4 auth            an unknown key, a key without the upload scope (refused before any upload)
    5 unreachable     a port nobody listens on, after retrying
    6 timed out       --timeout shorter than the bake, which goes on on the server
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from baked_service import PARAMS
from live_service import Service, live_service
from service_fixtures import free_port

# slow: a real server and worker (or browser) for tens of seconds; scripts/test.sh runs it with CROWDBAKE_SLOW_TESTS=1, as CI does
pytestmark = [pytest.mark.integration, pytest.mark.slow]

CLIENT_ONLY = Path(__file__).resolve().parent / "client_only.py"
BAKE_FLAGS = ["--impostor-frames", str(PARAMS["impostor_frames"]), "--azimuths", str(PARAMS["azimuths"]),
              "--elevations", ",".join(str(value) for value in PARAMS["elevations_deg"]), "--tile-size", str(PARAMS["tile_size"]),
              "--candidates", str(PARAMS["candidates"]), "--cycle-views", str(PARAMS["cycle_views"])]
BAKE_TIMEOUT_S = 240
NAME = "exit-codes"


@pytest.fixture(scope="module")
def service(tmp_path_factory, small_sample):
    with live_service(tmp_path_factory.mktemp("exit-codes"), small_sample) as running:
        yield running


def command(service: Service, version: str, *extra: str, server: str | None = None, cloth: Path | None = None) -> list[str]:
    sample = service.sample
    return [sys.executable, str(CLIENT_ONLY), "--server", server or service.url, str(sample / "character.glb"),
            "--cloth", str(cloth or sample / "cloth.pc2"), "--cloth-mesh", str(sample / "cloth.obj"), "--textures", str(sample / "textures"),
            "--name", NAME, "--version", version, "--json", "--poll", "0.3", "--timeout", str(BAKE_TIMEOUT_S), *BAKE_FLAGS, *extra]


def run_submit(service: Service, args: list[str], key: str | None = "all", timeout: float = BAKE_TIMEOUT_S + 60) -> tuple[int, dict, str]:
    env = dict(service.env, CROWDBAKE_API_KEY=service.keys[key] if key in service.keys else (key or ""))
    result = subprocess.run(args, env=env, capture_output=True, text=True, timeout=timeout)
    return result.returncode, parse_json(result.stdout, result.stderr), result.stderr


def parse_json(stdout: str, stderr: str) -> dict:
    lines = stdout.strip().splitlines()
    assert len(lines) == 1, f"--json prints one line on stdout, got:\n{stdout}\nstderr:\n{stderr}"
    return json.loads(lines[0])


def assert_outcome(code: int, outcome: dict, stderr: str, expected: int) -> None:
    assert code == expected, f"exit {code}, expected {expected}\n{json.dumps(outcome, indent=1)}\n{stderr}"
    assert outcome["exit_code"] == expected
    last = stderr.strip().splitlines()[-1] if expected else ""
    if expected:
        assert last.startswith("crowdbake submit: error: "), stderr  # one line saying what went wrong
        assert outcome["problem"] and outcome["problem"]["detail"]


def test_exit_2_usage_is_refused_before_uploading(service, tmp_path):
    before = service.asset_count()
    code, outcome, stderr = run_submit(service, command(service, "2.0.0", "--download", str(tmp_path), "--no-publish"))
    assert_outcome(code, outcome, stderr, 2)
    assert "--no-publish" in outcome["problem"]["detail"] and outcome["bake_id"] is None
    # A flag argparse refuses is a usage error with the same JSON object.
    code, outcome, stderr = run_submit(service, command(service, "2.0.0", "--tile-size", "many"))
    assert code == 2 and outcome["exit_code"] == 2 and "--tile-size" in outcome["problem"]["detail"]
    assert service.asset_count() == before


def test_exit_3_bad_name_is_refused_by_the_server_before_uploading(service):
    before = service.asset_count()
    args = command(service, "3.0.0")
    args[args.index("--name") + 1] = "Not A Name!"
    code, outcome, stderr = run_submit(service, args)
    assert_outcome(code, outcome, stderr, 3)
    assert outcome["problem"]["status"] == 422 and [error["field"] for error in outcome["problem"]["errors"]] == ["name"]
    assert service.asset_count() == before  # nothing was uploaded
    # So are parameters the server's schema refuses (the pipeline's limits).
    code, outcome, stderr = run_submit(service, command(service, "3.0.0", "--tile-size", "30"))
    assert_outcome(code, outcome, stderr, 3)
    assert outcome["problem"]["errors"][0]["field"] == "params.tile_size" and service.asset_count() == before


def test_exit_3_a_file_the_server_rejects(service, tmp_path):
    truncated = tmp_path / "cloth.pc2"
    truncated.write_bytes((service.sample / "cloth.pc2").read_bytes()[:-12])
    code, outcome, stderr = run_submit(service, command(service, "3.1.0", cloth=truncated))
    assert_outcome(code, outcome, stderr, 3)
    assert outcome["problem"]["status"] == 422 and outcome["problem"]["errors"][0]["field"] == "cache"
    assert "uploading cloth" in stderr.splitlines()[-1]


def test_exit_4_unknown_key_and_missing_scope_before_uploading(service):
    before = service.asset_count()
    code, outcome, stderr = run_submit(service, command(service, "4.0.0"), key="cbk_unknown_0000000000000000")
    assert_outcome(code, outcome, stderr, 4)
    assert outcome["problem"]["status"] == 401
    code, outcome, stderr = run_submit(service, command(service, "4.0.0"), key="read")
    assert_outcome(code, outcome, stderr, 4)
    assert outcome["problem"]["status"] == 403
    code, outcome, stderr = run_submit(service, command(service, "4.0.0"), key="")
    assert_outcome(code, outcome, stderr, 4)
    assert service.asset_count() == before


def test_exit_5_unreachable_after_retrying(service):
    closed = f"http://127.0.0.1:{free_port()}"
    started = time.monotonic()
    code, outcome, stderr = run_submit(service, command(service, "5.0.0", "--retry-for", "2", server=closed), timeout=60)
    assert_outcome(code, outcome, stderr, 5)
    assert outcome["retries"] >= 2 and "retrying in" in stderr  # backoff 0.5 s, 1 s, ... within 2 s
    assert time.monotonic() - started < 30


def test_exit_6_timed_out_while_the_bake_goes_on(service):
    code, outcome, stderr = run_submit(service, command(service, "6.0.0", "--wait", "--timeout", "1"))
    assert_outcome(code, outcome, stderr, 6)
    assert outcome["bake_id"] and outcome["state"] in ("queued", "running")
    with service.client() as client:  # it does go on; cancel it to leave the worker to the next test
        assert client.get(f"/v1/bakes/{outcome['bake_id']}").json()["state"] in ("queued", "running", "succeeded")
        client.post(f"/v1/bakes/{outcome['bake_id']}/cancel")


def test_exit_1_bake_failed_in_a_worker(service):
    code, outcome, stderr = run_submit(service, command(service, "1.0.0-broken", "--lod-triangles", "100000000", "--wait"))
    assert_outcome(code, outcome, stderr, 1)
    assert outcome["state"] == "failed" and outcome["problem"]["stage"] == "validate" and outcome["problem"]["field"]
    assert "failed in validate" in stderr.splitlines()[-1]


def test_exit_0_follows_the_bake_across_an_api_restart_and_downloads(service, tmp_path):
    from crowdbake.formats.bundle import verify_bundle

    downloads = tmp_path / "downloads"
    env = dict(service.env, CROWDBAKE_API_KEY=service.keys["all"])
    process = subprocess.Popen(command(service, "1.0.0", "--download", str(downloads)), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # Restart the API once the bake is under way: the client must wait for it and carry on.
        deadline = time.monotonic() + BAKE_TIMEOUT_S
        with service.client() as client:
            while True:
                assert process.poll() is None, process.communicate()
                bakes = client.get("/v1/bakes", params={"limit": 5}).json()["data"]
                if any(bake["version"] == "1.0.0" and bake["state"] == "running" for bake in bakes):
                    break
                assert time.monotonic() < deadline
                time.sleep(0.2)
        service.restart_api(down_s=3.0)
        stdout, stderr = process.communicate(timeout=BAKE_TIMEOUT_S + 60)
    finally:
        if process.poll() is None:
            process.kill()
    outcome = parse_json(stdout, stderr)
    assert_outcome(process.returncode, outcome, stderr, 0)
    assert outcome["state"] == "succeeded" and outcome["progress"] == 1.0 and outcome["problem"] is None
    assert outcome["retries"] >= 1 and "retrying in" in stderr
    folder = Path(outcome["bundle"])
    assert folder == downloads / NAME / "1.0.0"
    # The client alone checks sizes and hashes; the full package checks the formats too (here).
    assert outcome["verified"].startswith("size and sha256 of ") and "binary formats" not in outcome["verified"]
    verify_bundle(folder)

    # Progress lines (stderr is not a terminal): the overall percentage never goes back, and no it/s.
    percents = [int(match) for match in re.findall(rf"^bake {outcome['bake_id']}: \w+ (\d+)%", stderr, re.MULTILINE)]
    assert len(percents) >= 2 and percents == sorted(percents), percents
    for stage, values in stage_percents(stderr).items():
        assert values == sorted(values), (stage, values)
    assert "it/s" not in stderr
    shutil.rmtree(downloads)


def stage_percents(stderr: str) -> dict[str, list[int]]:
    """Stage -> the percentages the progress lines showed for it, in order."""
    found: dict[str, list[int]] = {}
    for inside in re.findall(r"^bake \S+: \w+ \d+% \((.*)\)$", stderr, re.MULTILINE):
        for stage, percent in re.findall(r"(\w+) (\d+)%", inside):
            found.setdefault(stage, []).append(int(percent))
    return found


def test_exit_0_a_character_without_cloth_bakes_and_exports(service, tmp_path):
    """`crowdbake submit CHAR.glb` with no --cloth bakes the body alone (its animation's loop) through the
    real server and worker, and its engine export passes the glTF-Validator like a clothed one's.
    Regression: --cloth was required, though the server takes `cloth: null`."""
    from test_export import check_export

    sample = service.sample
    args = [sys.executable, str(CLIENT_ONLY), "--server", service.url, str(sample / "character.glb"), "--textures", str(sample / "textures"),
            "--name", "plain", "--version", "1.0.0", "--json", "--poll", "0.3", "--timeout", str(BAKE_TIMEOUT_S),
            "--impostor-frames", "2", "--azimuths", "4", "--elevations", "0,30", "--tile-size", "32",
            "--download", str(tmp_path / "bundles"), "--export-out", str(tmp_path / "exports")]
    code, outcome, stderr = run_submit(service, args)
    assert_outcome(code, outcome, stderr, 0)
    assert "cloth" not in stderr, stderr  # nothing uploaded as cloth
    with service.client() as client:
        bake = client.get(f"/v1/bakes/{outcome['bake_id']}").json()
    assert bake["state"] == "succeeded" and "cloth" not in bake["inputs"]
    bundle = Path(outcome["bundle"])
    from crowdbake.formats.bundle import verify_bundle

    manifest = verify_bundle(bundle).manifest
    assert {mesh["kind"] for mesh in manifest["meshes"]} == {"body"}
    check_export(bundle, tmp_path / "exports" / "plain" / "1.0.0")


def test_exit_2_cloth_mesh_without_cloth(service):
    sample = service.sample
    args = [sys.executable, str(CLIENT_ONLY), "--server", service.url, str(sample / "character.glb"), "--cloth-mesh", str(sample / "cloth.obj"),
            "--name", "plain", "--version", "2.0.0", "--json"]
    code, outcome, stderr = run_submit(service, args)
    assert_outcome(code, outcome, stderr, 2)
    assert "--cloth-mesh goes with --cloth" in stderr.splitlines()[-1]
