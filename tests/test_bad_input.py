"""Every broken upload or request of the corpus (tests/corpus.py) gets a 4xx problem document of the
right type, never a 5xx, and stores nothing: the blob folder (staging included) and every table are
compared before and after each request.

The app is the real one (TestClient over ASGI) on a temporary SQLite file and blob store, with small
limits so that the corpus stays small: 1 MiB bodies, 40 zip entries, 8 MiB unzipped, 50:1 ratio,
256² texture pixels.

Regressions this corpus found (fixed in crowdbake.ingest.uploads):
* "glb with an external buffer uri": only .gltf uploads were checked for external URIs, so a .glb
  whose JSON chunk named "../../../etc/passwd" made the reader read that server file (and the error
  named the staging path). Every non-data URI is now refused, whatever the container.
* "zip with an unsupported compression method": zipfile raises NotImplementedError when such an entry
  is opened, which became a 500; the method is now checked with the other entry checks (422).
* "png truncated", "png with a bad CRC": Pillow's message names the file it opened, so the problem
  document showed the server's staging path; it now names the uploaded file.
* "glb whose nodes are null", "glb whose first accessor is a string", "a .gltf nested 100000 lists
  deep" (found by tests/test_fuzz.py): the glTF reader raised TypeError, AttributeError or
  RecursionError on JSON of the wrong shape, each a 500; crowdbake.formats.gltf.load_character now
  turns them into the ValueError its contract promises.
* "zip with strong encryption", "zip needing version 6.4", "zip entry with an empty name" (fuzz):
  NotImplementedError and IndexError from zipfile, and OSError from a seek before the file's start,
  were 500s; they are now invalid-file or unsafe-archive.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from corpus import (
    MAX_TEXTURE_PIXELS,
    MAX_UPLOAD_BYTES,
    MAX_ZIP_ENTRIES,
    MAX_ZIP_RATIO,
    MAX_ZIP_UNCOMPRESSED_BYTES,
    Case,
    corpus,
)
from service_fixtures import make_api

with tempfile.TemporaryDirectory() as _folder:
    CASES = corpus(Path(_folder))


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    return make_api(
        tmp_path_factory.mktemp("bad-input"), max_upload_bytes=MAX_UPLOAD_BYTES, max_zip_entries=MAX_ZIP_ENTRIES,
        max_zip_uncompressed_bytes=MAX_ZIP_UNCOMPRESSED_BYTES, max_zip_ratio=MAX_ZIP_RATIO, max_texture_pixels=MAX_TEXTURE_PIXELS,
    )


def send(api, case: Case, key: str = "all"):
    headers = {**api.auth(key), **case.headers}
    if case.files is not None or case.data is not None:
        return api.client.request(case.method, case.path, files=case.files, data=case.data, headers=headers)
    if case.content is not None:
        return api.client.request(case.method, case.path, content=case.content, headers=headers)
    return api.client.request(case.method, case.path, json=case.json_body, headers=headers)


def test_the_corpus_covers_every_kind_of_bad_input():
    names = " ".join(case.name for case in CASES)
    for kind in ("glb truncated", "glb with garbage", "pc2 that promises", "obj with a face index past", "NaN vertex",
                 "2^40", "zip bomb", "zip entry '../evil.obj'", "symbolic link", "a JSON body to an upload",
                 "more than the limit", "bake name '../escape'", "bake version '%2e%2e%2f'", "bake name 'walker\\x00'"):
        assert kind in names, kind
    assert len(CASES) >= 120


@pytest.mark.parametrize("case", CASES, ids=[case.name for case in CASES])
def test_bad_input_is_a_4xx_problem_and_stores_nothing(api, case):
    before = api.snapshot()
    response = send(api, case)
    assert response.status_code in case.statuses, (response.status_code, response.text[:500])
    assert response.headers["content-type"] == "application/problem+json"
    problem = response.json()
    if case.problem is not None:
        assert problem["type"] == f"/problems/{case.problem}", problem
    assert problem["status"] == response.status_code and problem["instance"] == case.path
    assert problem["detail"] and "Traceback" not in response.text
    for error in problem.get("errors") or []:
        assert error["field"] and error["message"]
        # Messages name the uploaded file, never the server's staging path.
        assert ".incoming" not in error["message"] and str(api.settings.data_dir) not in response.text
    assert api.snapshot() == before


def test_a_streamed_body_over_the_limit_is_cut_off_and_stores_nothing(api):
    """No Content-Length (chunked): the server counts what arrives and stops at the limit."""
    before = api.snapshot()
    head = b'--x\r\nContent-Disposition: form-data; name="file"; filename="c.glb"\r\n\r\n'

    def body():
        yield head
        for _ in range(MAX_UPLOAD_BYTES // 65536 + 2):
            yield b"\0" * 65536

    response = api.client.post("/v1/assets/characters", content=body(),
                               headers={**api.auth("upload"), "Content-Type": "multipart/form-data; boundary=x"})
    assert response.status_code == 413 and response.json()["type"] == "/problems/payload-too-large"
    assert api.snapshot() == before


def test_good_inputs_still_pass_with_the_same_limits(api, tmp_path):
    """The corpus's limits refuse what is broken, not what is merely small: the valid files it is
    derived from are accepted (so each refusal above is about the defect, not the setup)."""
    from service_fixtures import obj_bytes, obj_sequence_zip, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth

    points, faces = tiny_cloth(frames=12)
    auth = api.auth("upload")
    assert api.client.post("/v1/assets/characters", files={"file": ("c.glb", tiny_character_glb())}, headers=auth).status_code == 201
    assert api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))},
                           headers=auth).status_code == 201
    assert api.client.post("/v1/assets/cloth", files={"sequence": ("f.zip", obj_sequence_zip(points * 2, faces, tmp_path))}, headers=auth).status_code == 201
    assert api.client.post("/v1/assets/textures", files={"file": ("diffuse_0.png", png_bytes())}, headers=auth).status_code == 201


def test_a_chain_of_16000_nodes_loads_in_linear_time(tmp_path):
    """The node hierarchy is walked once: a 16,000-node chain (317 KB) is a valid character and loads
    in well under a second (a quadratic check took 18.7 s)."""
    import time

    from corpus import glb_node_chain
    from crowdbake.formats.gltf import load_character

    path = tmp_path / "chain.glb"
    path.write_bytes(glb_node_chain(16_000))
    started = time.perf_counter()
    character = load_character(path)
    assert time.perf_counter() - started < 5.0  # 0.1 s on an idle core; margin for a loaded machine
    assert character.joint_count == 1


def test_a_normal_embedded_texture_still_loads(tmp_path):
    """The header check refuses what is too large, not textures as such."""
    from corpus import big_png, glb_with_image
    from crowdbake.formats.gltf import load_character

    path = tmp_path / "textured.glb"
    path.write_bytes(glb_with_image(big_png(64, 32)))
    assert load_character(path).texture.shape[:2] == (32, 64)
