"""A clip timeline over REST: POST /v1/assets/timelines takes timeline.json with the checks `crowdbake bake
--timeline` applies (crowdbake.ingest.timeline), a bake request names it in `timeline`, checked against the
cloth's frames and rate and the character's clips, and the worker hands it to the stages as the CLI does.

The app is the real one with the filesystem broker; no worker runs (the worker's part is called in process
on the recorded bake)."""
from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from service_fixtures import make_api, obj_bytes, pc2_bytes, tiny_character_glb, tiny_cloth

PROBLEM = "application/problem+json"
CLOTH_FRAMES = 12


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    return make_api(tmp_path_factory.mktemp("timelines"))


@pytest.fixture(scope="module")
def assets(api, tmp_path_factory):
    points, faces = tiny_cloth(frames=CLOTH_FRAMES)
    upload = api.auth("upload")
    character = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", tiny_character_glb())}, headers=upload).json()
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)),
                                                       "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path_factory.mktemp("mesh")))}, headers=upload).json()
    clip = character["info"]["animations"][0]["name"]
    return {"character": character["id"], "cloth": cloth["id"], "clip": clip}


def timeline_json(clip: str, total: int = CLOTH_FRAMES, fps: float = 24, clip_frames: int = 6, **changes) -> bytes:
    """One segment of the tiny character's only clip (a quarter second: 6 frames at 24 fps) over the cache."""
    segment = {"clip": clip, "first_frame": 0, "last_frame": total - 1, "pure_first_frame": 0, "pure_last_frame": total - 1,
               "clip_frames": clip_frames, **changes}
    return json.dumps({"fps": fps, "total_frames": total, "segments": [segment]}).encode()


def upload_timeline(api, document: bytes, name: str = "timeline.json"):
    return api.client.post("/v1/assets/timelines", files={"timeline": (name, document)}, headers=api.auth("upload"))


def bake_body(assets, **changes):
    body = {"name": "walker", "version": "1.0.0", "character": assets["character"], "cloth": assets["cloth"],
            "params": {"impostor_frames": 2, "azimuths": 4, "tile_size": 32}}
    body.update(changes)
    return body


def test_a_timeline_is_stored_with_what_the_bake_request_checks(api, assets):
    response = upload_timeline(api, timeline_json(assets["clip"]))
    assert response.status_code == 201, response.text
    asset = response.json()
    assert asset["kind"] == "timeline" and asset["files"]["file"]["media_type"] == "application/json"
    assert asset["info"] == {"fps": 24.0, "total_frames": CLOTH_FRAMES, "clips": {assets["clip"]: 6}, "segments": 1}
    assert upload_timeline(api, timeline_json(assets["clip"]), name="again.json").json()["id"] == asset["id"]


@pytest.mark.parametrize("changes, pointer", [
    ({"clip_frames": 1}, "/segments/0/clip_frames"),
    ({"pure_first_frame": 5, "first_frame": 6}, "/segments/0/pure_first_frame"),
    ({"last_frame": 99}, "/segments/0/last_frame"),
    ({"clip_frames": "six"}, "/segments/0/clip_frames"),
])
def test_a_bad_timeline_is_a_422_naming_the_field_by_its_pointer(api, assets, changes, pointer):
    before = api.snapshot()
    response = upload_timeline(api, timeline_json(assets["clip"], **changes))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM, response.text
    error = response.json()["errors"][0]
    assert (error["field"], error["file"], error["where"]) == ("timeline", "timeline.json", pointer)
    assert error["message"].startswith(f"timeline.json: {pointer} ")
    assert api.snapshot() == before


@pytest.mark.parametrize("document, pointer, words", [
    (lambda clip: timeline_json(clip, total=10), "/total_frames", "is 10, but the cloth cache has 12 frames"),
    (lambda clip: timeline_json(clip, fps=30, clip_frames=8), "/fps", "is 30, but the cloth cache plays at 24 frames per second"),
    (lambda clip: timeline_json("Sleeping"), "/segments", "names 'Sleeping', which the character lacks (it has "),
    (lambda clip: timeline_json(clip, clip_frames=5), "/segments", "= 6 frames at 24 fps"),
])
def test_a_timeline_that_does_not_fit_the_cloth_or_the_character_is_a_422(api, assets, document, pointer, words):
    timeline = upload_timeline(api, document(assets["clip"])).json()
    response = api.client.post("/v1/bakes", json=bake_body(assets, timeline=timeline["id"]), headers=api.auth("ci"))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM, response.text
    error = response.json()["errors"][0]
    assert (error["field"], error["where"]) == ("timeline", pointer) and words in error["message"], error


def test_an_animation_the_timeline_does_not_play_is_a_422(api, assets):
    timeline = upload_timeline(api, timeline_json(assets["clip"])).json()
    response = api.client.post("/v1/bakes", json=bake_body(assets, timeline=timeline["id"], params={"animation": "Run"}), headers=api.auth("ci"))
    assert response.status_code == 422 and response.json()["errors"][0]["field"] == "params.animation"
    assert "not a clip of the timeline" in response.json()["errors"][0]["message"]


def test_a_bake_with_a_timeline_keys_on_it_and_the_worker_gets_the_file(api, assets, tmp_path):
    from crowdbake.jobs.tasks import _materialize_inputs
    from crowdbake.storage.models import Bake

    document = timeline_json(assets["clip"])
    timeline = upload_timeline(api, document).json()
    plain = api.client.post("/v1/bakes", json=bake_body(assets, version="2.0.0"), headers=api.auth("ci")).json()
    response = api.client.post("/v1/bakes", json=bake_body(assets, version="2.0.1", timeline=timeline["id"]), headers=api.auth("ci"))
    assert response.status_code == 202, response.text
    bake = response.json()
    assert bake["inputs"]["timeline"] == timeline["id"] and "timeline" not in plain["inputs"]
    assert bake["input_key"] != plain["input_key"]
    context = SimpleNamespace(services=SimpleNamespace(blobs=api.client.app.state.services.blobs), work=tmp_path / "work")
    with api.sessions() as session:
        inputs = _materialize_inputs(context, session.get(Bake, bake["id"]), session)
    assert inputs.timeline is not None and inputs.timeline.read_bytes() == document
    assert plain["inputs"].get("timeline") is None


def test_a_timeline_needs_cloth_and_no_cycle(api, assets):
    timeline = upload_timeline(api, timeline_json(assets["clip"])).json()
    body = bake_body(assets, timeline=timeline["id"])
    del body["cloth"]
    response = api.client.post("/v1/bakes", json=body, headers=api.auth("ci"))
    assert response.status_code == 422 and response.json()["errors"][0]["field"] == "cloth"
    wrong_kind = api.client.post("/v1/bakes", json=bake_body(assets, timeline=assets["cloth"]), headers=api.auth("ci"))
    assert wrong_kind.status_code == 422 and wrong_kind.json()["errors"][0]["field"] == "timeline"


def test_submit_uploads_the_timeline_and_names_it_in_the_bake(api, assets, tmp_path, capsys):
    """`crowdbake submit --timeline`: checked locally (a missing file, or with --cycle, is exit 2), then uploaded
    to /v1/assets/timelines and named in the bake request, which the server takes (202)."""
    from crowdbake.client.http import Server
    from crowdbake.client.submit import bake_body as client_body
    from crowdbake.client.submit import build_parser, check_locally, run, upload
    from crowdbake.ingest.input_modes import BakeInputSet

    points, faces = tiny_cloth(frames=CLOTH_FRAMES)
    (tmp_path / "walker.glb").write_bytes(tiny_character_glb())
    (tmp_path / "c.pc2").write_bytes(pc2_bytes(points))
    (tmp_path / "c.obj").write_bytes(obj_bytes(points[0], faces, tmp_path))
    (tmp_path / "timeline.json").write_bytes(timeline_json(assets["clip"]))
    base = [str(tmp_path / "walker.glb"), "--server", "http://127.0.0.1:9", "--cloth", str(tmp_path / "c.pc2"),
            "--cloth-mesh", str(tmp_path / "c.obj"), "--name", "clips", "--version", "3.0.0"]
    assert run(build_parser().parse_args([*base, "--timeline", str(tmp_path / "none.json")])) == 2
    assert "--timeline" in (error := capsys.readouterr().err) and "no such file" in error
    (tmp_path / "cycle.json").write_text("{}")
    assert run(build_parser().parse_args([*base, "--timeline", str(tmp_path / "timeline.json"), "--cycle", str(tmp_path / "cycle.json")])) == 2
    assert "give one of them" in capsys.readouterr().err

    args = build_parser().parse_args([*base, "--timeline", str(tmp_path / "timeline.json")])
    checked = check_locally(args)
    api.client.headers.update(api.auth("all"))
    server = Server(api.client, retry_for=1.0)
    quiet = lambda line: None  # noqa: E731
    character = upload(server, "/v1/assets/characters", {"file": checked.character}, "character", quiet)
    cloth = upload(server, "/v1/assets/cloth", checked.cloth_files, "cloth", quiet)
    timeline = upload(server, "/v1/assets/timelines", {"timeline": checked.timeline}, "timeline", quiet)
    response = server.request("POST", "/v1/bakes", "starting the bake",
                              json=client_body(args, checked, BakeInputSet(character["id"], cloth["id"], timeline=timeline["id"])))
    assert response.status_code == 202, response.text
    assert response.json()["inputs"]["timeline"] == timeline["id"]


def test_cycle_frames_with_a_timeline_is_a_422(api, assets):
    timeline = upload_timeline(api, timeline_json(assets["clip"])).json()
    response = api.client.post("/v1/bakes", json=bake_body(assets, timeline=timeline["id"], params={"cycle_frames": 6}), headers=api.auth("ci"))
    assert response.status_code == 422 and response.json()["errors"][0]["field"] == "params.cycle_frames"


def _with_rows(clip: str, changes: dict | None = None, row: int = 0) -> dict:
    """The one-segment timeline with a row per frame, `changes` made to the fields of row `row`."""
    document = json.loads(timeline_json(clip))
    document["frames"] = [{"frame": f, "clip": clip, "clip_frame": f % 6, "weight": 1.0} for f in range(CLOTH_FRAMES)]
    document["frames"][row].update(changes or {})
    return document


def _segments(clips: list[str], total: int = CLOTH_FRAMES) -> dict:
    """Back-to-back segments of `clips` over `total` frames (no blends), each clip 6 frames long."""
    step = total // len(clips)
    segments = [{"clip": clip, "first_frame": k * step, "last_frame": total - 1 if k == len(clips) - 1 else (k + 1) * step - 1,
                 "clip_frames": 6} for k, clip in enumerate(clips)]
    for segment in segments:
        segment.update(pure_first_frame=segment["first_frame"], pure_last_frame=segment["last_frame"])
    return {"fps": 24, "total_frames": total, "segments": segments}


# Each case: a timeline.json a client may send, and the JSON pointer of the field the 422 names. The first
# three were 500s (TypeError: unhashable type) before every field was typed at the boundary.
HOSTILE_TIMELINES = {
    "a row's clip is a list": (lambda clip: _with_rows(clip, {"clip": [clip]}), "/frames/0/clip"),
    "a row's clip is an object": (lambda clip: _with_rows(clip, {"clip": {clip: 1}}), "/frames/0/clip"),
    "a row's blend_from is a list": (lambda clip: _with_rows(clip, {"weight": 0.5, "blend_from": [clip], "blend_from_frame": 0}, row=3), "/frames/3/blend_from"),
    "a segment's clip is a list": (lambda clip: json.loads(timeline_json([clip])), "/segments/0/clip"),
    "a clip name with a path": (lambda clip: json.loads(timeline_json("../../etc/passwd")), "/segments/0/clip"),
    "a clip name with a backslash": (lambda clip: json.loads(timeline_json("..\\evil")), "/segments/0/clip"),
    "a clip name with NUL": (lambda clip: json.loads(timeline_json("walk\x00.pc2")), "/segments/0/clip"),
    "a clip name with a newline": (lambda clip: json.loads(timeline_json("walk\nrun")), "/segments/0/clip"),
    "a clip name of 65 characters": (lambda clip: json.loads(timeline_json("w" * 65)), "/segments/0/clip"),
    "two clips equal under case folding": (lambda clip: _segments(["Walking", "walking"]), "/segments/1/clip"),
    "total_frames true": (lambda clip: {**json.loads(timeline_json(clip)), "total_frames": True}, "/total_frames"),
    "clip_frames true": (lambda clip: json.loads(timeline_json(clip, clip_frames=True)), "/segments/0/clip_frames"),
    "first_frame false": (lambda clip: json.loads(timeline_json(clip, first_frame=False)), "/segments/0/first_frame"),
    "a row's frame true": (lambda clip: _with_rows(clip, {"frame": True}, row=1), "/frames/1/frame"),
    "a row's weight true": (lambda clip: _with_rows(clip, {"weight": True}), "/frames/0/weight"),
    "clip_frames 10^9": (lambda clip: json.loads(timeline_json(clip, clip_frames=10**9)), "/segments/0/clip_frames"),
    "total_frames 2^26 with no rows": (lambda clip: json.loads(timeline_json(clip, total=1 << 26)), "/total_frames"),
    "total_frames 2^31 - 1 with no rows": (lambda clip: json.loads(timeline_json(clip, total=(1 << 31) - 1)), "/total_frames"),
    "total_frames past the segments": (lambda clip: {**json.loads(timeline_json(clip)), "total_frames": 50_000}, "/segments/0/last_frame"),
    "fewer rows than total_frames": (lambda clip: {**_with_rows(clip), "frames": _with_rows(clip)["frames"][:-1]}, "/frames"),
    "a gap between segments": (lambda clip: _segments(["Idle", "Walk"]) | {"segments": [
        {**_segments(["Idle", "Walk"])["segments"][0], "last_frame": 3, "pure_last_frame": 3}, _segments(["Idle", "Walk"])["segments"][1]]},
        "/segments/1/first_frame"),
    "a segment blending past its neighbour": (lambda clip: {"fps": 24, "total_frames": 12, "segments": [
        {"clip": "A", "first_frame": 0, "last_frame": 11, "pure_first_frame": 0, "pure_last_frame": 1, "clip_frames": 6},
        {"clip": "B", "first_frame": 2, "last_frame": 11, "pure_first_frame": 2, "pure_last_frame": 3, "clip_frames": 6},
        {"clip": "C", "first_frame": 4, "last_frame": 11, "pure_first_frame": 4, "pure_last_frame": 11, "clip_frames": 6}]},
        "/segments/2/first_frame"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_TIMELINES))
def test_a_hostile_timeline_is_a_422_naming_its_pointer(api, assets, case):
    document, pointer = HOSTILE_TIMELINES[case]
    before = api.snapshot()
    response = upload_timeline(api, json.dumps(document(assets["clip"])).encode())
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM, response.text
    error = response.json()["errors"][0]
    assert (error["field"], error["where"]) == ("timeline", pointer), error
    assert api.snapshot() == before


def test_a_key_given_twice_in_one_object_is_a_422(api, assets):
    """Python's json keeps the last of two equal keys: the file would mean one thing here and another to
    a reader that keeps the first."""
    document = timeline_json(assets["clip"]).replace(b'"fps": 24', b'"fps": 24, "fps": 30')
    response = upload_timeline(api, document)
    assert response.status_code == 422 and "'fps' appears twice" in response.json()["errors"][0]["message"], response.text


def test_a_timeline_over_the_byte_limit_is_a_422_before_it_is_parsed(api, assets, monkeypatch):
    import crowdbake.ingest.timeline as timeline_module

    monkeypatch.setattr(timeline_module, "MAX_TIMELINE_BYTES", 100)
    response = upload_timeline(api, timeline_json(assets["clip"]) + b" " * 100)
    assert response.status_code == 422 and "a timeline has at most 100" in response.json()["errors"][0]["message"], response.text
