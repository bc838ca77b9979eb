"""`created` in a REST bake request reaches the manifest as `crowdbake bake --created` does.

A real Celery worker (subprocess, filesystem broker: no Redis needed) bakes a REST request that gives
`created`, on the session's procedural sample (the `small_sample` fixture); the CLI bakes the same files
with the same options and --created. Both manifests carry the
given time, and since every option that shapes the bundle is a REST field (test_layout), the two
manifests are the same document.
"""
from __future__ import annotations

import json
import time

import pytest

from crowdbake.cli import main as cli_main
from baked_service import PARAMS
from service_fixtures import make_api, service_env, start_worker

CREATED = "2006-09-04T12:00:00Z"  # not the files' time, nor now: only the request can have put it there
# baked_service.PARAMS (small enough to bake in seconds) as `crowdbake bake` options.
CLI_PARAMS = ["--impostor-frames", "2", "--azimuths", "4", "--elevations", "0,30", "--tile-size", "32",
              "--candidates", "2", "--cycle-views", "2"]
BAKE_TIMEOUT_S = 240

pytestmark = pytest.mark.slow  # two bakes of the sample, about a minute on 2 cores


def test_a_rest_bake_with_created_gives_the_manifest_time_the_cli_gives(small_sample, tmp_path, capsys):
    files = small_sample
    api = make_api(tmp_path / "service")
    upload = api.auth("upload")
    character = api.client.post("/v1/assets/characters", files={"file": ("character.glb", (files / "character.glb").read_bytes())}, headers=upload)
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("cloth.pc2", (files / "cloth.pc2").read_bytes()),
                                                        "mesh": ("cloth.obj", (files / "cloth.obj").read_bytes())}, headers=upload)
    assert character.status_code == cloth.status_code == 201, (character.text, cloth.text)
    textures = {}
    for path in sorted((files / "textures").glob("*.png")):
        answer = api.client.post("/v1/assets/textures", files={"file": (path.name, path.read_bytes())}, headers=upload)
        assert answer.status_code == 201, answer.text
        textures[path.name] = answer.json()["id"]
    body = {"name": "walker", "version": "1.0.0", "character": character.json()["id"], "cloth": cloth.json()["id"],
            "textures": textures, "params": PARAMS, "created": CREATED}
    created = api.client.post("/v1/bakes", json=body, headers=api.auth("ci"))
    assert created.status_code == 202, created.text

    # The worker shares the API's database (a PostgreSQL one when scripts/test.sh started a server).
    env = service_env(api.settings.data_dir, api.settings.broker_url, CROWDBAKE_DATABASE_URL=api.settings.database_url)
    worker = start_worker(env, tmp_path / "worker.log", concurrency=1)
    try:
        deadline = time.monotonic() + BAKE_TIMEOUT_S
        while (bake := api.client.get(created.headers["location"], headers=api.auth("all")).json())["state"] not in ("succeeded", "failed"):
            assert time.monotonic() < deadline and worker.popen.poll() is None, worker.tail(60)
            time.sleep(0.5)
    finally:
        worker.stop()
    assert bake["state"] == "succeeded", (bake["error"], worker.tail(60))
    rest_manifest = api.client.get("/v1/bundles/walker/1.0.0/manifest.json", headers=api.auth("read")).json()

    out = tmp_path / "bundles"
    assert cli_main(["bake", str(files / "character.glb"), "--cloth", str(files / "cloth.pc2"), "--cloth-mesh", str(files / "cloth.obj"),
                     "--textures", str(files / "textures"), "--name", "walker", "--version", "1.0.0", "--out", str(out),
                     "--json", "--created", CREATED, *CLI_PARAMS]) == 0
    cli_manifest = json.loads((out / "walker" / "1.0.0" / "manifest.json").read_bytes())
    # stderr is no terminal here (as in a CI job): each stage still says when it starts and ends.
    log = capsys.readouterr().err
    for stage in ("validate", "cycle", "probes", "poses", "impostors", "pack", "publish"):
        assert f"bake: {stage} started" in log and f"bake: {stage} done in" in log, log[-2000:]
    # A stage is done when all its nodes are: the poses stage's choice waits for the probes.
    assert log.index("bake: probes done in") < log.index("bake: poses done in"), log[-2000:]

    assert rest_manifest["created"] == cli_manifest["created"] == CREATED
    assert rest_manifest == cli_manifest
