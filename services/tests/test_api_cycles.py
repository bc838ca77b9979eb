"""A chosen cycle over REST: POST /v1/assets/cycles takes cycle.json (and its looped.pc2) with the checks
`crowdbake bake --cycle` applies (crowdbake.ingest.cycle_document), a bake request names it in `cycle`,
checked against the cloth's frames, and the worker hands it to the stages as the CLI does.

The app is the real one with the filesystem broker; no worker runs (the worker's part is called in
process on the recorded bake)."""
from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from service_fixtures import make_api, obj_bytes, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth

PROBLEM = "application/problem+json"
CLOTH_FRAMES = 12


@pytest.fixture
def api(tmp_path):
    return make_api(tmp_path)


@pytest.fixture
def assets(api, tmp_path):
    points, faces = tiny_cloth(frames=CLOTH_FRAMES)
    upload = api.auth("upload")
    character = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", tiny_character_glb())}, headers=upload).json()
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))}, headers=upload).json()
    return {"character": character["id"], "cloth": cloth["id"], "points": points}


def cycle_json(start: int = 2, frames: int = 6, method: str = "crossfade", **extra) -> bytes:
    return json.dumps({"start_frame": start, "cycle_frames": frames, "end_frame": start + frames, "closing": {"method": method}, **extra}).encode()


def upload_cycle(api, document: bytes, looped: bytes | None = None, who: str = "upload", name: str = "cycle.json"):
    files = {"cycle": (name, document)}
    if looped is not None:
        files["looped"] = ("looped.pc2", looped)
    return api.client.post("/v1/assets/cycles", files=files, headers=api.auth(who))


def bake_body(assets, **changes):
    body = {"name": "walker", "version": "1.0.0", "character": assets["character"], "cloth": assets["cloth"],
            "params": {"impostor_frames": 2, "azimuths": 4, "tile_size": 32}}
    body.update(changes)
    return body


# ------------------------------------------------------------------------------------------ upload


def test_a_cycle_is_stored_once_with_or_without_its_loop(api, assets):
    alone = upload_cycle(api, cycle_json())
    assert alone.status_code == 201, alone.text
    asset = alone.json()
    assert asset["kind"] == "cycle" and set(asset["files"]) == {"file"} and asset["files"]["file"]["media_type"] == "application/json"
    assert asset["info"] == {"start_frame": 2, "cycle_frames": 6, "closing": "crossfade", "looped_points": None}
    again = upload_cycle(api, cycle_json(), name="renamed.json")
    assert again.status_code == 200 and again.json()["id"] == asset["id"]

    looped = pc2_bytes(assets["points"][2:8])
    paired = upload_cycle(api, cycle_json(), looped)
    assert paired.status_code == 201 and paired.json()["id"] != asset["id"]  # another content: cycle.json + looped.pc2
    assert set(paired.json()["files"]) == {"file", "looped"} and paired.json()["info"]["looped_points"] == 9
    listed = api.client.get("/v1/assets", params={"kind": "cycle"}, headers=api.auth("all")).json()
    assert {row["id"] for row in listed["data"]} == {asset["id"], paired.json()["id"]}


@pytest.mark.parametrize("document, words", [
    (b"{not json", "is not JSON"),
    (b"[1, 2]", "must hold a JSON object"),
    (cycle_json(start=-1), "/start_frame must be an integer in 0.."),
    (json.dumps({"start_frame": True, "cycle_frames": 6}).encode(), "/start_frame must be an integer in 0.."),
    (json.dumps({"start_frame": 0}).encode(), "/cycle_frames must be an integer in 0.."),
    (cycle_json(frames=1), "/cycle_frames must be at least 2"),
    (cycle_json(method="cubic"), "/closing/method must be one of"),
])
def test_a_bad_cycle_document_is_refused_and_nothing_is_kept(api, document, words):
    before = api.snapshot()
    response = upload_cycle(api, document)
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    body = response.json()
    assert body["type"] == "/problems/invalid-file"
    assert [(error["field"], error["file"]) for error in body["errors"]] == [("cycle", "cycle.json")]
    assert words in body["errors"][0]["message"]
    assert api.snapshot() == before


def _hostile(**fields) -> bytes:
    document = {"start_frame": 2, "cycle_frames": 6, "end_frame": 8, "closing": {"method": "crossfade"}}
    document.update(fields)
    return json.dumps(document).encode()


@pytest.mark.parametrize("document, pointer", [
    (_hostile(input={"fps": float("nan")}), "/input/fps"),
    (_hostile(input={"fps": -24}), "/input/fps"),
    (_hostile(input={"fps": 1e308}), "/input/fps"),
    (_hostile(input={"fps": "fast"}), "/input/fps"),
    (_hostile(input={"fps": 1e-300}), "/input/fps"),
    (_hostile(input=[24]), "/input"),
    (_hostile(input="24 fps"), "/input"),
    (_hostile(seam=[1, 2]), "/seam"),
    (_hostile(seam={"position_jump_ratio": "big"}), "/seam/position_jump_ratio"),
    (_hostile(seam={"velocity_jump_ratio": float("inf")}), "/seam/velocity_jump_ratio"),
    (_hostile(root_motion=True), "/root_motion"),
    (_hostile(root_motion={"removed": "yes"}), "/root_motion/removed"),
    (_hostile(end_frame="8"), "/end_frame"),
    (_hostile(end_frame=8.5), "/end_frame"),
    (_hostile(end_frame=99), "/end_frame"),
    (_hostile(closing="crossfade"), "/closing"),
    (_hostile(start_frame=10**400), "/start_frame"),
], ids=lambda value: value if isinstance(value, str) else None)
def test_every_field_a_stage_reads_is_checked_at_upload(api, document, pointer):
    """Regression: the upload checked start_frame, cycle_frames and closing.method only. input.fps NaN,
    -24, 1e308, "fast" or 1e-300, and input, seam, root_motion, end_frame of the wrong type were stored
    with a 201; the bake then failed with a raw TypeError, AttributeError or "cannot convert float NaN
    to integer". Each is now a 422 naming the field by its JSON pointer."""
    before = api.snapshot()
    response = upload_cycle(api, document)
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM, response.text
    error = response.json()["errors"][0]
    assert (error["field"], error["file"], error["where"]) == ("cycle", "cycle.json", pointer)
    assert error["message"].startswith(f"cycle.json: {pointer} ")
    assert api.snapshot() == before


def test_a_key_given_twice_is_a_422(api):
    """json keeps the last of two equal keys, so one file would give two readers two cycles."""
    response = upload_cycle(api, b'{"start_frame": 2, "cycle_frames": 6, "start_frame": 0}')
    assert response.status_code == 422 and "'start_frame' appears twice" in response.text, response.text


def test_a_5000_digit_number_is_a_422_not_a_500(api):
    """Regression: json refuses integers over 4,300 digits with a ValueError that is no JSONDecodeError;
    it escaped the upload's check as a 500."""
    response = upload_cycle(api, b'{"start_frame": ' + b"9" * 5000 + b', "cycle_frames": 6}')
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM, response.text
    assert "is not JSON" in response.json()["errors"][0]["message"]


def test_a_cycle_document_as_crowdbake_cycle_writes_it_is_accepted(api):
    """The optional sections, filled as `crowdbake cycle` fills them (nulls included), pass."""
    document = _hostile(input={"fps": 30.0, "frame_count": 12}, seam={"position_jump_ratio": 0.4, "velocity_jump_ratio": None},
                        root_motion={"removed": True, "offset_per_loop": [0.0, 0.0, 1.2]})
    assert upload_cycle(api, document).status_code == 201
    assert upload_cycle(api, _hostile(input={"fps": None}, seam=None, root_motion=None)).status_code == 201


def test_the_validate_stage_applies_the_same_checks(tmp_path):
    """`crowdbake bake --cycle` reads cycle.json through the same function, then the cache's frame count."""
    from crowdbake.errors import InputError
    from crowdbake.ingest.cycle_document import check_cycle_document

    path = tmp_path / "cycle.json"
    path.write_bytes(cycle_json(method="cubic"))
    with pytest.raises(InputError, match="/closing/method must be one of") as refused:
        check_cycle_document(path, CLOTH_FRAMES)
    assert refused.value.field == "cycle"
    path.write_bytes(cycle_json(start=8, frames=6))
    with pytest.raises(InputError, match=r"the cycle \[8, 14\) runs past the cache's 12 frames"):
        check_cycle_document(path, CLOTH_FRAMES)
    assert check_cycle_document(path, 14)["start_frame"] == 8


def test_a_bad_looped_cache_or_form_is_refused(api, assets):
    before = api.snapshot()
    short = upload_cycle(api, cycle_json(frames=6), pc2_bytes(assets["points"][:5]))
    assert short.status_code == 422 and short.json()["errors"][0]["field"] == "looped"
    assert "5 frames, but cycle.json says cycle_frames 6" in short.json()["errors"][0]["message"]
    broken = upload_cycle(api, cycle_json(), pc2_bytes(assets["points"][:6])[:-7])
    assert broken.status_code == 422 and broken.json()["errors"][0]["field"] == "looped" and broken.json()["errors"][0]["where"].startswith("byte ")
    mismatch = upload_cycle(api, png_bytes())
    assert mismatch.status_code == 422 and mismatch.json()["type"] == "/problems/format-mismatch"
    wrong_name = upload_cycle(api, cycle_json(), name="cycle.txt")
    assert wrong_name.status_code == 415 and wrong_name.json()["errors"][0]["field"] == "cycle"
    missing = api.client.post("/v1/assets/cycles", files={"looped": ("looped.pc2", pc2_bytes(assets["points"][:6]))}, headers=api.auth("upload"))
    assert missing.status_code == 400 and missing.json()["errors"][0]["field"] == "cycle"
    assert api.client.post("/v1/assets/cycles", files={"cycle": ("cycle.json", cycle_json())}, headers=api.auth("bake")).status_code == 403
    assert api.snapshot() == before


# ------------------------------------------------------------------------------------ bake request


def test_a_bake_with_a_cycle_records_it_and_keys_on_it(api, assets):
    cycle = upload_cycle(api, cycle_json()).json()
    plain = api.client.post("/v1/bakes", json=bake_body(assets), headers=api.auth("ci")).json()
    chosen = api.client.post("/v1/bakes", json=bake_body(assets, version="1.0.1", cycle=cycle["id"]), headers=api.auth("ci"))
    assert chosen.status_code == 202, chosen.text
    assert chosen.json()["inputs"]["cycle"] == cycle["id"] and "cycle" not in plain["inputs"]
    # The same request again is the same bake; without the cycle (or with another one) it is another.
    again = api.client.post("/v1/bakes", json=bake_body(assets, version="1.0.1", cycle=cycle["id"]), headers=api.auth("ci"))
    assert again.status_code == 200 and again.json()["id"] == chosen.json()["id"]
    other = upload_cycle(api, cycle_json(start=3)).json()
    moved = api.client.post("/v1/bakes", json=bake_body(assets, version="1.0.2", cycle=other["id"]), headers=api.auth("ci")).json()
    assert len({plain["input_key"], chosen.json()["input_key"], moved["input_key"]}) == 3


def test_a_given_cycle_need_not_fit_twice_in_the_cloth(api, assets):
    """As `crowdbake bake --cycle`: the two-cycle rule is the search's, a given cycle only has to lie within the cache."""
    looped = pc2_bytes(assets["points"][:10])
    cycle = upload_cycle(api, cycle_json(start=1, frames=10), looped).json()
    searched = api.client.post("/v1/bakes", json=bake_body(assets, params={"cycle_frames": 10}), headers=api.auth("ci"))
    assert searched.status_code == 422 and searched.json()["errors"][0]["field"] == "cloth"
    given = api.client.post("/v1/bakes", json=bake_body(assets, cycle=cycle["id"], params={"cycle_frames": 10}), headers=api.auth("ci"))
    assert given.status_code == 202, given.text


@pytest.mark.parametrize("start, frames, method, with_loop, words", [
    (8, 6, "none", False, "the cycle [8, 14) runs past the cache's 12 frames"),
    (6, 6, "crossfade", False, "closing the cycle needs frame 12, the cache ends at 11"),
])
def test_a_cycle_that_does_not_fit_the_cloth_is_a_problem_naming_cycle(api, assets, start, frames, method, with_loop, words):
    cycle = upload_cycle(api, cycle_json(start=start, frames=frames, method=method)).json()
    response = api.client.post("/v1/bakes", json=bake_body(assets, cycle=cycle["id"]), headers=api.auth("ci"))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    assert [error["field"] for error in response.json()["errors"]] == ["cycle"]
    assert words in response.json()["errors"][0]["message"]
    # With its looped.pc2 the last cycle of the cache needs no frame after it.
    if method != "none":
        looped = upload_cycle(api, cycle_json(start=start, frames=frames, method=method), pc2_bytes(assets["points"][start:start + frames])).json()
        assert api.client.post("/v1/bakes", json=bake_body(assets, cycle=looped["id"]), headers=api.auth("ci")).status_code == 202


def test_a_cycle_must_be_a_cycle_asset_of_the_key(api, assets, tmp_path):
    response = api.client.post("/v1/bakes", json=bake_body(assets, cycle=assets["cloth"]), headers=api.auth("ci"))
    assert response.status_code == 422 and [error["field"] for error in response.json()["errors"]] == ["cycle"]
    # Without a shared workspace another key's cycle is not there (crowdbake.api.deps ownership).
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.keys import create_api_key

    private = make_api(tmp_path / "private", shared_workspace=False)
    with session_scope(private.sessions) as session:
        for name in ("alice", "bob"):
            private.keys[name], _ = create_api_key(session, "upload,bake,publish,read", name)
    theirs = upload_cycle(private, cycle_json(), who="alice").json()
    assert private.client.get(f"/v1/assets/{theirs['id']}", headers=private.auth("bob")).status_code == 404
    mine = {kind: private.client.post(f"/v1/assets/{route}", files=files, headers=private.auth("bob")).json()["id"]
            for kind, route, files in (("character", "characters", {"file": ("w.glb", tiny_character_glb())}),
                                       ("cloth", "cloth", {"cache": ("c.pc2", pc2_bytes(assets["points"])),
                                                           "mesh": ("c.obj", obj_bytes(assets["points"][0], tiny_cloth()[1], tmp_path))}))}
    response = private.client.post("/v1/bakes", json=bake_body(mine, cycle=theirs["id"]), headers=private.auth("bob"))
    assert response.status_code == 422 and [error["field"] for error in response.json()["errors"]] == ["cycle"]
    assert "no cycle asset" in response.json()["errors"][0]["message"]


# -------------------------------------------------------------------------------------- the worker


def test_the_worker_hands_the_cycle_to_the_stages_as_the_cli_does(api, assets, tmp_path):
    """_materialize_inputs puts cycle.json with looped.pc2 beside it, where the validate stage looks."""
    from crowdbake.jobs.tasks import _materialize_inputs
    from crowdbake.storage.models import Bake

    document, looped = cycle_json(), pc2_bytes(assets["points"][2:8])
    cycle = upload_cycle(api, document, looped).json()
    bake = api.client.post("/v1/bakes", json=bake_body(assets, cycle=cycle["id"]), headers=api.auth("ci")).json()
    context = SimpleNamespace(services=SimpleNamespace(blobs=api.client.app.state.services.blobs), work=tmp_path / "work")
    with api.sessions() as session:
        inputs = _materialize_inputs(context, session.get(Bake, bake["id"]), session)
    assert inputs.cycle is not None and inputs.cycle.read_bytes() == document
    assert inputs.cycle.with_name("looped.pc2").read_bytes() == looped


# -------------------------------------------------------------------------------------- the client


def test_submit_sends_the_cycle_with_the_loop_beside_it(tmp_path):
    from crowdbake.client.http import ClientError
    from crowdbake.client.submit import build_parser, check_locally

    for name in ("walker.glb", "cloth.pc2", "cloth.obj", "cycle.json"):
        (tmp_path / name).write_bytes(b"glTF" if name.endswith(".glb") else b"x")  # the client checks a .glb's magic
    common = [str(tmp_path / "walker.glb"), "--server", "http://127.0.0.1:9", "--cloth", str(tmp_path / "cloth.pc2"),
              "--cloth-mesh", str(tmp_path / "cloth.obj"), "--name", "walker", "--version", "1"]
    parse = build_parser().parse_args
    assert check_locally(parse(common)).cycle_files == {}
    assert check_locally(parse(common + ["--cycle", str(tmp_path / "cycle.json")])).cycle_files == {"cycle": tmp_path / "cycle.json"}
    (tmp_path / "looped.pc2").write_bytes(b"x")
    assert check_locally(parse(common + ["--cycle", str(tmp_path / "cycle.json")])).cycle_files == {
        "cycle": tmp_path / "cycle.json", "looped": tmp_path / "looped.pc2"}
    with pytest.raises(ClientError, match="--cycle .*no such file") as refused:
        check_locally(parse(common + ["--cycle", str(tmp_path / "elsewhere.json")]))
    assert int(refused.value.exit_code) == 2
