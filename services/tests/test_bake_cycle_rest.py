"""A chosen cycle over REST gives the bundle `crowdbake bake --cycle` gives.

`crowdbake cycle` picks a cycle of the session's procedural sample (the `small_sample` fixture) once;
`crowdbake submit --cycle` sends it (cycle.json and the looped.pc2 beside it) to a real service (uvicorn
and a Celery worker on the filesystem broker: no Redis needed) and downloads the bundle; the CLI bakes
the same files with --cycle. The two manifests are the same document.
"""
from __future__ import annotations

import json

import httpx
import pytest

from crowdbake.cli import main as cli_main
from live_service import live_service

CREATED = "2006-09-04T12:00:00Z"  # both bakes get the manifest time, so only the inputs can differ
# baked_service.PARAMS (small enough to bake in seconds) as options of `crowdbake bake` and `submit`.
BAKE_OPTIONS = ["--impostor-frames", "2", "--azimuths", "4", "--elevations", "0,30", "--tile-size", "32",
                "--candidates", "2", "--cycle-views", "2"]

pytestmark = pytest.mark.slow  # a cycle search and two bakes of the sample, about two minutes on 2 cores


def test_a_rest_bake_with_a_cycle_gives_the_bundle_the_cli_gives(small_sample, tmp_path):
    files = small_sample
    chosen = tmp_path / "chosen"
    assert cli_main(["cycle", str(files / "cloth.pc2"), "--mesh", str(files / "cloth.obj"), "--character", str(files / "character.glb"),
                     "--candidates", "2", "--views", "2", "--out", str(chosen)]) == 0
    cycle = json.loads((chosen / "cycle.json").read_text())
    assert (chosen / "looped.pc2").is_file()

    with live_service(tmp_path / "service", files) as service:
        assert cli_main(["submit", str(files / "character.glb"), "--server", service.url, "--key", service.keys["all"],
                         "--cloth", str(files / "cloth.pc2"), "--cloth-mesh", str(files / "cloth.obj"), "--textures", str(files / "textures"),
                         "--cycle", str(chosen / "cycle.json"), "--name", "walker", "--version", "1.0.0", "--created", CREATED,
                         "--download", str(tmp_path / "downloaded"), "--poll", "0.3", "--timeout", "300", *BAKE_OPTIONS]) == 0, \
            service.worker.tail(60)
        with httpx.Client(base_url=service.url, headers={"Authorization": f"Bearer {service.keys['all']}"}) as client:
            bake, = client.get("/v1/bakes").json()["data"]
            cycles = client.get("/v1/assets", params={"kind": "cycle"}).json()["data"]
    assert [set(asset["files"]) for asset in cycles] == [{"file", "looped"}]
    assert bake["state"] == "succeeded" and bake["inputs"]["cycle"] == cycles[0]["id"]
    rest_manifest = json.loads((tmp_path / "downloaded" / "walker" / "1.0.0" / "manifest.json").read_bytes())

    out = tmp_path / "bundles"
    assert cli_main(["bake", str(files / "character.glb"), "--cloth", str(files / "cloth.pc2"), "--cloth-mesh", str(files / "cloth.obj"),
                     "--textures", str(files / "textures"), "--cycle", str(chosen / "cycle.json"), "--name", "walker", "--version", "1.0.0",
                     "--out", str(out), "--json", "--created", CREATED, *BAKE_OPTIONS]) == 0
    cli_manifest = json.loads((out / "walker" / "1.0.0" / "manifest.json").read_bytes())

    assert rest_manifest["clips"][0]["source_start_frame"] == cli_manifest["clips"][0]["source_start_frame"] == cycle["start_frame"]
    assert rest_manifest == cli_manifest
