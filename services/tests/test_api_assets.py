"""Asset uploads through the real app (TestClient, SQLite and blob store in tmp_path, or PostgreSQL and
an S3 bucket when the tests have those servers): stored once by sha256, refused with RFC 9457 problems
that name the field, file and place, and nothing of a refused upload is kept (the blob store and every
table are unchanged)."""
from __future__ import annotations

import pytest

from service_fixtures import STORES, make_api, obj_bytes, obj_sequence_zip, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth

PROBLEM = "application/problem+json"


@pytest.fixture(params=STORES)
def api(tmp_path, request):
    return make_api(tmp_path, request.param, max_upload_bytes=200_000)


@pytest.fixture
def cloth(tmp_path):
    points, faces = tiny_cloth(frames=12)
    return points, faces, pc2_bytes(points), obj_bytes(points[0], faces, tmp_path)


def assert_problem(response, status: int, slug: str):
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == PROBLEM
    body = response.json()
    assert body["type"] == f"/problems/{slug}" and body["status"] == status
    assert body["title"] and body["detail"] and body["instance"].startswith("/v1/")
    return body


def test_character_is_stored_once_by_sha256(api):
    glb = tiny_character_glb()
    first = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", glb)}, headers=api.auth("upload"))
    assert first.status_code == 201, first.text
    asset = first.json()
    assert first.headers["location"] == f"/v1/assets/{asset['id']}"
    assert asset["kind"] == "character" and asset["files"]["file"]["size"] == len(glb)
    assert asset["info"]["vertex_count"] == 4 and asset["info"]["animation_seconds"] == pytest.approx(0.25)
    blob_files, counts = api.snapshot()
    again = api.client.post("/v1/assets/characters", files={"file": ("renamed.glb", glb)}, headers=api.auth("upload"))
    assert again.status_code == 200 and again.json()["id"] == asset["id"]
    assert api.snapshot() == (blob_files, counts)  # deduplicated: no new blob, no new row
    fetched = api.client.get(asset["files"] and f"/v1/assets/{asset['id']}", headers=api.auth("bake"))
    assert fetched.status_code == 200 and fetched.json()["digest"] == asset["digest"]


def test_cloth_pair_and_sequence(api, cloth, tmp_path):
    points, faces, cache, mesh = cloth
    pair = api.client.post("/v1/assets/cloth", files={"cache": ("skirt.pc2", cache), "mesh": ("skirt.obj", mesh)},
                           data={"cycle_frames": "6"}, headers=api.auth("upload"))
    assert pair.status_code == 201, pair.text
    assert pair.json()["info"]["frame_count"] == 12 and set(pair.json()["files"]) == {"cache", "mesh"}
    # The same frames as a zip of OBJs convert to the same PC2 and OBJ bytes: the same asset.
    same = api.client.post("/v1/assets/cloth", files={"sequence": ("skirt.zip", obj_sequence_zip(points, faces, tmp_path))},
                           headers=api.auth("upload"))
    assert same.status_code == 200 and same.json()["id"] == pair.json()["id"], same.text
    other_points, _ = tiny_cloth(frames=12, seed=1)
    sequence = api.client.post("/v1/assets/cloth", files={"sequence": ("walk.zip", obj_sequence_zip(other_points, faces, tmp_path))},
                               headers=api.auth("upload"))
    assert sequence.status_code == 201, sequence.text
    info = sequence.json()["info"]
    assert info["frames_from"] == "obj-sequence" and info["frame_count"] == 12 and info["source"]["filename"] == "walk.zip"
    assert sequence.json()["files"]["cache"]["filename"] == "walk.pc2"


def test_texture_upload_and_listing(api):
    response = api.client.post("/v1/assets/textures", files={"file": ("diffuse_0.png", png_bytes(8, 4))}, headers=api.auth("upload"))
    assert response.status_code == 201 and response.json()["info"] == {"width": 8, "height": 4, "mode": "RGBA"}
    listing = api.client.get("/v1/assets?kind=texture", headers=api.auth("upload")).json()
    assert listing["count"] == 1 and listing["data"][0]["id"] == response.json()["id"]
    assert api.client.get("/v1/assets?kind=character", headers=api.auth("upload")).json()["count"] == 0


def bad_uploads(cloth, tmp_path):
    """(endpoint, files, data, status, problem slug, field, expected where) for each refused upload."""
    points, faces, cache, mesh = cloth
    glb = tiny_character_glb()
    nan_cache = bytearray(cache)
    nan_cache[32 + 4 * 7: 32 + 4 * 8] = b"\x00\x00\xc0\x7f"  # float NaN at point 2, y
    return {
        "unknown extension": ("/v1/assets/characters", {"file": ("walker.fbx", glb)}, None, 415, "unsupported-format", "file", None),
        "png named glb": ("/v1/assets/characters", {"file": ("walker.glb", png_bytes())}, None, 422, "format-mismatch", "file", "byte 0"),
        "truncated glb": ("/v1/assets/characters", {"file": ("walker.glb", glb[:-7])}, None, 422, "invalid-file", "file", "byte 8"),
        "truncated pc2": ("/v1/assets/cloth", {"cache": ("c.pc2", cache[:-3]), "mesh": ("c.obj", mesh)}, None, 422, "invalid-file", "cache", f"byte {len(cache) - 3}"),
        "nan in pc2": ("/v1/assets/cloth", {"cache": ("c.pc2", bytes(nan_cache)), "mesh": ("c.obj", mesh)}, None, 422, "invalid-file", "cache", "byte 60"),
        "vertex counts disagree": ("/v1/assets/cloth", {"cache": ("c.pc2", pc2_bytes(points[:, :-2])), "mesh": ("c.obj", mesh)}, None, 422, "invalid-file", "cache", "byte 16"),
        "too few frames": ("/v1/assets/cloth", {"cache": ("c.pc2", cache), "mesh": ("c.obj", mesh)}, {"cycle_frames": "7"}, 422, "invalid-file", "cache", "byte 28"),
        "zip slip": ("/v1/assets/cloth", {"sequence": ("s.zip", _zip({"../../evil.obj": b"v 0 0 0\n"}))}, None, 422, "unsafe-archive", "sequence", "entry ../../evil.obj"),
        "zip bomb": ("/v1/assets/cloth", {"sequence": ("s.zip", _zip({"f/frame0.obj": b"\n" * (4 << 20)}))}, None, 422, "unsafe-archive", "sequence", "entry f/frame0.obj"),
        "truncated png": ("/v1/assets/textures", {"file": ("diffuse_0.png", png_bytes(32, 32)[:-30])}, None, 422, "invalid-file", "file", None),
        "missing mesh": ("/v1/assets/cloth", {"cache": ("c.pc2", cache)}, None, 400, "malformed-request", "mesh", None),
        "unexpected field": ("/v1/assets/characters", {"model": ("walker.glb", glb)}, None, 400, "malformed-request", "model", None),
    }


def _zip(entries: dict[str, bytes]) -> bytes:
    import io
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


CASES = ["unknown extension", "png named glb", "truncated glb", "truncated pc2", "nan in pc2", "vertex counts disagree",
         "too few frames", "zip slip", "zip bomb", "truncated png", "missing mesh", "unexpected field"]


@pytest.mark.parametrize("case", CASES)
def test_refused_uploads_store_nothing(api, cloth, tmp_path, case):
    endpoint, files, data, status, slug, field, where = bad_uploads(cloth, tmp_path)[case]
    before = api.snapshot()
    response = api.client.post(endpoint, files=files, data=data or {}, headers=api.auth("upload"))
    body = assert_problem(response, status, slug)
    assert body["errors"], body
    assert body["errors"][0]["field"] == field
    if where is not None:
        assert body["errors"][0]["where"] == where
    assert api.snapshot() == before


def test_oversize_body_is_refused_by_content_length(api):
    before = api.snapshot()
    body = b"x" * 300_000
    response = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", body)}, headers=api.auth("upload"))
    assert_problem(response, 413, "payload-too-large")
    assert api.snapshot() == before


def test_oversize_body_is_cut_off_while_streaming(api):
    """Without Content-Length (chunked), the limit is enforced as bytes arrive."""
    before = api.snapshot()
    boundary = "b0undary"
    head = f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="walker.glb"\r\n\r\n'.encode()

    def chunks():
        yield head
        for _ in range(40):
            yield b"glTF" + b"\0" * 9996
        yield f"\r\n--{boundary}--\r\n".encode()

    response = api.client.post("/v1/assets/characters", content=chunks(),
                               headers={**api.auth("upload"), "Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert_problem(response, 413, "payload-too-large")
    assert api.snapshot() == before


def test_uploads_need_the_upload_scope(api):
    files = {"file": ("walker.glb", tiny_character_glb())}
    assert_problem(api.client.post("/v1/assets/characters", files=files), 401, "unauthorized")
    assert_problem(api.client.post("/v1/assets/characters", files=files, headers={"Authorization": "Bearer cbk_000000000000_nope-nope-nope-nope-nope"}), 401, "unauthorized")
    assert_problem(api.client.post("/v1/assets/characters", files=files, headers=api.auth("read")), 403, "forbidden")
    response = api.client.post("/v1/assets/characters", files=files, headers={"X-API-Key": api.keys["upload"]})
    assert response.status_code == 201


def test_non_multipart_body_is_unsupported(api):
    response = api.client.post("/v1/assets/characters", content=tiny_character_glb(), headers={**api.auth("upload"), "Content-Type": "model/gltf-binary"})
    assert_problem(response, 415, "unsupported-format")


def test_multipart_body_cut_short_is_malformed_and_stores_nothing(api):
    before = api.snapshot()
    boundary = "cut"
    body = (f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="walker.glb"\r\n\r\n').encode() + tiny_character_glb()
    response = api.client.post("/v1/assets/characters", content=body,
                               headers={**api.auth("upload"), "Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert_problem(response, 400, "malformed-request")
    assert api.snapshot() == before
