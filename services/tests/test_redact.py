"""Bake logs, bake errors and problem details never show the server's data folder: workers write
absolute paths, the API answers relative names."""
from __future__ import annotations

from crowdbake.redact import path_replacements, redact_text
from service_fixtures import make_api, obj_bytes, pc2_bytes, tiny_character_glb, tiny_cloth


def test_log_and_error_name_relative_paths(tmp_path):
    from crowdbake.storage import records
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.models import Bake

    api = make_api(tmp_path)
    points, faces = tiny_cloth(frames=12)
    auth = api.auth("ci")
    character = api.client.post("/v1/assets/characters", files={"file": ("w.glb", tiny_character_glb())}, headers=auth).json()
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))}, headers=auth).json()
    bake_id = api.client.post("/v1/bakes", json={"name": "walker", "version": "1", "character": character["id"], "cloth": cloth["id"]}, headers=auth).json()["id"]
    work = f"{api.settings.work_dir}/abc123/cycle"
    blob = f"{api.settings.blob_dir}/ab/cdef"
    with session_scope(api.sessions) as session:
        records.append_log(session, bake_id, "INFO", "cycle", f"cycle outputs written to {work}")
        records.fail_bake(session, session.get(Bake, bake_id), "validate", {"type": "invalid-file", "title": "bad input", "detail": f"{blob}: truncated"})
    data_dir = str(api.settings.data_dir)
    log = api.client.get(f"/v1/bakes/{bake_id}/log", headers=auth).text
    assert "cycle outputs written to work/abc123/cycle" in log and "blobs/ab/cdef: truncated" in log
    bake = api.client.get(f"/v1/bakes/{bake_id}", headers=auth)
    assert bake.json()["error"]["detail"] == "blobs/ab/cdef: truncated"
    assert data_dir not in log and data_dir not in bake.text
    # The database keeps what the worker wrote, for operators.
    with session_scope(api.sessions) as session:
        assert any(work in line.message for line in records.log_lines(session, bake_id))


def test_problem_details_never_show_the_data_folder(tmp_path):
    api = make_api(tmp_path)
    import json

    from starlette.requests import Request

    from crowdbake.api.problems import Problem, problem_response

    app = api.client.app
    request = Request({"type": "http", "app": app, "method": "GET", "path": "/v1/x", "headers": [], "query_string": b""})
    problem = Problem("invalid-file", f"{api.settings.blob_dir}/.incoming/tmp1: bad", [{"field": "file", "message": f"{api.settings.data_dir}/x bad"}])
    body = json.loads(problem_response(request, problem).body)
    assert body["detail"] == "blobs/.incoming/tmp1: bad" and body["errors"][0]["message"] == "x bad"


def test_nested_folders_win_over_the_data_folder(tmp_path):
    from crowdbake.settings import Settings

    settings = Settings(data_dir=tmp_path / "data")
    replacements = path_replacements(settings)
    assert redact_text(f"{settings.work_dir}/k/x.png and {settings.data_dir}/crowdbake.sqlite3", replacements) == "work/k/x.png and crowdbake.sqlite3"
