"""Inputs as studios export them, through every entry point: `crowdbake cycle`, `crowdbake bake` (the
validate stage) and the REST upload + bake request. The files are made here from a garment whose
answer is known: the synthetic skirt of test_cycle_cli on its cylinder body (Y-up metres), then
rotated to Z-up, scaled to centimetres, written at 30 fps, as MDD, as a zip of OBJ frames; and a JPEG
texture variation. Placement must refuse the wrong frames with one line (CLI) or a problem naming
`up` / `units` (REST), and accept them converted when told."""
from __future__ import annotations

import io
import itertools
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from crowdbake.cli import main
from crowdbake.formats.mdd import write_mdd
from crowdbake.formats.obj import write_obj
from crowdbake.formats.pc2 import read_pc2, write_pc2
from service_fixtures import make_api, obj_bytes, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth
from test_cycle_cli import CYCLE, TARGET, cylinder_body, skirt_with_seam


def z_up(points: np.ndarray) -> np.ndarray:
    """Y-up -> Z-up, as Blender's exporters turn it: (x, y, z) -> (x, -z, y)."""
    return np.stack([points[..., 0], -points[..., 2], points[..., 1]], axis=-1).astype(np.float32)


@pytest.fixture(scope="module")
def garment(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("studio_inputs")
    cloth, faces = skirt_with_seam()
    body, body_faces = cylinder_body(len(cloth))
    paths = {name: folder / name for name in ("cloth.pc2", "cloth.obj", "body.pc2", "body.obj", "zup.pc2", "zup.obj", "cm.pc2", "cm.obj", "cloth.mdd", "frames.zip")}
    write_pc2(paths["cloth.pc2"], cloth)
    write_obj(paths["cloth.obj"], cloth[0], faces)
    write_pc2(paths["body.pc2"], body)
    write_obj(paths["body.obj"], body[0], body_faces)
    write_pc2(paths["zup.pc2"], z_up(cloth))
    write_obj(paths["zup.obj"], z_up(cloth[0]), faces)
    write_pc2(paths["cm.pc2"], cloth * 100)
    write_obj(paths["cm.obj"], cloth[0] * 100, faces)
    write_mdd(paths["cloth.mdd"], cloth, fps=30.0)
    with zipfile.ZipFile(paths["frames.zip"], "w") as archive:
        for index, frame in enumerate(cloth):
            write_obj(folder / "frame.obj", frame, faces)
            archive.write(folder / "frame.obj", f"skirt/frame{index + 1}.obj")  # natural order: frame2 before frame10
    return paths


def cycle(garment: dict[str, Path], out: Path, cache: str, mesh: str | None, *extra: str) -> int:
    args = ["cycle", str(garment[cache])]
    if mesh is not None:
        args += ["--mesh", str(garment[mesh])]
    args += ["--body", str(garment["body.pc2"]), "--body-mesh", str(garment["body.obj"]), "--cycle-frames", str(CYCLE),
             "--no-edge-pass", "--out", str(out), *extra]
    return main(args)


def one_line(capsys) -> str:
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    return lines[0]


# ------------------------------------------------------------------------------------- crowdbake cycle


@pytest.mark.parametrize("cache, mesh, flag", [("zup.pc2", "zup.obj", "--up z"), ("cm.pc2", "cm.obj", "--units cm")])
def test_cycle_refuses_a_wrong_frame_naming_the_flag_and_converts_with_it(garment, tmp_path, capsys, cache, mesh, flag):
    assert cycle(garment, tmp_path / "refused", cache, mesh) == 2
    line = one_line(capsys)
    assert line.startswith("crowdbake cycle: error: the cloth cache looks") and line.endswith(f"pass {flag}")
    assert not (tmp_path / "refused" / "cycle.json").exists()
    assert cycle(garment, tmp_path / "converted", cache, mesh, *flag.split()) == 0
    document = json.loads((tmp_path / "converted" / "cycle.json").read_text())
    assert document["start_frame"] == TARGET  # the same seam as the Y-up metre cache
    # The looped cache is in Y-up metres: frame 0 is the original cache's frame Fs.
    looped = read_pc2(tmp_path / "converted" / "looped.pc2").points
    original = read_pc2(garment["cloth.pc2"]).points
    np.testing.assert_allclose(looped[CYCLE // 2], original[TARGET + CYCLE // 2], atol=1e-5)


def test_cycle_reads_mdd_frame_rate_and_obj_zip_without_a_mesh(garment, tmp_path):
    assert cycle(garment, tmp_path / "mdd", "cloth.mdd", "cloth.obj") == 0
    mdd = json.loads((tmp_path / "mdd" / "cycle.json").read_text())
    assert mdd["start_frame"] == TARGET and mdd["input"]["fps"] == pytest.approx(30.0)  # from the MDD's frame times
    assert cycle(garment, tmp_path / "zip", "frames.zip", None) == 0
    sequence = json.loads((tmp_path / "zip" / "cycle.json").read_text())
    assert sequence["start_frame"] == TARGET and sequence["input"]["fps"] == 24.0
    # --fps overrides what the cache says (a 30 fps PC2: PC2 stores no rate).
    assert cycle(garment, tmp_path / "pc2", "cloth.pc2", "cloth.obj", "--fps", "30") == 0
    assert json.loads((tmp_path / "pc2" / "cycle.json").read_text())["input"]["fps"] == 30.0


def test_cycle_refuses_a_garment_beside_the_body(garment, tmp_path, capsys):
    cloth = read_pc2(garment["cloth.pc2"]).points
    write_pc2(tmp_path / "beside.pc2", cloth + np.array([3.0, 0.0, 0.0], np.float32))
    shutil.copy(garment["cloth.obj"], tmp_path / "beside.obj")
    paths = dict(garment, **{"beside.pc2": tmp_path / "beside.pc2", "beside.obj": tmp_path / "beside.obj"})
    assert cycle(paths, tmp_path / "out", "beside.pc2", "beside.obj") == 2
    assert "export the garment where it sits on the character" in one_line(capsys)


def test_cycle_needs_the_mesh_of_a_pc2_and_refuses_one_with_a_zip(garment, tmp_path, capsys):
    assert cycle(garment, tmp_path / "a", "cloth.pc2", None) == 2
    assert "needs its rest mesh" in one_line(capsys)
    assert cycle(garment, tmp_path / "b", "frames.zip", "cloth.obj") == 2
    assert "carries its own mesh" in one_line(capsys)


def test_shared_alembic_finds_a_cycle_as_good_as_its_pc2(shared_asset, tmp_path):
    """long_skirt.abc on CesiumMan with no --mesh: the same cycle as the PC2 (or within 10 % of its
    pass-1 distance)."""
    from crowdbake.formats.alembic import alembic_available

    abc = shared_asset("long_skirt/long_skirt.abc")
    character = shared_asset("CesiumMan.glb")
    if not alembic_available():
        pytest.skip("the crowdbake[alembic] extra (bpy) is not installed")
    common = ["--character", str(character), "--no-edge-pass"]
    assert main(["cycle", str(abc), *common, "--out", str(tmp_path / "abc")]) == 0
    assert main(["cycle", str(abc.with_suffix(".pc2")), "--mesh", str(abc.with_suffix(".obj")), *common, "--out", str(tmp_path / "pc2")]) == 0
    from_abc = json.loads((tmp_path / "abc" / "cycle.json").read_text())
    from_pc2 = json.loads((tmp_path / "pc2" / "cycle.json").read_text())
    assert from_abc["input"]["fps"] == pytest.approx(24.0) and from_abc["cycle_frames"] == from_pc2["cycle_frames"]
    best = {c["start_frame"]: c["vertex_distance"] for c in from_pc2["candidates"]}
    abc_distance = next(c["vertex_distance"] for c in from_abc["candidates"] if c["start_frame"] == from_abc["start_frame"])
    assert from_abc["start_frame"] == from_pc2["start_frame"] or abc_distance <= 1.1 * best[from_pc2["start_frame"]]


# ---------------------------------------------------------------------- crowdbake bake / validate stage


@pytest.fixture(scope="module")
def studio_sample(small_sample, tmp_path_factory) -> Path:
    """The small sample with its cloth as a Z-up centimetre MDD at 30 fps and one JPEG variation."""
    from PIL import Image

    folder = tmp_path_factory.mktemp("studio_sample")
    shutil.copy(small_sample / "character.glb", folder / "character.glb")
    shutil.copy(small_sample / "cloth.obj", folder / "plain.obj")
    cloth = read_pc2(small_sample / "cloth.pc2").points
    write_mdd(folder / "skirt.mdd", z_up(cloth) * 100, fps=30.0)
    from crowdbake.formats.obj import read_obj

    mesh = read_obj(small_sample / "cloth.obj")
    rest = np.zeros((mesh.position_count, 3), np.float32)
    rest[mesh.source_index] = mesh.positions
    write_obj(folder / "skirt.obj", z_up(rest) * 100, mesh.source_index[mesh.faces.astype(np.int64)],
              uvs=mesh.uvs, uv_faces=mesh.faces.astype(np.int64))
    textures = folder / "textures"
    shutil.copytree(small_sample / "textures", textures)
    first = sorted(textures.glob("diffuse_*.png"))[0]
    with Image.open(first) as image:
        image.convert("RGB").save(first.with_suffix(".jpg"), quality=95)
    first.unlink()
    return folder


def bake_args(folder: Path, out: Path, *extra: str) -> list[str]:
    return ["bake", str(folder / "character.glb"), "--cloth", str(folder / "skirt.mdd"), "--cloth-mesh", str(folder / "skirt.obj"),
            "--textures", str(folder / "textures"), "--name", "studio", "--version", "1", "--out", str(out / "bundles"),
            "--work", str(out / "work"), "--frames", "1", "--azimuths", "2", "--elevations", "0", "--tile", "16",
            "--lod-triangles", "900", "--candidates", "2", "--cycle-views", "2", *extra]


def test_bake_of_a_z_up_centimetre_mdd_with_a_jpeg_variation(studio_sample, small_sample, tmp_path, capsys):
    from crowdbake.formats.bundle import verify_bundle
    from crowdbake.stages.validate import load_job

    assert main(bake_args(studio_sample, tmp_path)) == 2
    line = one_line(capsys)
    assert line.startswith("crowdbake bake: error: --up: the cloth cache looks Z-up") and "pass --up z --units cm" in line

    assert main(bake_args(studio_sample, tmp_path, "--up", "z", "--units", "cm")) == 0
    out = capsys.readouterr().out
    assert "at 30 fps" in out  # the MDD's own rate, recorded by validate and used by the cycle
    jpeg = next((studio_sample / "textures").glob("*.jpg")).name
    assert "no colour-region codes" in out and jpeg in out
    job = load_job(tmp_path / "work")
    assert job.fps == pytest.approx(30.0) and job.cloth_format == "mdd" and job.textures["without_region_codes"] == [jpeg]
    staged = read_pc2(tmp_path / "work" / "inputs" / job.inputs["cloth"]).points
    np.testing.assert_allclose(staged, read_pc2(small_sample / "cloth.pc2").points, atol=1e-5)  # back in Y-up metres
    verify_bundle(tmp_path / "bundles" / "studio" / "1")


# ------------------------------------------------------------------------------ REST upload + bake request


@pytest.fixture
def api(tmp_path):
    return make_api(tmp_path)


def _upload_character(api) -> str:
    response = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", tiny_character_glb())}, headers=api.auth("upload"))
    assert response.status_code == 201, response.text
    return response.json()["id"]


def _mdd_bytes(points: np.ndarray, fps: float, tmp_path: Path) -> bytes:
    write_mdd(tmp_path / "upload.mdd", points, fps)
    return (tmp_path / "upload.mdd").read_bytes()


_VERSIONS = itertools.count()


def _bake(api, character: str, cloth: str, textures: dict | None = None, **params):
    # A new version each time: one version baking from other inputs is a conflict (409).
    body = {"name": "walker", "version": f"1.0.{next(_VERSIONS)}", "character": character, "cloth": cloth,
            "textures": textures or {}, "params": {"impostor_frames": 2, "azimuths": 4, "tile_size": 32, **params}}
    return api.client.post("/v1/bakes", json=body, headers=api.auth("ci"))


def test_rest_mdd_upload_and_placement_problems_name_up_and_units(api, tmp_path):
    points, faces = tiny_cloth(frames=12)
    character = _upload_character(api)
    upload = api.auth("upload")
    zup = api.client.post("/v1/assets/cloth", files={"cache": ("sheet.mdd", _mdd_bytes(z_up(points), 24.0, tmp_path)),
                                                     "mesh": ("sheet.obj", obj_bytes(z_up(points[0]), faces, tmp_path))}, headers=upload)
    assert zup.status_code == 201, zup.text
    info = zup.json()["info"]
    assert info["format"] == "mdd" and info["fps"] == pytest.approx(24.0) and info["frame_count"] == 12
    assert zup.json()["files"]["cache"]["media_type"] == "application/x-mdd"

    refused = _bake(api, character, zup.json()["id"])
    assert refused.status_code == 422 and refused.headers["content-type"] == "application/problem+json"
    error = refused.json()["errors"][0]
    assert error["field"] == "params.up" and 'params.up = "z"' in error["message"]
    assert _bake(api, character, zup.json()["id"], up="z").status_code == 202

    cm = api.client.post("/v1/assets/cloth", files={"cache": ("cm.pc2", pc2_bytes(points * 100)),
                                                    "mesh": ("cm.obj", obj_bytes(points[0] * 100, faces, tmp_path))}, headers=upload)
    assert cm.status_code == 201, cm.text
    refused = _bake(api, character, cm.json()["id"])
    assert refused.status_code == 422 and refused.json()["errors"][0]["field"] == "params.units"
    assert 'params.units = "cm"' in refused.json()["errors"][0]["message"]
    assert _bake(api, character, cm.json()["id"], units="cm", up="y").status_code == 202


def test_rest_mdd_frame_rate_sets_the_cycle_length(api, tmp_path):
    """The tiny walk lasts 0.25 s: 6 frames at 24 fps, 12 at 48 fps, so 12 frames of MDD at 48 fps
    hold one cycle only."""
    points, faces = tiny_cloth(frames=12)
    character = _upload_character(api)
    fast = api.client.post("/v1/assets/cloth", files={"cache": ("fast.mdd", _mdd_bytes(points, 48.0, tmp_path)),
                                                      "mesh": ("fast.obj", obj_bytes(points[0], faces, tmp_path))}, headers=api.auth("upload"))
    assert fast.status_code == 201, fast.text
    response = _bake(api, character, fast.json()["id"])
    assert response.status_code == 422 and "two cycles of 12" in response.json()["errors"][0]["message"]
    assert _bake(api, character, fast.json()["id"], fps=24.0).status_code == 202


@pytest.mark.parametrize("fps", [1e-30, 1e30, 0.5, 5000.0])
def test_rest_mdd_frame_rate_outside_the_sane_range_is_refused_at_upload(api, tmp_path, fps):
    """Regression: an MDD at 1e-30 fps was stored and baked, publishing frames_per_second 1e-30; at 1e30
    the bake failed with "OverflowError: Python int too large". The one range, crowdbake.params'
    MIN_FPS..MAX_FPS, now refuses both at upload, naming the value and the range."""
    points, faces = tiny_cloth(frames=12)
    response = api.client.post("/v1/assets/cloth", files={"cache": ("odd.mdd", _mdd_bytes(points, fps, tmp_path)),
                                                          "mesh": ("odd.obj", obj_bytes(points[0], faces, tmp_path))}, headers=api.auth("upload"))
    assert response.status_code == 422 and response.headers["content-type"] == "application/problem+json", response.text
    error = response.json()["errors"][0]
    assert error["field"] == "cache" and "frames per second is outside the sane range 1..1000" in error["message"]


@pytest.mark.parametrize("fps, sample_rate, field", [(0.5, 1.0, "params.fps"), (1e30, 1.0, "params.fps"), (None, 1e-30, "cloth"), (None, 100.0, "cloth")])
def test_rest_bake_frame_rate_outside_the_sane_range_is_a_422(api, tmp_path, fps, sample_rate, field):
    """The fps parameter and a PC2's rate (24 / its sample interval) meet the same range at the request."""
    points, faces = tiny_cloth(frames=12)
    character = _upload_character(api)
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points, sample_rate=sample_rate)),
                                                       "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))}, headers=api.auth("upload"))
    assert cloth.status_code == 201, cloth.text
    response = _bake(api, character, cloth.json()["id"], cycle_frames=4, **({} if fps is None else {"fps": fps}))
    assert response.status_code == 422 and response.headers["content-type"] == "application/problem+json", response.text
    error = response.json()["errors"][0]
    # The parameter meets its schema's bounds (ge 1, le 1000); a cache's rate meets crowdbake.params.cache_fps.
    assert error["field"] == field and ("1..1000" in error["message"] or "equal to 1" in error["message"]), error


def test_cache_fps_is_the_one_range_every_input_meets():
    from crowdbake.params import MAX_FPS, MIN_FPS, FrameRateError, cache_fps

    assert cache_fps(None, 30.0) == 30.0 and cache_fps(None, None, 2.0) == 12.0 and cache_fps(MIN_FPS, None) == MIN_FPS
    for given, file_fps, sample_rate in [(MAX_FPS * 2, None, 1.0), (None, 1e-300, 1.0), (None, None, 1e-30), (float("nan"), None, 1.0)]:
        with pytest.raises(FrameRateError, match=r"outside the sane range 1\.\.1000"):
            cache_fps(given, file_fps, sample_rate)


def test_rest_animation_by_name_or_index(api, tmp_path):
    points, faces = tiny_cloth(frames=12)
    character = _upload_character(api)
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))},
                            headers=api.auth("upload")).json()["id"]
    names = [entry["name"] for entry in api.client.get(f"/v1/assets/{character}", headers=api.auth("bake")).json()["info"]["animations"]]
    assert len(names) == 1
    response = _bake(api, character, cloth, animation="Run")
    assert response.status_code == 422 and response.json()["errors"][0]["field"] == "params.animation"
    assert names[0] in response.json()["errors"][0]["message"]
    assert _bake(api, character, cloth, animation=3).json()["errors"][0]["field"] == "params.animation"
    assert _bake(api, character, cloth, animation=names[0]).status_code == 202


def test_rest_jpeg_texture_variation(api, tmp_path):
    from PIL import Image

    picture = io.BytesIO()
    Image.new("RGB", (8, 8), (200, 40, 40)).save(picture, "JPEG")
    response = api.client.post("/v1/assets/textures", files={"file": ("red.jpg", picture.getvalue())}, headers=api.auth("upload"))
    assert response.status_code == 201, response.text
    asset = response.json()
    assert asset["info"]["has_region_codes"] is False and "no colour-region codes" in asset["info"]["note"]
    assert asset["files"]["file"]["media_type"] == "image/jpeg"
    png = api.client.post("/v1/assets/textures", files={"file": ("d.png", png_bytes())}, headers=api.auth("upload")).json()["id"]
    points, faces = tiny_cloth(frames=12)
    character = _upload_character(api)
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))},
                            headers=api.auth("upload")).json()["id"]
    misnamed = _bake(api, character, cloth, {"diffuse_0.png": asset["id"]})
    assert misnamed.status_code == 422 and misnamed.json()["errors"][0]["field"] == "textures.diffuse_0.png"
    assert _bake(api, character, cloth, {"diffuse_0.jpg": asset["id"], "diffuse_1.png": png}).status_code == 202
    broken = api.client.post("/v1/assets/textures", files={"file": ("bad.jpg", b"\xff\xd8\xff" + b"\0" * 40)}, headers=api.auth("upload"))
    assert broken.status_code == 422 and broken.json()["errors"][0]["file"] == "bad.jpg"


def test_rest_alembic_needs_the_extra(api, monkeypatch, shared_asset):
    abc = shared_asset("long_skirt/long_skirt.abc").read_bytes()
    monkeypatch.setenv("CROWDBAKE_BPY_PYTHON", "/nonexistent/python")
    response = api.client.post("/v1/assets/cloth", files={"cache": ("skirt.abc", abc)}, headers=api.auth("upload"))
    assert response.status_code == 415 and response.headers["content-type"] == "application/problem+json"
    assert "crowdbake[alembic]" in response.json()["detail"] and response.json()["errors"][0]["field"] == "cache"


def test_rest_alembic_upload_and_bake_request_on_cesium_man(tmp_path, shared_asset):
    from crowdbake.formats.alembic import alembic_available

    abc = shared_asset("long_skirt/long_skirt.abc")
    glb = shared_asset("CesiumMan.glb")
    if not alembic_available():
        pytest.skip("the crowdbake[alembic] extra (bpy) is not installed")
    api = make_api(tmp_path, max_upload_bytes=64 << 20)
    character = api.client.post("/v1/assets/characters", files={"file": ("CesiumMan.glb", glb.read_bytes())}, headers=api.auth("upload"))
    assert character.status_code == 201, character.text
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("long_skirt.abc", abc.read_bytes())}, headers=api.auth("upload"))
    assert cloth.status_code == 201, cloth.text
    info = cloth.json()["info"]
    assert info["format"] == "abc" and info["fps"] == pytest.approx(24.0) and info["frame_count"] == 385 and set(cloth.json()["files"]) == {"cache"}
    assert _bake(api, character.json()["id"], cloth.json()["id"]).status_code == 202
