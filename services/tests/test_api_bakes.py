"""Bakes through the real app with the real filesystem broker (no worker here: the enqueued message
is read back from the broker's folder): 202 + Location, parameters validated and recorded,
idempotent resubmission, cancel, retry, scopes."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from service_fixtures import bake_body, make_api, tiny_character_glb, upload_small_assets

PROBLEM = "application/problem+json"


@pytest.fixture
def api(tmp_path):
    return make_api(tmp_path)


@pytest.fixture
def assets(api, tmp_path):
    return upload_small_assets(api, tmp_path)


def queued_messages(api) -> list[dict]:
    """The task messages waiting in the filesystem broker's folder: (task name, args)."""
    messages = []
    for path in sorted((Path(api.settings.broker_dir) / "queue").glob("*.msg")):
        envelope = json.loads(path.read_bytes())
        messages.append({"task": envelope["headers"]["task"], "args": envelope["headers"]["argsrepr"]})
    return messages


def test_create_returns_202_with_location_and_enqueues_validate(api, assets):
    response = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci"))
    assert response.status_code == 202, response.text
    bake = response.json()
    assert response.headers["location"] == f"/v1/bakes/{bake['id']}"
    assert bake["state"] == "queued" and bake["attempt"] == 0 and bake["progress"] == 0.0
    assert [stage["stage"] for stage in bake["stages"]] == ["validate", "loops", "cycle", "probes", "poses", "impostors", "pack", "publish"]
    # The first stage is due (its message sent), the others wait for it.
    assert [stage["state"] for stage in bake["stages"]] == ["queued"] + ["pending"] * 7
    # Parameters are validated, completed with defaults and recorded with the job.
    assert bake["params"]["tile_size"] == 32 and bake["params"]["close"] == "crossfade" and bake["params"]["elevations_deg"] == [0.0, 20.0, 40.0]
    assert bake["inputs"]["textures"] == {"diffuse_0.png": assets["texture"]}
    assert queued_messages(api) == [{"task": "crowdbake.stage.validate", "args": repr([bake["id"], 0])}]
    followed = api.client.get(response.headers["location"], headers=api.auth("bake")).json()
    assert followed["id"] == bake["id"] and "queued" in followed["log"][0]["message"]


def test_resubmission_is_idempotent(api, assets):
    first = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci"))
    again = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci"))
    assert again.status_code == 200 and again.json()["id"] == first.json()["id"]
    assert again.headers["location"] == first.headers["location"]
    assert len(queued_messages(api)) == 1  # nothing enqueued twice
    other = api.client.post("/v1/bakes", json=bake_body(assets, version="1.0.1"), headers=api.auth("ci"))
    assert other.status_code == 202 and other.json()["id"] != first.json()["id"]
    assert other.json()["input_key"] != first.json()["input_key"]


@pytest.mark.parametrize("created", ["2006-09-04 12:00:00", "2006-13-04T12:00:00Z", "yesterday"])
def test_created_must_be_a_real_utc_time(api, assets, created):
    response = api.client.post("/v1/bakes", json=bake_body(assets, created=created), headers=api.auth("ci"))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    assert [error["field"] for error in response.json()["errors"]] == ["created"]
    assert queued_messages(api) == []


def test_created_is_kept_with_the_inputs_and_is_part_of_the_key(api, assets):
    """The manifest time shapes the bundle's bytes, so the same inputs with another time are another bake."""
    plain = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci")).json()
    dated = api.client.post("/v1/bakes", json=bake_body(assets, version="1.0.1", created="2006-09-04T12:00:00Z"), headers=api.auth("ci"))
    later = api.client.post("/v1/bakes", json=bake_body(assets, version="1.0.1", created="2006-09-05T12:00:00Z"), headers=api.auth("ci"))
    assert dated.status_code == 202 and dated.json()["inputs"]["created"] == "2006-09-04T12:00:00Z"
    assert "created" not in plain["inputs"]
    assert later.status_code == 409  # same name/version, other inputs: a different bake, already baking


def test_same_version_from_other_inputs_conflicts_while_baking(api, assets):
    assert api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci")).status_code == 202
    response = api.client.post("/v1/bakes", json=bake_body(assets, params={"tile_size": 64}), headers=api.auth("ci"))
    assert response.status_code == 409 and response.headers["content-type"] == PROBLEM


@pytest.mark.parametrize("params,field", [
    ({"tile_size": 30}, "params.tile_size"),
    ({"impostor_frames": 0}, "params.impostor_frames"),
    ({"close": "cubic"}, "params.close"),
    ({"elevations_deg": [0, 95]}, "params.elevations_deg"),
    ({"lod_ratio": 0.5, "lod_triangles": 100}, "params"),
    ({"unknown_knob": 1}, "params.unknown_knob"),
])
def test_invalid_parameters_are_problems_naming_the_field(api, assets, params, field):
    response = api.client.post("/v1/bakes", json=bake_body(assets, params=params), headers=api.auth("ci"))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    body = response.json()
    assert body["type"] == "/problems/validation-error"
    assert any(error["field"] == field for error in body["errors"]), body["errors"]
    assert queued_messages(api) == []


def test_unknown_assets_and_reserved_version(api, assets):
    response = api.client.post("/v1/bakes", json=bake_body(assets, character="as_nope", cloth=assets["character"]), headers=api.auth("ci"))
    assert response.status_code == 422
    assert {error["field"] for error in response.json()["errors"]} == {"character", "cloth"}
    response = api.client.post("/v1/bakes", json=bake_body(assets, version="latest"), headers=api.auth("ci"))
    assert response.status_code == 422 and response.json()["errors"][0]["field"] == "version"
    response = api.client.post("/v1/bakes", json=bake_body(assets, textures={"albedo.png": assets["texture"]}), headers=api.auth("ci"))
    assert response.status_code == 422 and response.json()["errors"][0]["field"] == "textures"


def test_ids_with_nul_or_odd_characters_name_nothing(api, assets):
    """A NUL in an id once reached PostgreSQL (which refuses text holding NUL) as a server error; such an
    id is as unknown as any other, wherever it comes from."""
    response = api.client.post("/v1/bakes", json=bake_body(assets, cloth="\u0000", textures={"diffuse_0.png": "as_\u0000x"}), headers=api.auth("ci"))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    assert {error["field"] for error in response.json()["errors"]} == {"cloth", "textures.diffuse_0.png"}, response.json()
    for path in ("/v1/bakes/%00", "/v1/assets/%00", "/v1/bakes/bk_%00/log", f"/v1/bakes/{'b' * 65}"):
        missing = api.client.get(path, headers=api.auth("ci"))
        assert missing.status_code == 404 and missing.headers["content-type"] == PROBLEM, (path, missing.text)
    odd_name = api.client.get("/v1/bakes", params={"name": "walker\x00"}, headers=api.auth("bake"))
    assert odd_name.status_code == 422 and odd_name.headers["content-type"] == PROBLEM
    # An upload's file name is a label: control characters are dropped, the file is kept.
    uploaded = api.client.post("/v1/assets/characters", files={"file": ("walk\x00er\x07.glb", tiny_character_glb())}, headers=api.auth("upload"))
    assert uploaded.status_code in (200, 201), uploaded.text
    assert uploaded.json()["filename"] == "walker.glb"


def test_too_few_frames_for_the_requested_cycle(api, assets):
    response = api.client.post("/v1/bakes", json=bake_body(assets, params={"cycle_frames": 7}), headers=api.auth("ci"))
    assert response.status_code == 422 and response.json()["type"] == "/problems/invalid-file"
    assert "too few frames for two cycles" in response.json()["errors"][0]["message"]


def test_cycle_length_comes_from_the_animation_or_the_parameters(api, assets):
    still = api.client.post("/v1/assets/characters", files={"file": ("still.glb", tiny_character_glb(animated=False))}, headers=api.auth("upload")).json()
    response = api.client.post("/v1/bakes", json=bake_body(assets, character=still["id"]), headers=api.auth("ci"))
    assert response.status_code == 422 and response.json()["errors"][0]["field"] == "params.cycle_frames"
    response = api.client.post("/v1/bakes", json=bake_body(assets, character=still["id"], params={"cycle_frames": 6}), headers=api.auth("ci"))
    assert response.status_code == 202, response.text


def test_scopes(api, assets):
    assert api.client.post("/v1/bakes", json=bake_body(assets)).status_code == 401
    assert api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("upload")).status_code == 403
    # baking without publishing needs only the bake scope; publishing needs the publish scope too
    assert api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("bake")).status_code == 403
    response = api.client.post("/v1/bakes", json=bake_body(assets, publish=False), headers=api.auth("bake"))
    assert response.status_code == 202
    assert api.client.get(f"/v1/bakes/{response.json()['id']}", headers=api.auth("read")).status_code == 403


def test_cancel_then_retry(api, assets):
    bake = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci")).json()
    assert api.client.post(f"/v1/bakes/{bake['id']}/retry", headers=api.auth("bake")).status_code == 409  # still queued
    cancelled = api.client.post(f"/v1/bakes/{bake['id']}/cancel", headers=api.auth("bake"))
    assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
    assert {stage["state"] for stage in cancelled.json()["stages"]} == {"cancelled"}
    again = api.client.post(f"/v1/bakes/{bake['id']}/cancel", headers=api.auth("bake"))
    assert again.status_code == 409 and again.json()["type"] == "/problems/invalid-state"
    # A cancelled bake is not reused by a resubmission: a new bake starts...
    fresh = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci"))
    assert fresh.status_code == 202 and fresh.json()["id"] != bake["id"]
    # ...and holds the inputs and the version: the old one cannot run beside it in the same work folder.
    blocked = api.client.post(f"/v1/bakes/{bake['id']}/retry", headers=api.auth("bake"))
    assert blocked.status_code == 409 and blocked.json()["type"] == "/problems/conflict", blocked.text
    assert api.client.post(f"/v1/bakes/{fresh.json()['id']}/cancel", headers=api.auth("bake")).status_code == 202
    retried = api.client.post(f"/v1/bakes/{bake['id']}/retry", headers=api.auth("bake"))
    assert retried.status_code == 202
    assert retried.json()["attempt"] == 1 and retried.json()["state"] == "queued"
    assert queued_messages(api)[-1]["args"] == repr([bake["id"], 1])
    log = api.client.get(f"/v1/bakes/{bake['id']}/log", headers=api.auth("bake"))
    assert log.headers["content-type"].startswith("text/plain")
    assert [line.split()[-1] for line in log.text.splitlines()][-2:] == ["cancelled", "1"]


def test_listing_and_not_found(api, assets):
    created = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci")).json()
    listing = api.client.get("/v1/bakes?state=queued", headers=api.auth("bake")).json()
    assert [bake["id"] for bake in listing["data"]] == [created["id"]]
    assert api.client.get("/v1/bakes?state=failed", headers=api.auth("bake")).json()["count"] == 0
    missing = api.client.get("/v1/bakes/bk_nope", headers=api.auth("bake"))
    assert missing.status_code == 404 and missing.headers["content-type"] == PROBLEM


def test_worker_errors_are_classified():
    """Bad input and version conflicts fail a bake at once; a busy database or a full disk is retried."""
    import errno

    from sqlalchemy.exc import OperationalError

    from crowdbake.errors import InputError, VersionConflict
    from crowdbake.jobs.failures import describe_error, is_transient as _is_transient

    bad = describe_error(InputError("lod_triangles 9 is not below 4", "lod_triangles"), "validate")
    assert bad == {"type": "invalid-input", "title": "the inputs cannot be baked", "detail": "lod_triangles 9 is not below 4", "field": "lod_triangles"}
    assert describe_error(VersionConflict("walker/1.0.0 differs"), "publish")["type"] == "version-conflict"
    crash = describe_error(ZeroDivisionError("division by zero"), "pack")
    assert crash["type"] == "stage-failed" and crash["detail"] == "ZeroDivisionError: division by zero"
    assert _is_transient(OSError(errno.ENOSPC, "No space left on device"))
    assert _is_transient(OperationalError("UPDATE", {}, Exception("database is locked")))
    assert not _is_transient(FileNotFoundError(errno.ENOENT, "gone"))
    assert not _is_transient(InputError("bad", "cloth"))


@pytest.mark.parametrize("route, scope", [("/v1/bakes", "bake"), ("/v1/assets", "upload")])
def test_huge_list_offset_is_a_problem_not_a_server_error(api, route, scope):
    """Regression: an offset beyond SQLite's 64-bit integers raised OverflowError, a 500."""
    response = api.client.get(f"{route}?offset=99999999999999999999", headers=api.auth(scope))
    assert response.status_code == 422
    assert response.headers["content-type"].startswith("application/problem+json")
