"""`crowdbake submit` sends every cloth form the server takes (.pc2 or .mdd with its mesh, .abc or .zip
alone) and JPEG texture variations; a wrong combination is one line and exit 2 before any upload.

The uploads go through the client's own functions (check_locally, upload, bake_body) to the real app
(FastAPI's TestClient is an httpx client), so the field names are checked against the server's route."""
from __future__ import annotations

from pathlib import Path

import pytest

from crowdbake.client.http import Server
from crowdbake.client.submit import bake_body, build_parser, check_locally, run, upload
from crowdbake.formats.mdd import write_mdd
from crowdbake.ingest.input_modes import BakeInputSet
from service_fixtures import make_api, obj_bytes, obj_sequence_zip, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth


@pytest.fixture
def inputs(tmp_path) -> Path:
    """A folder with the tiny character, its sheet as .pc2, .mdd, .zip (and its .obj), and textures."""
    from PIL import Image

    points, faces = tiny_cloth(frames=12)
    (tmp_path / "character.glb").write_bytes(tiny_character_glb())
    (tmp_path / "sheet.pc2").write_bytes(pc2_bytes(points))
    write_mdd(tmp_path / "sheet.mdd", points, fps=30.0)
    (tmp_path / "sheet.obj").write_bytes(obj_bytes(points[0], faces, tmp_path))
    (tmp_path / "frames.zip").write_bytes(obj_sequence_zip(points, faces, tmp_path))
    textures = tmp_path / "textures"
    textures.mkdir()
    (textures / "diffuse_plain.png").write_bytes(png_bytes())
    Image.new("RGB", (8, 8), (200, 40, 40)).save(textures / "diffuse_photo.jpg", "JPEG")
    (textures / "notes.txt").write_text("not a texture")
    return tmp_path


def _args(folder: Path, cloth: str, *extra: str) -> list[str]:
    return [str(folder / "character.glb"), "--server", "http://127.0.0.1:9", "--cloth", str(folder / cloth),
            "--name", "forms", "--version", "1.0.0", *extra]


@pytest.mark.parametrize("cloth, mesh, fields", [
    ("sheet.pc2", True, {"cache": "sheet.pc2", "mesh": "sheet.obj"}),
    ("sheet.mdd", True, {"cache": "sheet.mdd", "mesh": "sheet.obj"}),
    ("skirt.abc", False, {"cache": "skirt.abc"}),
    ("frames.zip", False, {"sequence": "frames.zip"}),
])
def test_each_cloth_form_goes_in_the_servers_fields(inputs, cloth, mesh, fields):
    (inputs / "skirt.abc").write_bytes(b"Ogawa")  # only the file's presence is checked locally
    args = build_parser().parse_args(_args(inputs, cloth, *(["--cloth-mesh", str(inputs / "sheet.obj")] if mesh else []),
                                           "--textures", str(inputs / "textures")))
    checked = check_locally(args)
    assert {field: path.name for field, path in checked.cloth_files.items()} == fields
    assert sorted(checked.textures) == ["diffuse_photo.jpg", "diffuse_plain.png"]


@pytest.mark.parametrize("cloth, extra, message", [
    ("sheet.mdd", [], "--cloth {dir}/sheet.mdd needs --cloth-mesh CLOTH.obj"),
    ("sheet.pc2", [], "--cloth {dir}/sheet.pc2 needs --cloth-mesh CLOTH.obj"),
    ("frames.zip", ["--cloth-mesh", "{dir}/sheet.obj"], "--cloth-mesh goes with a .pc2 or .mdd cache; a .zip of OBJ frames carries its own mesh"),
    ("skirt.abc", ["--cloth-mesh", "{dir}/sheet.obj"], "--cloth-mesh goes with a .pc2 or .mdd cache; an Alembic .abc carries its own mesh"),
    ("sheet.obj", [], "a cloth cache is .pc2 or .mdd (with --cloth-mesh), or .abc or .zip (alone)"),
    ("missing.mdd", ["--cloth-mesh", "{dir}/sheet.obj"], "{dir}/missing.mdd: no such file"),
    ("sheet.pc2", ["--cloth-mesh", "{dir}/sheet.obj", "--textures", "{dir}/outfits-jpeg"], "outfits.jpg: the outfit map must be a PNG"),
])
def test_a_wrong_cloth_or_texture_combination_is_one_line_and_exit_2(inputs, capsys, cloth, extra, message):
    outfits_jpeg = inputs / "outfits-jpeg"
    outfits_jpeg.mkdir()
    (outfits_jpeg / "diffuse_a.png").write_bytes(png_bytes())
    (outfits_jpeg / "outfits.jpg").write_bytes(b"\xff\xd8\xff")
    args = build_parser().parse_args([part.format(dir=inputs) for part in _args(inputs, cloth, *extra)])
    assert run(args) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [f"crowdbake submit: error: {lines[0].removeprefix('crowdbake submit: error: ')}"]
    assert message.format(dir=inputs) in lines[0]


def test_mdd_zip_and_jpeg_uploads_are_taken_by_the_server(inputs, tmp_path):
    """Each form the client builds is stored by POST /v1/assets/cloth as its format, and a bake of an
    MDD cloth with a JPEG and a PNG variation is accepted (202): the names match the server's."""
    api = make_api(tmp_path / "api")
    api.client.headers.update(api.auth("all"))
    server = Server(api.client, retry_for=1.0)
    formats = {}
    for cloth, mesh in (("sheet.mdd", True), ("frames.zip", False), ("sheet.pc2", True)):
        args = build_parser().parse_args(_args(inputs, cloth, *(["--cloth-mesh", str(inputs / "sheet.obj")] if mesh else []),
                                               "--textures", str(inputs / "textures")))
        checked = check_locally(args)
        asset = upload(server, "/v1/assets/cloth", checked.cloth_files, cloth, say=lambda line: None)
        formats[cloth] = (asset["files"]["cache"]["media_type"], asset["info"].get("source", {}).get("filename"))
    # The zip is converted to PC2 + OBJ on upload (and keeps its name as the source); the PC2 of the same
    # frames is then that very asset.
    assert formats == {"sheet.mdd": ("application/x-mdd", None), "frames.zip": ("application/x-pc2", "frames.zip"),
                       "sheet.pc2": ("application/x-pc2", "frames.zip")}

    args = build_parser().parse_args(_args(inputs, "sheet.mdd", "--cloth-mesh", str(inputs / "sheet.obj"), "--textures", str(inputs / "textures"),
                                           "--cycle-frames", "6"))
    checked = check_locally(args)
    character = upload(server, "/v1/assets/characters", {"file": checked.character}, "character", say=lambda line: None)
    cloth = upload(server, "/v1/assets/cloth", checked.cloth_files, "cloth", say=lambda line: None)
    textures = {name: upload(server, "/v1/assets/textures", {"file": path}, name, say=lambda line: None)["id"] for name, path in checked.textures.items()}
    response = server.request("POST", "/v1/bakes", "starting the bake", json=bake_body(args, checked, BakeInputSet(character["id"], cloth["id"], textures=textures)))
    assert response.status_code == 202, response.text


def test_an_abc_goes_alone_in_the_cache_field(inputs, tmp_path):
    """The server reads an .abc sent alone in 'cache' as Alembic (here a broken one, refused naming
    'cache'), not as a malformed request (which it answers for a wrong set of fields)."""
    (inputs / "skirt.abc").write_bytes(b"not an alembic archive")
    api = make_api(tmp_path / "api")
    api.client.headers.update(api.auth("all"))
    checked = check_locally(build_parser().parse_args(_args(inputs, "skirt.abc")))
    response = api.client.post("/v1/assets/cloth", files={field: (path.name, path.read_bytes()) for field, path in checked.cloth_files.items()})
    problem = response.json()
    assert response.status_code in (415, 422), problem
    assert problem["errors"][0]["field"] == "cache" and "Alembic" in problem["errors"][0]["message"], problem
