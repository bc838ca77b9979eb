"""Ownership with two keys, in the default mode (no shared workspace): every route that names an asset,
a bake or a bundle answers another key's resource as if it did not exist (404, or a validation error
naming the field for a bake's inputs), lists only the caller's own, and an admin key sees everything.

The app is the real one with the filesystem broker (no worker runs: bakes stay queued unless the test
moves them on through the database, as a worker would)."""
from __future__ import annotations

import pytest

from service_fixtures import make_api, obj_bytes, pc2_bytes, png_bytes, publish_vector_bundle, tiny_character_glb, tiny_cloth

EVERYTHING = "upload,bake,publish,read"


@pytest.fixture
def api(tmp_path):
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.keys import create_api_key

    api = make_api(tmp_path, shared_workspace=False)
    with session_scope(api.sessions) as session:
        for name, scopes in {"alice": EVERYTHING, "bob": EVERYTHING, "operator": EVERYTHING + ",admin"}.items():
            api.keys[name], _ = create_api_key(session, scopes, name)
    return api


def upload_assets(api, who: str, tmp_path) -> dict[str, str]:
    points, faces = tiny_cloth(frames=12)
    auth = api.auth(who)
    character = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", tiny_character_glb())}, headers=auth)
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))}, headers=auth)
    texture = api.client.post("/v1/assets/textures", files={"file": ("d.png", png_bytes())}, headers=auth)
    assert {character.status_code, cloth.status_code, texture.status_code} == {201}, (character.text, cloth.text, texture.text)
    return {"character": character.json()["id"], "cloth": cloth.json()["id"], "texture": texture.json()["id"]}


def bake_body(assets, version="1.0.0", **changes):
    body = {"name": "walker", "version": version, "character": assets["character"], "cloth": assets["cloth"],
            "textures": {"diffuse_0.png": assets["texture"]}, "params": {"impostor_frames": 2, "azimuths": 4, "tile_size": 32}}
    body.update(changes)
    return body


def test_assets_are_their_uploaders(api, tmp_path):
    alice = upload_assets(api, "alice", tmp_path)
    # The same bytes from bob are bob's own asset (the blobs are stored once).
    bob = upload_assets(api, "bob", tmp_path)
    assert set(alice.values()).isdisjoint(bob.values())
    for asset_id in alice.values():
        assert api.client.get(f"/v1/assets/{asset_id}", headers=api.auth("alice")).status_code == 200
        missing = api.client.get(f"/v1/assets/{asset_id}", headers=api.auth("bob"))
        assert missing.status_code == 404 and missing.json()["type"] == "/problems/not-found"
        assert api.client.get(f"/v1/assets/{asset_id}", headers=api.auth("operator")).status_code == 200
    listed = {who: {asset["id"] for asset in api.client.get("/v1/assets", headers=api.auth(who)).json()["data"]} for who in ("alice", "bob", "operator")}
    assert listed["alice"] == set(alice.values()) and listed["bob"] == set(bob.values())
    assert listed["operator"] == set(alice.values()) | set(bob.values())


def test_a_bake_cannot_use_another_keys_assets(api, tmp_path):
    alice = upload_assets(api, "alice", tmp_path)
    response = api.client.post("/v1/bakes", json=bake_body(alice), headers=api.auth("bob"))
    assert response.status_code == 422
    assert {error["field"] for error in response.json()["errors"]} == {"character", "cloth", "textures.diffuse_0.png"}


def test_every_bake_route_hides_another_keys_bake(api, tmp_path):
    alice = upload_assets(api, "alice", tmp_path)
    bake = api.client.post("/v1/bakes", json=bake_body(alice), headers=api.auth("alice"))
    assert bake.status_code == 202, bake.text
    bake_id = bake.json()["id"]
    bob = api.auth("bob")
    for method, path in (("GET", f"/v1/bakes/{bake_id}"), ("GET", f"/v1/bakes/{bake_id}/log"), ("POST", f"/v1/bakes/{bake_id}/cancel"),
                         ("POST", f"/v1/bakes/{bake_id}/retry"), ("POST", f"/v1/bakes/{bake_id}/publish"),
                         ("GET", f"/v1/bakes/{bake_id}/cycle/report.html")):
        response = api.client.request(method, path, headers=bob)
        assert response.status_code == 404, (method, path, response.status_code)
        assert bake_id in response.json()["detail"]
    assert api.client.get("/v1/bakes", headers=bob).json()["count"] == 0
    assert [row["id"] for row in api.client.get("/v1/bakes", headers=api.auth("alice")).json()["data"]] == [bake_id]
    assert [row["id"] for row in api.client.get("/v1/bakes", headers=api.auth("operator")).json()["data"]] == [bake_id]
    # Bob's identical submission from his own assets is his own bake, not alice's handed over.
    bob_assets = upload_assets(api, "bob", tmp_path)
    bobs = api.client.post("/v1/bakes", json=bake_body(bob_assets, version="2.0.0"), headers=bob)
    assert bobs.status_code == 202 and bobs.json()["id"] != bake_id
    # The owner and an admin can act on it.
    assert api.client.get(f"/v1/bakes/{bake_id}/log", headers=api.auth("alice")).status_code == 200
    assert api.client.post(f"/v1/bakes/{bake_id}/cancel", headers=api.auth("operator")).status_code == 202
    assert api.client.post(f"/v1/bakes/{bake_id}/retry", headers=api.auth("alice")).status_code == 202


def _alices_bundle(api, tmp_path) -> tuple[str, str]:
    """A bundle published from a bake alice created (the bundle record names the bake)."""
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.models import Bundle

    assets = upload_assets(api, "alice", tmp_path)
    bake_id = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("alice")).json()["id"]
    name, version = publish_vector_bundle(api)
    with session_scope(api.sessions) as session:
        session.query(Bundle).filter_by(name=name, version=version).one().bake_id = bake_id
    return name, version


def test_private_bundles_are_their_publishers(api, tmp_path):
    name, version = _alices_bundle(api, tmp_path)
    base = f"/v1/bundles/{name}/{version}"
    for who, status in (("alice", 200), ("bob", 404), ("operator", 200)):
        auth = api.auth(who)
        assert api.client.get(f"{base}/manifest.json", headers=auth).status_code == status, who
        assert api.client.get(base, headers=auth).status_code == status, who
        assert api.client.get(f"/v1/bundles/{name}/latest/manifest.json", headers=auth).status_code == status, who
        assert api.client.get(f"/v1/bundles/{name}", headers=auth).status_code == status, who
        assert (name in api.client.get("/v1/bundles", headers=auth).json()["names"]) == (status == 200), who
    # Bob can neither publish it nor hide it; alice can.
    assert api.client.patch(base, json={"public": True}, headers=api.auth("bob")).status_code == 404
    assert api.client.patch(base, json={"public": True}, headers=api.auth("alice")).status_code == 200
    # Public: anyone reads it, bob included, but still cannot change it.
    assert api.client.get(f"{base}/manifest.json", headers=api.auth("bob")).status_code == 200
    assert api.client.get(f"{base}/manifest.json").status_code == 200
    assert api.client.patch(base, json={"public": False}, headers=api.auth("bob")).status_code == 404
    assert api.client.patch(base, json={"public": False}, headers=api.auth("operator")).status_code == 200
    assert api.client.get(f"{base}/manifest.json", headers=api.auth("bob")).status_code == 404


def test_a_private_bundle_answers_as_a_missing_one(api, tmp_path):
    """Without a key, or with another workspace's, a private version is told apart from a missing one by
    nothing: the same status, type and detail (names aside). Anonymous callers once got 401 "not public"
    for a private version and 404 for a missing one, which told anyone the version exists."""
    name, version = _alices_bundle(api, tmp_path)
    urls = ["{n}/{v}/manifest.json", "{n}/{v}", "{n}/latest/manifest.json", "{n}", "{n}/{v}/files/cycle/cycle.json", "{n}/{v}/export.zip"]

    def answer(url: str, who: str | None, bundle: tuple[str, str]) -> tuple:
        response = api.client.get("/v1/bundles/" + url.format(n=bundle[0], v=bundle[1]), headers=api.auth(who) if who else {})
        problem = response.json()
        return response.status_code, problem["type"], problem["detail"].replace(bundle[0], "NAME").replace(bundle[1], "VERSION")

    for who in (None, "bob"):
        for url in urls:
            private = answer(url, who, (name, version))
            assert private[0] == 404 and private == answer(url, who, ("nobody", "9.9.9")), (who, url, private)
            if "{v}" in url:
                assert private == answer(url, who, (name, "9.9.9")), (who, url)


def test_shared_workspace_lets_every_key_see_everything(tmp_path):
    api = make_api(tmp_path, shared_workspace=True)
    texture = api.client.post("/v1/assets/textures", files={"file": ("d.png", png_bytes())}, headers=api.auth("upload")).json()
    assert api.client.get(f"/v1/assets/{texture['id']}", headers=api.auth("bake")).status_code == 200
