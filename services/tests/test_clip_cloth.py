"""Several clips from one cloth cache per clip (`crowdbake bake --clip-cloth`, REST `clip_cloth`): each cache a
separate simulation of one clip of the sample humanoid (crowdbake.sample, `--clips Walking:3` and
`--clips Running:3`, a coarse skirt), baked to a format-2 bundle with a loop per clip and no transitions."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service_fixtures import make_api

PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def caches(tmp_path_factory) -> dict[str, Path]:
    """{clip: folder} of two one-clip simulations (character.glb, cloth.pc2, cloth.obj; the same character)."""
    from crowdbake.sample.generate import generate_sample

    root = tmp_path_factory.mktemp("clip_caches")
    folders = {}
    for clip in ("Walking", "Running"):
        folders[clip] = root / clip
        generate_sample(folders[clip], clips=((clip, 3),), seed=1, cycle_frames=24, texture_size=64, cloth_rows=8, cloth_columns=24)
    return folders


def clip_args(caches, *clips: str) -> list[str]:
    return [arg for clip in clips for arg in ("--clip-cloth", f"{clip}={caches[clip] / 'cloth.pc2'},{caches[clip] / 'cloth.obj'}")]


def bake(caches, out: Path, *extra: str) -> int:
    from crowdbake.cli import main

    return main(["bake", str(caches["Walking"] / "character.glb"), "--name", "clips", "--version", "1", "--out", str(out / "bundles"),
                 "--work", str(out / "work"), "--frames", "2", "--azimuths", "4", "--elevations", "0", "--tile", "32",
                 "--cycle-views", "3", "--candidates", "3", "--no-export", *extra])


def test_one_cache_per_clip_bakes_a_loop_each_and_no_transitions(caches, tmp_path, capsys):
    from crowdbake.formats.bundle import verify_bundle

    assert bake(caches, tmp_path, *clip_args(caches, "Walking", "Running")) == 0
    out = capsys.readouterr().out
    assert "no transitions (no simulation joined the clips)" in out
    # Each clip's impostor scored as crowdview draws it, one line each (fidelity.json runtime.ranges).
    assert all(f"runtime  clip {name}: SSIM at baked views " in out for name in ("Walking", "Running")), out[-1500:]
    # One impostor budget for both clips, its split said once (not the per-clip rule's lines).
    assert "MiB archetype budget, split by measuring: Walking " in out and "budget chose" not in out, out[-1500:]
    bundle = verify_bundle(tmp_path / "bundles" / "clips" / "1")
    assert bundle.manifest["format_version"] == 4  # the skinned body
    assert [(c.name, c.frames) for c in bundle.ranges.clips] == [("Walking", 24), ("Running", 17)]
    assert tuple(bundle.ranges.transitions) == () and bundle.manifest["transitions"] == []
    cycle = json.loads((tmp_path / "work" / "cycle" / "cycle.json").read_text())
    segments = cycle["timeline"]["segments"]
    assert [(s["clip"], s["first_frame"], s["last_frame"], s.get("new_simulation", False)) for s in segments] == [
        ("Walking", 0, 72, False), ("Running", 73, 124, True)]
    for entry, segment in zip(cycle["clips"], segments):  # each loop cut from its own simulation, none across the join
        assert segment["first_frame"] <= entry["searched_frames"][0] and entry["searched_frames"][1] <= segment["last_frame"]
        assert entry["closing"]["quality"]["within_bounds"], entry["closing"]["quality"]
    assert cycle["transitions"] == []
    assert "simulated apart" in (tmp_path / "work" / "cycle" / "report.html").read_text()


def test_the_joined_timeline_reads_back_with_no_change_of_clip():
    from crowdbake.ingest.clip_caches import join_clip_frames
    from crowdbake.ingest.timeline import timeline_fields

    a, b = np.zeros((10, 4, 3)), np.ones((7, 4, 3))
    frames, document = join_clip_frames([a, b], ["Walk", "Run"], {"Walk": 5, "Run": 3}, 24.0)
    assert frames.shape == (17, 4, 3) and frames.dtype == np.float32 and np.all(frames[10:] == 1)
    timeline = timeline_fields(document)
    assert timeline.clips() == ["Walk", "Run"] and timeline.changes() == []
    assert [int(timeline.clip_frame[f]) for f in (0, 9, 10, 12, 13)] == [0, 4, 0, 2, 0]  # each clip from its frame 0
    # The same segments simulated in one run would be a change of clip.
    document["segments"][1].pop("new_simulation")
    assert timeline_fields(document).changes() == [(0, 1)]


def _variant(caches, tmp_path, kind: str) -> str:
    """A --clip-cloth value for Running whose cache is wrong in one way."""
    from crowdbake.formats.pc2 import read_pc2, write_pc2

    source = caches["Running"]
    cache, mesh = source / "cloth.pc2", source / "cloth.obj"
    if kind == "short":  # 30 frames: fewer than two Running cycles of 17
        cache = tmp_path / "short.pc2"
        write_pc2(cache, read_pc2(source / "cloth.pc2").points[:30])
    elif kind == "points":  # another garment: a quarter of the points
        points = read_pc2(source / "cloth.pc2").points[:, :48]
        cache, mesh = tmp_path / "small.pc2", tmp_path / "small.obj"
        write_pc2(cache, points)
        mesh.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in points[0]) + "f 1 2 3\nf 2 3 4\n")
    elif kind == "rest":  # the same points, other triangles (every face turned round)
        mesh = tmp_path / "turned.obj"
        lines = [(" ".join(["f", *reversed(line.split()[1:])]) if line.startswith("f ") else line) for line in (source / "cloth.obj").read_text().splitlines()]
        mesh.write_text("\n".join(lines) + "\n")
    return f"Running={cache},{mesh}"


@pytest.mark.parametrize("case, words", [
    ("lacking", "'Flying': the character has no such animation (it has 'Idle', 'Walking', 'Running')"),
    ("twice", "clip 'Walking' is given two cloth caches"),
    ("points", "moves 48 points, clip 'Walking''s 192"),
    ("rest", "its rest mesh differs from clip 'Walking''s"),
    ("short", "its cache has 30 frames, fewer than two cycles of the clip (17 frames each, 34 in all)"),
    ("timeline", "leave out --timeline"),
    ("cloth", "leave out --cloth"),
    ("malformed", "must read NAME=CACHE or NAME=CACHE,MESH.obj"),
    ("cycle_frames", "drop --cycle-frames"),
])
def test_bad_clip_caches_are_one_line_and_exit_2(caches, tmp_path, capsys, case, words):
    walking = clip_args(caches, "Walking")
    extra = {
        "lacking": [*walking, "--clip-cloth", f"Flying={caches['Running'] / 'cloth.pc2'},{caches['Running'] / 'cloth.obj'}"],
        "twice": [*walking, *walking],
        "timeline": [*walking, "--timeline", str(tmp_path / "timeline.json")],
        "cloth": [*walking, "--cloth", str(caches["Walking"] / "cloth.pc2")],
        "malformed": ["--clip-cloth", "Walking"],
        "cycle_frames": [*walking, "--cycle-frames", "24"],
    }.get(case) or [*walking, "--clip-cloth", _variant(caches, tmp_path, case)]
    assert bake(caches, tmp_path, *extra) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and error.startswith("crowdbake bake: error: --clip-cloth: ") and words in error, error
    assert not (tmp_path / "bundles").exists()


def test_the_cycle_command_takes_a_cache_per_clip(caches, tmp_path, capsys):
    """`crowdbake cycle --clip-cloth`: the same joined inputs as the bake, a closed loop per clip."""
    from crowdbake.cli import main

    out = tmp_path / "cycle"
    assert main(["cycle", *clip_args(caches, "Walking", "Running"), "--character", str(caches["Walking"] / "character.glb"),
                 "--views", "3", "--candidates", "3", "--out", str(out)]) == 0
    cycle = json.loads((out / "cycle.json").read_text())
    assert [entry["clip"] for entry in cycle["clips"]] == ["Walking", "Running"] and cycle["transitions"] == []
    assert all(entry["closing"]["quality"]["within_bounds"] for entry in cycle["clips"])
    for extra, words in ((["--timeline", str(tmp_path / "t.json")], "leave out --timeline"),
                         ([str(caches["Walking"] / "cloth.pc2")], "leave out CLOTH"),
                         (["--clip-cloth", f"Flying={caches['Running'] / 'cloth.pc2'},{caches['Running'] / 'cloth.obj'}"], "Flying")):
        capsys.readouterr()
        assert main(["cycle", *clip_args(caches, "Walking"), *extra, "--character", str(caches["Walking"] / "character.glb"),
                     "--out", str(tmp_path / "bad")]) == 2
        error = capsys.readouterr().err.strip()
        assert len(error.splitlines()) == 1 and words in error, error


# REST: the real app, no worker (the worker's part, materializing the inputs, is called in process).

@pytest.fixture(scope="module")
def api(tmp_path_factory):
    return make_api(tmp_path_factory.mktemp("clip_cloth_api"))


@pytest.fixture(scope="module")
def assets(api, caches, tmp_path_factory) -> dict[str, str]:
    upload = api.auth("upload")
    folder = tmp_path_factory.mktemp("short")
    from crowdbake.formats.pc2 import read_pc2, write_pc2

    write_pc2(folder / "short.pc2", read_pc2(caches["Running"] / "cloth.pc2").points[:30])
    ids = {"character": api.client.post("/v1/assets/characters", files={"file": ("walker.glb", (caches["Walking"] / "character.glb").read_bytes())},
                                        headers=upload).json()["id"]}
    for name, cache, mesh in (("Walking", caches["Walking"] / "cloth.pc2", caches["Walking"] / "cloth.obj"),
                              ("Running", caches["Running"] / "cloth.pc2", caches["Running"] / "cloth.obj"),
                              ("short", folder / "short.pc2", caches["Running"] / "cloth.obj")):
        response = api.client.post("/v1/assets/cloth", files={"cache": (cache.name, cache.read_bytes()), "mesh": (mesh.name, mesh.read_bytes())}, headers=upload)
        assert response.status_code == 201, response.text
        ids[name] = response.json()["id"]
    return ids


def rest_body(assets, clip_cloth, **changes):
    body = {"name": "clips", "version": "1.0.0", "character": assets["character"], "clip_cloth": clip_cloth,
            "params": {"impostor_frames": 2, "azimuths": 4, "tile_size": 32}}
    return {**body, **changes}


def test_a_rest_bake_names_a_cloth_asset_per_clip_and_the_worker_joins_them(api, assets, tmp_path):
    from types import SimpleNamespace

    from crowdbake.ingest.timeline import read_timeline
    from crowdbake.jobs.tasks import _materialize_inputs
    from crowdbake.storage.models import Bake

    clip_cloth = [{"clip": "Walking", "cloth": assets["Walking"]}, {"clip": "Running", "cloth": assets["Running"]}]
    response = api.client.post("/v1/bakes", json=rest_body(assets, clip_cloth), headers=api.auth("ci"))
    assert response.status_code == 202, response.text
    bake = response.json()
    assert bake["inputs"]["clip_cloth"] == [["Walking", assets["Walking"]], ["Running", assets["Running"]]]
    swapped = api.client.post("/v1/bakes", json=rest_body(assets, clip_cloth[::-1], version="1.0.1"), headers=api.auth("ci")).json()
    assert swapped["input_key"] != bake["input_key"]
    context = SimpleNamespace(services=SimpleNamespace(blobs=api.client.app.state.services.blobs), work=tmp_path / "work")
    with api.sessions() as session:
        inputs = _materialize_inputs(context, session.get(Bake, bake["id"]), session)
    timeline = read_timeline(inputs.timeline)
    assert [(s.clip, s.first_frame, s.last_frame, s.new_simulation) for s in timeline.segments] == [
        ("Walking", 0, 72, False), ("Running", 73, 124, True)]
    assert timeline.changes() == [] and inputs.cloth.suffix == ".pc2" and inputs.cloth_mesh is not None


@pytest.mark.parametrize("case, field, words", [
    ("lacking", "clip_cloth.1.clip", "the character has no such animation"),
    ("twice", "clip_cloth.1.clip", "given two cloth caches"),
    ("short", "clip_cloth.1", "fewer than two cycles of the clip (17 frames each, 34 in all)"),
    ("with_cloth", "cloth", "leave out cloth"),
    ("cycle_frames", "params.cycle_frames", "drop cycle_frames"),
    ("unknown", "clip_cloth.1.cloth", "no cloth asset"),
])
def test_bad_clip_cloth_is_a_422_naming_the_field(api, assets, case, field, words):
    walking = {"clip": "Walking", "cloth": assets["Walking"]}
    second = {"lacking": {"clip": "Flying", "cloth": assets["Running"]}, "twice": walking, "short": {"clip": "Running", "cloth": assets["short"]},
              "unknown": {"clip": "Running", "cloth": "no-such-asset"}}.get(case, {"clip": "Running", "cloth": assets["Running"]})
    body = rest_body(assets, [walking, second], version="2.0.0")
    if case == "with_cloth":
        body["cloth"] = assets["Walking"]
    if case == "cycle_frames":
        body["params"]["cycle_frames"] = 24
    before = api.snapshot()
    response = api.client.post("/v1/bakes", json=body, headers=api.auth("ci"))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM, response.text
    error = response.json()["errors"][0]
    assert error["field"] == field and words in error["message"], error
    assert api.snapshot() == before


def test_submit_uploads_a_cloth_per_clip_and_names_them_in_the_bake(api, caches, tmp_path, capsys):
    """`crowdbake submit --clip-cloth`: checked locally (with --cloth, or a missing file, is exit 2), the
    server's checks before uploading take it (preflight, published-version check), then each cache is
    uploaded and the bake names them in order (202)."""
    from crowdbake.client.http import Server
    from crowdbake.client.preflight import check_name_and_version
    from crowdbake.client.submit import bake_body as client_body
    from crowdbake.client.submit import build_parser, check_locally, local_inputs, preflight, run, upload
    from crowdbake.ingest.input_modes import BakeInputSet

    base = [str(caches["Walking"] / "character.glb"), "--server", "http://127.0.0.1:9", "--name", "clips", "--version", "3.0.0",
            "--frames", "2", "--azimuths", "4", "--tile", "32"]
    walking = clip_args(caches, "Walking")
    assert run(build_parser().parse_args([*base, *walking, "--cloth", str(caches["Walking"] / "cloth.pc2")])) == 2
    assert "leave out --cloth" in capsys.readouterr().err
    assert run(build_parser().parse_args([*base, *walking, "--clip-cloth", f"Running={tmp_path / 'none.pc2'},{caches['Running'] / 'cloth.obj'}"])) == 2
    assert "--clip-cloth Running" in (error := capsys.readouterr().err) and "no such file" in error

    args = build_parser().parse_args([*base, *clip_args(caches, "Walking", "Running")])
    checked = check_locally(args)
    assert [clip for clip, _ in checked.clip_cloth] == ["Walking", "Running"]
    api.client.headers.update(api.auth("all"))
    server = Server(api.client, retry_for=1.0)
    preflight(server, args, checked)  # refused only for want of the assets
    check_name_and_version(server, args.name, args.bundle_version, local_inputs(checked), checked.params, None, True)
    quiet = lambda line: None  # noqa: E731
    character = upload(server, "/v1/assets/characters", {"file": checked.character}, "character", quiet)
    cloths = [upload(server, "/v1/assets/cloth", files, clip, quiet)["id"] for clip, files in checked.clip_cloth]
    assets = BakeInputSet(character["id"], clip_cloth=zip(["Walking", "Running"], cloths))
    response = server.request("POST", "/v1/bakes", "starting the bake", json=client_body(args, checked, assets))
    assert response.status_code == 202, response.text
    assert response.json()["inputs"]["clip_cloth"] == [["Walking", cloths[0]], ["Running", cloths[1]]]
