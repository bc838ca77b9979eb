"""Security properties, each checked against the real thing:

* every write operation of the OpenAPI document needs a key, with the right scope (401 without one,
  401 for a revoked or malformed one, 403 for a key without the scope);
* keys are stored as sha256 digests: the raw key is nowhere in the database files;
* no user-supplied name reaches the file system unchecked: bundle names, versions and file paths
  with `../`, `%2e%2e`, absolute paths, NUL and very long names, sent as raw bytes to uvicorn,
  never serve a file outside the bundle (a planted secret never appears) and never 5xx; an upload's
  filename with `../` only labels the asset; a .glb whose JSON names a server file is refused;
* the C++ runtime (build/runtime/crowdview) refuses bundles whose hashes do not match, and fetching
  from a malicious server on loopback (paths with `../`, absolute paths, a sha256 that is a path,
  wrong bytes, too many bytes, a redirect to file://) writes nothing outside its cache folder.
"""
from __future__ import annotations

import hashlib
import http.server
import json
import os
import shutil
import socket
import sqlite3
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from reliability_fixtures import REPO, files_under, make_service
from service_fixtures import GOOD_BUNDLE, make_api, png_bytes, publish_vector_bundle, tiny_character_glb

CROWDVIEW = REPO / "build" / "runtime" / "crowdview"
SECRET = b"crowdbake-security-test-secret-7d1f"

# The scope each write operation needs (docs/service.md, "Endpoints").
WRITE_SCOPES = {
    ("POST", "/v1/assets/characters"): "upload", ("POST", "/v1/assets/cloth"): "upload", ("POST", "/v1/assets/textures"): "upload",
    ("POST", "/v1/assets/cycles"): "upload", ("POST", "/v1/assets/timelines"): "upload",
    ("POST", "/v1/bakes"): "bake", ("POST", "/v1/bakes/check"): "bake", ("POST", "/v1/bakes/{bake_id}/cancel"): "bake", ("POST", "/v1/bakes/{bake_id}/retry"): "bake",
    ("POST", "/v1/bakes/{bake_id}/publish"): "publish", ("PATCH", "/v1/bundles/{name}/{version}"): "publish",
}
OTHER_SCOPE = {"upload": "bake", "bake": "upload", "publish": "bake"}


# ------------------------------------------------------------------------------------------ keys


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    api = make_api(tmp_path_factory.mktemp("security"))
    publish_vector_bundle(api, public=False)
    return api


def write_operations(api) -> list[tuple[str, str]]:
    document = api.client.get("/openapi.json").json()
    return sorted((method.upper(), path) for path, item in document["paths"].items() for method in item if method not in ("get", "head", "options"))


def concrete(path: str) -> str:
    return path.replace("{bake_id}", "bk_missing").replace("{name}", "vector-good").replace("{version}", "1.0.0")


def request(api, method: str, path: str, headers: dict[str, str]):
    body = {"public": True} if method == "PATCH" else {"name": "x", "version": "1", "character": "a", "cloth": "b", "publish": False}
    if "/assets/" in path:
        return api.client.request(method, concrete(path), files={"file": ("t.png", png_bytes())}, headers=headers)
    return api.client.request(method, concrete(path), json=body, headers=headers)


def test_every_write_operation_is_listed_with_its_scope(api):
    assert set(write_operations(api)) == set(WRITE_SCOPES)


@pytest.mark.parametrize("operation", sorted(WRITE_SCOPES), ids=lambda op: f"{op[0]} {op[1]}")
def test_writes_need_a_key_with_the_right_scope(api, operation):
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.keys import create_api_key, revoke_api_key

    method, path = operation
    scope = WRITE_SCOPES[operation]
    with session_scope(api.sessions) as session:
        revoked, record = create_api_key(session, "upload,bake,publish,read", "revoked")
        revoke_api_key(session, record.id)
        wrong, _ = create_api_key(session, f"{OTHER_SCOPE[scope]},read", "wrong scope")
        right, _ = create_api_key(session, scope, "right scope")
    before = api.snapshot()
    for headers, status, problem in [
        ({}, 401, "unauthorized"),
        ({"Authorization": f"Bearer {revoked}"}, 401, "unauthorized"),
        ({"X-API-Key": revoked}, 401, "unauthorized"),
        ({"Authorization": "Bearer cbk_000000000000_" + "A" * 43}, 401, "unauthorized"),
        ({"Authorization": f"Bearer {right[:-1]}x"}, 401, "unauthorized"),  # right id, wrong secret
        ({"Authorization": "Bearer " + "x" * 5000}, 401, "unauthorized"),
        ({"Authorization": f"Bearer {wrong}"}, 403, "forbidden"),
    ]:
        response = request(api, method, path, headers)
        assert (response.status_code, response.json()["type"]) == (status, f"/problems/{problem}"), (headers, response.text)
        assert response.headers["content-type"] == "application/problem+json"
    assert api.snapshot() == before  # nothing written by a refused key
    allowed = request(api, method, path, {"Authorization": f"Bearer {right}"})
    assert allowed.status_code not in (401, 403), allowed.text


def test_a_bake_key_cannot_publish(api):
    response = api.client.post("/v1/bakes", json={"name": "x", "version": "1", "character": "a", "cloth": "b", "publish": True}, headers=api.auth("bake"))
    assert response.status_code == 403


def test_keys_are_stored_as_sha256_digests_only(tmp_path):
    """`crowdbake keys create` (the real command) prints a key once; the database files (main file,
    WAL and shared memory) hold its sha256 and never the key or its secret part, and the bootstrap
    key of the settings is stored the same way."""
    data = tmp_path / "data"
    env = {key: value for key, value in os.environ.items() if not key.startswith("CROWDBAKE_")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "services"), env.get("PYTHONPATH", "")])
    created = subprocess.run([sys.executable, "-m", "crowdbake", "keys", "create", "--data", str(data), "--scopes", "upload,read", "--label", "ci"],
                             env=env, capture_output=True, text=True, timeout=120)
    assert created.returncode == 0, created.stderr
    raw = created.stdout.strip()
    prefix, key_id, secret = raw.split("_", 2)
    assert prefix == "cbk" and len(secret) >= 43
    bootstrap = "bootstrap-" + hashlib.sha256(SECRET).hexdigest()
    from crowdbake.api.app import build_services
    from crowdbake.settings import Settings

    build_services(Settings(data_dir=data, bootstrap_key=bootstrap))
    listed = subprocess.run([sys.executable, "-m", "crowdbake", "keys", "list", "--data", str(data)], env=env, capture_output=True, text=True, timeout=120)
    assert listed.returncode == 0 and key_id in listed.stdout and secret not in listed.stdout

    stored = b"".join(path.read_bytes() for path in data.glob("crowdbake.sqlite3*"))
    for text in (raw, secret, bootstrap):
        assert text.encode() not in stored
    with sqlite3.connect(data / "crowdbake.sqlite3") as connection:
        hashes = {row[0]: row[1] for row in connection.execute("SELECT id, key_hash FROM api_keys")}
    assert hashes[key_id] == hashlib.sha256(raw.encode()).hexdigest()
    assert hashes["bootstrap"] == hashlib.sha256(bootstrap.encode()).hexdigest()


# --------------------------------------------------------------------------------- names and paths


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """uvicorn on a data folder with the good vector bundle published (private) and secrets planted
    next to it: in the data folder, the bundles folder and inside the bundle folder (not listed)."""
    root = tmp_path_factory.mktemp("paths")
    service = make_service(root / "service", "filesystem://")
    data = service.settings.data_dir
    shutil.copytree(GOOD_BUNDLE, service.settings.bundles_dir / "vector-good" / "1.0.0")
    from crowdbake.storage.bundles import register_bundle
    from crowdbake.storage.db import session_scope

    with session_scope(service.sessions()) as session:
        register_bundle(session, service.settings.bundles_dir, "vector-good", "1.0.0", False, None)
    for folder in (root, data, service.settings.bundles_dir, service.settings.bundles_dir / "vector-good", service.settings.bundles_dir / "vector-good" / "1.0.0"):
        (folder / "secret.txt").write_bytes(SECRET)
    service.start_api()
    yield service
    service.stop()


def raw_get(port: int, target: bytes, key: str) -> tuple[int, bytes]:
    """GET `target` byte for byte (no client-side normalisation of ../ or %2e); (status, whole answer)."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall(b"GET " + target + b" HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\nAuthorization: Bearer " + key.encode() + b"\r\n\r\n")
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    return int(answer.split(b" ", 2)[1]), answer


BASE = b"/v1/bundles/vector-good/1.0.0"
HOSTILE_TARGETS = [
    BASE + b"/files/../../../secret.txt", BASE + b"/files/../secret.txt", BASE + b"/files/secret.txt",
    BASE + b"/files/..%2f..%2fsecret.txt", BASE + b"/files/%2e%2e/%2e%2e/secret.txt", BASE + b"/files/%2e%2e%2f%2e%2e%2fsecret.txt",
    BASE + b"/files/..%5c..%5csecret.txt", BASE + b"/files/%252e%252e%252fsecret.txt", BASE + b"/files//etc/passwd",
    BASE + b"/files/%2fetc%2fpasswd", BASE + b"/files/cycle/cycle.json%00.txt", BASE + b"/files/cycle/cycle.json\x00",
    BASE + b"/files/" + b"a/" * 3000 + b"secret.txt", BASE + b"/files/" + b"x" * 20000,
    b"/v1/bundles/vector-good/../secret.txt", b"/v1/bundles/vector-good/%2e%2e/secret.txt", b"/v1/bundles/..%2fvector-good/1.0.0/manifest.json",
    b"/v1/bundles/%2e%2e/1.0.0/manifest.json", b"/v1/bundles/vector-good/..%2f..%2fsecret.txt/manifest.json",
    b"/v1/bundles/vector-good/%2e%2e/files/secret.txt", b"/v1/bundles/vector-good/1.0.0%00/manifest.json",
    b"/v1/bundles/" + b"n" * 5000 + b"/1.0.0/manifest.json", b"/v1/bundles/vector-good/" + b"9" * 5000 + b"/manifest.json",
    b"/v1/bundles/%2fetc/passwd/manifest.json", b"/v1/bakes/..%2f..%2fsecret.txt", b"/v1/assets/..%2fsecret.txt",
    b"/problems/..%2f..%2fsecret.txt", b"/v1/bundles/vector-good/latest/files/..%2fsecret.txt",
]


@pytest.mark.parametrize("target", HOSTILE_TARGETS, ids=lambda target: target.decode("latin-1")[:70])
def test_hostile_names_never_reach_a_file_outside_the_bundle(server, target):
    status, answer = raw_get(server.port, target, server.keys["all"])
    assert 400 <= status < 500, answer[:300]
    assert SECRET not in answer and b"root:" not in answer
    head = answer.split(b"\r\n\r\n", 1)[0].lower()
    if b"content-type: application/json" in head or b"content-type: application/problem+json" in head:
        assert b"content-type: application/problem+json" in head  # an answer from the app is a problem document


def test_listed_files_are_still_served(server):
    """The same server serves what the manifest lists (so the refusals above are about the names)."""
    status, answer = raw_get(server.port, BASE + b"/files/cycle/cycle.json", server.keys["read"])
    assert status == 200 and answer.endswith((GOOD_BUNDLE / "cycle" / "cycle.json").read_bytes())


def test_an_upload_filename_with_dot_dots_only_labels_the_asset(server, tmp_path):
    import httpx

    top = server.root.parent  # the test's folder: the secrets' and the service's
    outside_before = files_under(top)
    with httpx.Client(base_url=server.url, headers=server.auth("upload")) as client:
        for name in ("../../../../secret-upload.png", "/etc/secret-upload.png", "..\\..\\secret-upload.png", "../" * 60 + "secret-upload.png"):
            response = client.post("/v1/assets/textures", files={"file": (name, png_bytes(4, 4))})
            assert response.status_code in (200, 201), response.text
            assert "/" not in response.json()["filename"] and ".." not in response.json()["filename"].replace("..png", "")
    new = sorted(set(files_under(top)) - set(outside_before))
    digest = hashlib.sha256(png_bytes(4, 4)).hexdigest()
    # The only new files: the one blob (deduplicated), the database's own and the logs.
    assert [path for path in new if "secret-upload" in path] == []
    assert [path for path in new if "/blobs/" in path] == [f"service/data/blobs/sha256/{digest[:2]}/{digest[2:4]}/{digest}"]


def test_a_glb_naming_a_server_file_is_refused(server):
    """Regression: a .glb's JSON chunk may give a buffer a uri; the reader resolved it next to the
    staging file, so "../../secret.txt" made the server read one of its own files into the upload.
    The upload check refused external URIs only in .gltf files; it now does for .glb files too."""
    import httpx

    from corpus import make_glb, split_glb

    document, binary = split_glb(tiny_character_glb())
    staging = server.settings.blob_dir / ".incoming"
    relative = os.path.relpath(server.root / "secret.txt", staging)
    document["buffers"].append({"uri": relative, "byteLength": len(SECRET)})
    with httpx.Client(base_url=server.url, headers=server.auth("upload")) as client:
        response = client.post("/v1/assets/characters", files={"file": ("character.glb", make_glb(document, binary))})
    assert response.status_code == 422 and "external file" in response.text
    assert str(server.root) not in response.text and SECRET.decode() not in response.text


# -------------------------------------------------------------------------------------- runtime


def crowdview(*args: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    if not CROWDVIEW.is_file():
        pytest.skip(f"{CROWDVIEW} is not built (scripts/setup.sh builds it: cmake -S runtime -B build/runtime -G Ninja && cmake --build build/runtime)")
    env = {"PATH": os.environ.get("PATH", ""), "HOME": str(cwd / "home")}
    return subprocess.run([str(CROWDVIEW), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def test_crowdview_refuses_a_bundle_whose_bytes_do_not_match_its_hashes(tmp_path):
    bundle = tmp_path / "bundle"
    shutil.copytree(GOOD_BUNDLE, bundle)
    assert crowdview("--verify", str(bundle), cwd=tmp_path).returncode == 0
    manifest = json.loads((bundle / "manifest.json").read_text())
    entry = max(manifest["files"], key=lambda item: item["size"])
    data = bytearray((bundle / entry["path"]).read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit, same size: only the sha256 can tell
    (bundle / entry["path"]).write_bytes(bytes(data))
    result = crowdview("--verify", str(bundle), cwd=tmp_path)
    assert result.returncode != 0 and "sha256_mismatch" in result.stdout + result.stderr, result


class HostileServer:
    """A tiny http.server on loopback: `routes` maps a URL path to bytes, or to ("redirect", URL)."""

    def __init__(self, routes: dict[str, object]):
        routes_ = routes

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                body = routes_.get(self.path.split("?", 1)[0])
                if isinstance(body, tuple):
                    self.send_response(302)
                    self.send_header("Location", body[1])
                    self.end_headers()
                    return
                if body is None:
                    self.send_response(404)
                    self.end_headers()
                    return
                self.send_response(200)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *_):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def bundle_routes(prefix: str, manifest: dict, files: dict[str, bytes]) -> dict[str, object]:
    routes: dict[str, object] = {f"{prefix}/manifest.json": json.dumps(manifest).encode()}
    routes.update({f"{prefix}/files/{path}": data for path, data in files.items()})
    return routes


def hostile_bundles() -> dict[str, tuple[dict, dict[str, object]]]:
    """name -> (manifest, extra routes): the good vector with one entry made hostile."""
    manifest = json.loads((GOOD_BUNDLE / "manifest.json").read_text())
    files = {entry["path"]: (GOOD_BUNDLE / entry["path"]).read_bytes() for entry in manifest["files"]}
    escape = b"written outside the cache"
    escape_entry = {"path": "../../../../escape.bin", "size": len(escape), "sha256": hashlib.sha256(escape).hexdigest(),
                    "media_type": "application/json", "role": "cycle"}

    def variant(edit) -> dict:
        copy = json.loads(json.dumps(manifest))
        edit(copy)
        return copy

    cases: dict[str, tuple[dict, dict[str, object]]] = {"good": (manifest, dict(files))}
    cases["dot-dot-path"] = (variant(lambda m: m["files"].__setitem__(0, dict(m["files"][0], path=escape_entry["path"], sha256=escape_entry["sha256"], size=len(escape)))),
                             {**files, "../../../../escape.bin": escape})
    cases["absolute-path"] = (variant(lambda m: m["files"].__setitem__(0, dict(m["files"][0], path="/tmp/escape.bin", sha256=escape_entry["sha256"], size=len(escape)))),
                              {**files, "/tmp/escape.bin": escape})
    cases["sha256-is-a-path"] = (variant(lambda m: m["files"].__setitem__(0, dict(m["files"][0], sha256="../../../../../../tmp/escape-" + "0" * 40))), dict(files))
    first = manifest["files"][0]["path"]
    cases["wrong-bytes"] = (manifest, {**files, first: b"x" * len(files[first])})
    cases["too-many-bytes"] = (manifest, {**files, first: files[first] + b"\0" * (8 << 20)})
    cases["redirect-to-file"] = (manifest, {**files, first: ("redirect", "file:///etc/passwd")})
    return cases


def test_crowdview_fetch_from_a_hostile_server_writes_only_into_its_cache(tmp_path):
    bundles = hostile_bundles()
    routes: dict[str, object] = {}
    for name, (manifest, files) in bundles.items():
        routes.update(bundle_routes(f"/{name}", manifest, files))
    server = HostileServer(routes)
    work = tmp_path / "work"
    (work / "home").mkdir(parents=True)
    outcomes = {}
    try:
        for name in bundles:
            cache = tmp_path / f"cache-{name}"
            before = files_under(tmp_path)
            result = crowdview("--verify", f"{server.url}/{name}", "--cache", str(cache), cwd=work)
            outcomes[name] = (result.returncode, (result.stdout + result.stderr)[-400:])
            new = sorted(set(files_under(tmp_path)) - set(before))
            outside = [path for path in new if not path.startswith(f"cache-{name}/")]
            assert outside == [], (name, outside)
            # In the cache: only blobs named by their verified sha256 (and partial downloads).
            for path in new:
                parts = Path(path).parts
                assert parts[1] in ("blobs", "partial"), (name, path)
                if parts[1] == "blobs":
                    assert hashlib.sha256((tmp_path / path).read_bytes()).hexdigest() == parts[-1], (name, path)
                else:
                    assert (tmp_path / path).stat().st_size <= 1 << 20, (name, path)  # never the 8 MiB a server pushed
    finally:
        server.close()
    print("\n" + "\n".join(f"{name}: exit {code}: {output.strip().splitlines()[-1] if output.strip() else ''}" for name, (code, output) in outcomes.items()))
    assert outcomes["good"][0] == 0, outcomes["good"]
    for name, (code, output) in outcomes.items():
        if name != "good":
            assert code != 0, (name, output)
    assert "unsafe_path" in outcomes["dot-dot-path"][1] and "unsafe_path" in outcomes["absolute-path"][1]
    assert "sha256_mismatch" in outcomes["wrong-bytes"][1] and "size_mismatch" in outcomes["too-many-bytes"][1]
    assert "manifest_invalid" in outcomes["sha256-is-a-path"][1] and "fetch_failed" in outcomes["redirect-to-file"][1]
    assert not Path("/tmp/escape.bin").exists() and not (tmp_path.parent / "escape.bin").exists()
