"""POST /v1/bakes/check: a version published from other inputs is refused before any upload, whoever
published it, and another workspace's bake is not revealed.

Regression: `crowdbake submit` checked NAME/VERSION by reading the bundle, its bake and its assets with
its own key. In a workspace that is not shared, a version another key published is invisible to it, so
the 409 "already published from other inputs" still came only after every upload.
"""
from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import pytest

from crowdbake.client.http import ClientError, Exit, Server
from crowdbake.client.preflight import check_name_and_version
from service_fixtures import GOOD_BUNDLE, free_port, make_api, service_env, start_api, tiny_character_glb

CLIENT_ONLY = Path(__file__).resolve().parent / "client_only.py"
NAME, VERSION = "walker", "1.0.0"
PARAMS = {"impostor_frames": 2, "azimuths": 4, "tile_size": 32}
TAKEN = f"{NAME}/{VERSION} is already published from other inputs; bundles never change, choose a new version"
# Another workspace's version, published (public or private) or being baked: one answer, naming nothing of it.
TAKEN_ELSEWHERE = f"{NAME}/{VERSION} is taken by another workspace; bundles never change, choose a new version"


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """Workspaces not shared: key "all" bakes the body of a tiny character and its bake publishes
    walker/1.0.0 (the good vector bundle, recorded as that bake's); key "ci" is another workspace."""
    from crowdbake.storage.bundles import register_bundle
    from crowdbake.storage.db import session_scope

    tmp_path = tmp_path_factory.mktemp("bake_check")
    api = make_api(tmp_path, shared_workspace=False)
    character_path = tmp_path / "walker.glb"
    character_path.write_bytes(tiny_character_glb())
    character = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", character_path.read_bytes())}, headers=api.auth()).json()
    bake = api.client.post("/v1/bakes", json={"name": NAME, "version": VERSION, "character": character["id"], "params": PARAMS}, headers=api.auth())
    assert bake.status_code == 202, bake.text
    store = api.client.app.state.services.bundles
    store.publish(GOOD_BUNDLE, NAME, VERSION)
    with session_scope(api.sessions) as session:
        register_bundle(session, store, NAME, VERSION, False, bake.json()["id"])
    return api, character_path


def _check(api, key: str, character: Path, **changes):
    body = {"name": NAME, "version": VERSION, "inputs": {"character": [hashlib.sha256(character.read_bytes()).hexdigest()]}, "params": PARAMS}
    body.update(changes)
    return api.client.post("/v1/bakes/check", json=body, headers=api.auth(key))


def test_another_workspaces_version_is_taken_and_nothing_more_is_said(published):
    api, character = published
    refused = _check(api, "ci", character)  # the very same inputs: still not this key's bake to reuse
    assert refused.status_code == 409 and refused.headers["content-type"].startswith("application/problem+json")
    assert refused.json()["detail"] == TAKEN_ELSEWHERE
    assert _check(api, "ci", character, params={"azimuths": 8}).json()["detail"] == TAKEN_ELSEWHERE  # no parameter named
    assert _check(api, "ci", character, version="2.0.0").status_code == 204


def test_a_version_another_workspace_is_baking_gets_the_same_answer_as_a_private_one(published):
    """Regression: another workspace's private version answered "already published" and its queued one
    "already being baked", telling which state a version it cannot see is in. Both now answer alike, and
    POST /v1/bakes names no other workspace's bake id."""
    api, character = published
    asset = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", character.read_bytes())}, headers=api.auth()).json()
    queued = api.client.post("/v1/bakes", json={"name": NAME, "version": "3.0.0", "character": asset["id"], "params": PARAMS}, headers=api.auth())
    assert queued.status_code == 202, queued.text
    private, baking = _check(api, "ci", character), _check(api, "ci", character, version="3.0.0")
    assert private.status_code == baking.status_code == 409
    assert baking.json()["detail"] == TAKEN_ELSEWHERE.replace(VERSION, "3.0.0") and private.json()["detail"] == TAKEN_ELSEWHERE
    own = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", character.read_bytes())}, headers=api.auth("ci"))
    assert own.status_code in (200, 201), own.text
    refused = api.client.post("/v1/bakes", json={"name": NAME, "version": "3.0.0", "character": own.json()["id"], "params": PARAMS},
                              headers=api.auth("ci"))
    assert refused.status_code == 409 and refused.json()["detail"] == baking.json()["detail"], refused.text
    assert queued.json()["id"] not in refused.text


def test_the_owners_check_passes_its_own_inputs_and_names_what_differs(published, tmp_path):
    api, character = published
    assert _check(api, "all", character).status_code == 204  # a submit would reuse its bake
    other = tmp_path / "other.glb"
    other.write_bytes(character.read_bytes() + b"\0")
    cases = {"its character has other bytes": _check(api, "all", other),
             "parameter azimuths was 4, this bake asks for 8": _check(api, "all", character, params=dict(PARAMS, azimuths=8)),
             "its bake had no cloth": _check(api, "all", character, inputs={"character": [hashlib.sha256(character.read_bytes()).hexdigest()], "cloth": ["0" * 64]}),
             # Regression: the check refused a timeline role (422), and its digest was never compared.
             "its bake had no timeline": _check(api, "all", character, inputs={"character": [hashlib.sha256(character.read_bytes()).hexdigest()], "timeline": ["1" * 64]}),
             "its manifest time was the default": _check(api, "all", character, created="2006-09-04T12:00:00Z")}
    for reason, response in cases.items():
        assert response.status_code == 409 and reason in response.json()["detail"], (reason, response.text)


def test_a_malformed_check_is_a_problem_naming_the_field(published):
    api, character = published
    response = _check(api, "all", character, inputs={"character": ["not-a-digest"]})
    assert response.status_code == 422 and "inputs" in response.text


def test_an_unknown_key_is_named_by_its_json_pointer(published):
    """An unknown input role was refused (422) as "inputs" alone, leaving the client to guess which key.
    Each error's `where` is now the JSON pointer of the key or value at fault, and the detail lists them."""
    api, character = published
    digest = hashlib.sha256(character.read_bytes()).hexdigest()
    cases = {"/inputs/clothes": {"inputs": {"character": [digest], "clothes": [digest]}},
             "/inputs/cloth": {"inputs": {"character": [digest], "cloth": ["not-a-digest"]}},
             "/inputs/textures~1a": {"inputs": {"character": [digest], "textures/a": [digest]}},  # RFC 6901 escapes "/"
             "/params/azimuth": {"params": dict(PARAMS, azimuth=4)},
             "/colour": {"colour": "red"}}
    for pointer, changes in cases.items():
        response = _check(api, "all", character, **changes)
        assert response.status_code == 422 and response.headers["content-type"].startswith("application/problem+json"), response.text
        problem = response.json()
        assert [error["where"] for error in problem["errors"]] == [pointer] and pointer in problem["detail"], (pointer, problem)
    unknown_role = _check(api, "all", character, **cases["/inputs/clothes"]).json()["errors"][0]
    assert "'clothes' is not an input role" in unknown_role["message"], unknown_role


def test_the_client_refuses_before_uploading_in_another_workspace(published, tmp_path):
    api, character = published
    uploaded_before = api.client.get("/v1/assets", headers=api.auth("ci")).json()["count"]
    api.client.headers["Authorization"] = f"Bearer {api.keys['ci']}"
    with pytest.raises(ClientError) as refused:
        check_name_and_version(Server(api.client, retry_for=1), NAME, VERSION, {"character": [character]}, PARAMS, None)
    assert refused.value.exit_code == Exit.REJECTED and TAKEN_ELSEWHERE in str(refused.value)

    # The whole command against a real server: refused after the parameter check, before any upload.
    port = free_port()
    env = service_env(Path(api.settings.data_dir), "filesystem://", CROWDBAKE_SHARED_WORKSPACE="false",
                      CROWDBAKE_DATABASE_URL=api.settings.database_url)
    process = start_api(env, port, tmp_path / "api.log")
    try:
        command = [sys.executable, str(CLIENT_ONLY), "--server", f"http://127.0.0.1:{port}", str(character), "--name", NAME, "--version", VERSION,
                   "--impostor-frames", "2", "--azimuths", "4", "--tile-size", "32"]
        result = subprocess.run(command, env={**env, "CROWDBAKE_API_KEY": api.keys["ci"]}, capture_output=True, text=True, timeout=60)
    finally:
        process.stop()
    assert result.returncode == Exit.REJECTED, result.stderr
    assert TAKEN_ELSEWHERE in result.stderr.strip().splitlines()[-1] and "uploading" not in result.stderr, result.stderr
    api.client.headers["Authorization"] = f"Bearer {api.keys['ci']}"
    assert api.client.get("/v1/assets").json()["count"] == uploaded_before
