"""What a new user of `crowdbake submit` tripped on, each against the real thing:

- a version already published from other inputs was refused (409) only after every upload: now the
  client finds it before uploading (the bundle, the bake that published it, its assets' sha256);
- a wrong --server URL waited out --retry-for (120 s) before saying anything: a refused first contact is
  now one line after a couple of tries, while a busy server (503, 429) is still retried;
- a .glb that is not a glTF binary got a JSON parse error from the server: now the magic is checked;
- the engine export had to be fetched by hand: --export-out DIR fetches it after the bake."""
from __future__ import annotations

import http.server
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from crowdbake.client.download import download_export
from crowdbake.client.http import FIRST_CONTACT_TRIES, ClientError, Exit, Server
from crowdbake.client.preflight import check_not_published_otherwise, published_difference
from service_fixtures import GOOD_BUNDLE, free_port, make_api, obj_bytes, pc2_bytes, publish_vector_bundle, service_env, start_api, tiny_character_glb, tiny_cloth

CLIENT_ONLY = Path(__file__).resolve().parent / "client_only.py"


@pytest.fixture
def files(tmp_path) -> dict[str, Path]:
    points, faces = tiny_cloth()
    paths = {"character": tmp_path / "walker.glb", "cloth": tmp_path / "cloth.pc2", "mesh": tmp_path / "cloth.obj"}
    paths["character"].write_bytes(tiny_character_glb())
    paths["cloth"].write_bytes(pc2_bytes(points))
    paths["mesh"].write_bytes(obj_bytes(points[0], faces, tmp_path))
    return paths


def submit(server: str, files: dict[str, Path], *extra: str, key: str = "cbk_unused", timeout: float = 60) -> tuple[int, str, float]:
    """Run crowdbake-submit as the client distribution would; (exit code, stderr, seconds)."""
    command = [sys.executable, str(CLIENT_ONLY), "--server", server, str(files["character"]), "--cloth", str(files["cloth"]),
               "--cloth-mesh", str(files["mesh"]), "--name", "walker", "--version", "1.0.0", *extra]
    started = time.monotonic()
    result = subprocess.run(command, env={**service_env(Path("/nonexistent"), "filesystem://"), "CROWDBAKE_API_KEY": key},
                            capture_output=True, text=True, timeout=timeout)
    return result.returncode, result.stderr, time.monotonic() - started


def test_a_refused_connection_is_one_line_after_a_couple_of_tries(files):
    url = f"http://127.0.0.1:{free_port()}"  # nobody listens there
    code, stderr, seconds = submit(url, files)  # --retry-for keeps its default, 120 s
    assert code == Exit.UNREACHABLE, stderr
    assert stderr.strip().splitlines()[-1] == f"crowdbake submit: error: cannot connect to {url}: connection refused"
    assert stderr.count("retrying in") == FIRST_CONTACT_TRIES - 1
    assert seconds < 15, f"{seconds:.1f} s: a wrong URL must not wait out --retry-for"


class Busy(http.server.BaseHTTPRequestHandler):
    """Answers `busy` requests with 503 (or 429), then 200 with an empty JSON object."""

    busy, status, seen = 0, 503, 0

    def do_GET(self):  # noqa: N802 (http.server's name)
        type(self).seen += 1
        code = self.status if type(self).seen <= self.busy else 200
        body = json.dumps({"status": code, "title": "busy", "detail": "try later"} if code != 200 else {}).encode()
        self.send_response(code)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.mark.parametrize("status", [503, 429])
def test_a_busy_server_is_retried_beyond_the_first_contact_tries(status):
    handler = type("Handler", (Busy,), {"busy": FIRST_CONTACT_TRIES + 2, "status": status, "seen": 0})
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{httpd.server_address[1]}") as client:
            server = Server(client, retry_for=60, say=lambda line: None, sleep=lambda s: None)
            assert server.request("GET", "/v1/bakes", "listing").status_code == 200
            assert server.retries == FIRST_CONTACT_TRIES + 2
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_a_glb_that_is_not_a_gltf_binary_is_named_so_before_any_request(files):
    files["character"].write_text('{"asset": {"version": "2.0"}}')  # a .gltf's JSON, named .glb
    code, stderr, _ = submit(f"http://127.0.0.1:{free_port()}", files)
    assert code == Exit.REJECTED, stderr  # a rejected input, as the server would have said, not a usage error
    last = stderr.strip().splitlines()[-1]
    assert "not a glTF binary" in last and "walker.glb" in last and "JSON" not in last, last


@pytest.fixture
def published(tmp_path):
    """A real server (uvicorn, no worker) with the good vector bundle published by no bake, and a key."""
    api = make_api(tmp_path)
    name, version = publish_vector_bundle(api, "walker", "1.0.0")
    port = free_port()
    # The same workspace as make_api's app (shared: one team's keys see each other's bundles and bakes).
    # Its database too: make_api's is PostgreSQL where CROWDBAKE_TEST_DATABASE_URL is set.
    env = service_env(Path(api.settings.data_dir), "filesystem://", CROWDBAKE_SHARED_WORKSPACE="true",
                      CROWDBAKE_DATABASE_URL=api.settings.database_url)
    process = start_api(env, port, tmp_path / "api.log")
    try:
        yield api, f"http://127.0.0.1:{port}", name, version
    finally:
        process.stop()


def test_a_version_published_from_other_inputs_is_refused_before_any_upload(published, files):
    api, url, name, version = published
    before = api.client.get("/v1/assets", headers=api.auth()).json()["count"]
    code, stderr, _ = submit(url, files, key=api.keys["all"])
    assert code == Exit.REJECTED, stderr
    last = stderr.strip().splitlines()[-1]
    assert f"{name}/{version} is already published from other inputs" in last and "choose a new version" in last, last
    assert "uploading" not in stderr and "stored" not in stderr, stderr
    assert api.client.get("/v1/assets", headers=api.auth()).json()["count"] == before == 0


def test_a_server_url_with_a_path_the_service_lacks_is_a_url_problem(published, files):
    """`--server http://host:port/v1` answered 404 to every request, and submit exited 3 "Not found" as if
    the input were rejected. The URL is checked first: exit 2, one line naming the URL and the fix."""
    api, url, _, _ = published
    code, stderr, _ = submit(f"{url}/v1", files, key=api.keys["all"])
    assert code == Exit.USAGE, stderr
    last = stderr.strip().splitlines()[-1]
    assert f"{url}/v1" in last and "no crowdbake service answers there" in last and "without /v1" in last, last
    assert "uploading" not in stderr, stderr


def test_an_unpublished_version_passes_the_check(published, files):
    api, _, _, _ = published
    server = Server(api.client, retry_for=1)
    api.client.headers["Authorization"] = f"Bearer {api.keys['all']}"
    assert published_difference(server, "walker", "2.0.0", {"character": [files["character"]]}, {}, None) is None
    with pytest.raises(ClientError) as refused:
        check_not_published_otherwise(server, "walker", "1.0.0", {"character": [files["character"]]}, {}, None)
    assert refused.value.exit_code == Exit.REJECTED and "published without a bake" in str(refused.value)


def test_export_out_fetches_and_unpacks_the_engine_export(tmp_path):
    api = make_api(tmp_path)
    name, version = publish_vector_bundle(api)
    api.client.app.state.services.exports.publish(GOOD_BUNDLE)
    api.client.headers["Authorization"] = f"Bearer {api.keys['all']}"
    server = Server(api.client, retry_for=1)
    folder = download_export(server, name, version, tmp_path / "exports")
    assert folder == tmp_path / "exports" / name / version
    index = json.loads((folder / "export.json").read_text())
    assert index["format"] == "crowdbake-export"
    served = api.client.get(f"/v1/bundles/{name}/{version}/export/export.json")
    assert served.status_code == 200 and served.content == (folder / "export.json").read_bytes()
    # Again into the same folder: the same export is kept; a bundle without an export is said to lack one.
    assert download_export(server, name, version, tmp_path / "exports") == folder
    other, other_version = publish_vector_bundle(api, "no-export", "1.0.0")
    with pytest.raises(ClientError, match="without an engine export"):
        download_export(server, other, other_version, tmp_path / "exports")
