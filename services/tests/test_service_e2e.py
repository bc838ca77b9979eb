"""The whole service, for real: uvicorn (subprocess), Redis (CROWDBAKE_TEST_REDIS_URL, started by
scripts/test.sh), a Celery worker (subprocess, prefork) and the `crowdbake submit` CLI, on the
procedural sample character with small bake parameters.

Upload -> bake -> publish -> download, then every file's sha256 and the bundle's schema are checked
(verify_bundle), the same bytes are served with Range requests, a resubmission is idempotent, a bad
upload through the real server stores nothing, and a bake that fails in a worker makes the CLI exit
non-zero with one line. Every test runs on local folders and, when the tests have an S3 server, again
on the object store (uploads, stage outputs and bundles in the bucket, private work folders).
"""
from __future__ import annotations

import hashlib
import io
import subprocess
import sys
import time
import uuid
import zipfile
from pathlib import Path

import httpx
import pytest

from crowdbake.formats.bundle import verify_bundle
from service_fixtures import (
    STORES, database_env, free_port, published_files, raw_http, redis_url_or_skip, service_env, settings_overrides, start_api, start_process,
    start_worker,
    store_env, stored_blobs,
)

# slow: a real server and worker (or browser) for tens of seconds; scripts/test.sh runs it with CROWDBAKE_SLOW_TESTS=1, as CI does
pytestmark = [pytest.mark.integration, pytest.mark.slow]

# Small enough for a 2-core CI machine: the sample's 3 walk cycles, 2 impostor frames x 4 azimuths x
# 2 elevations of 32-texel tiles, 2 cycle candidates compared from 2 views.
SAMPLE_CYCLES = 3
SAMPLE_TEXTURE_SIZE = 64
BAKE_FLAGS = ["--impostor-frames", "2", "--azimuths", "4", "--elevations", "0,30", "--tile-size", "32",
              "--candidates", "2", "--cycle-views", "2"]
BAKE_TIMEOUT_S = 240


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    """The procedural sample character, generated with `crowdbake sample`."""
    out = tmp_path_factory.mktemp("sample")
    command = [sys.executable, "-m", "crowdbake", "sample", str(out), "--cycles", str(SAMPLE_CYCLES), "--texture-size", str(SAMPLE_TEXTURE_SIZE)]
    result = subprocess.run(command, env=service_env(out / "unused", "unused"), capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope="module", params=STORES)
def service(tmp_path_factory, request):
    """API + worker on a private data folder and a private queue of the test Redis, on each store."""
    redis_url = redis_url_or_skip()
    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
    from crowdbake.storage.keys import create_api_key

    root = tmp_path_factory.mktemp("service")
    data = root / "data"
    queue = f"crowdbake-e2e-{uuid.uuid4().hex[:8]}"
    backends = {**database_env(), **store_env(request.param)}  # PostgreSQL and S3 when the tests have them
    env = service_env(data, redis_url, CROWDBAKE_QUEUE=queue, CROWDBAKE_MAX_UPLOAD_BYTES=str(16 << 20), **backends)
    settings = Settings(data_dir=data, **settings_overrides(backends))
    engine = make_engine(settings.database_url)
    migrate(engine)
    with session_scope(make_sessionmaker(engine)) as session:
        key, _ = create_api_key(session, "upload,bake,publish,read", "e2e")
    port = free_port()
    api = start_api(env, port, root / "api.log")
    worker = start_worker(env, root / "worker.log", concurrency=2, queue=queue)
    try:
        yield {"url": f"http://127.0.0.1:{port}", "key": key, "env": env, "settings": settings, "root": root, "worker": worker, "api": api}
    finally:
        worker.stop()
        api.stop()


def submit(service, sample: Path, version: str, *extra: str, download: Path | None = None) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "crowdbake", "submit", "--server", service["url"], str(sample / "character.glb"),
               "--cloth", str(sample / "cloth.pc2"), "--cloth-mesh", str(sample / "cloth.obj"), "--textures", str(sample / "textures"),
               "--name", "sample-walker", "--version", version, "--wait", "--poll", "0.5", "--timeout", str(BAKE_TIMEOUT_S), *BAKE_FLAGS, *extra]
    if download is not None:
        command += ["--download", str(download)]
    env = dict(service["env"], CROWDBAKE_API_KEY=service["key"])
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=BAKE_TIMEOUT_S + 60)


def explain(result: subprocess.CompletedProcess, service) -> str:
    return (f"exit {result.returncode}\nstdout:\n{result.stdout}\nstderr:\n{result.stderr}\n"
            f"worker log:\n{service['worker'].tail(60)}\napi log:\n{service['api'].tail(20)}")


def test_upload_bake_publish_download_verify(service, sample, tmp_path):
    started = time.monotonic()
    downloads = tmp_path / "downloads"
    result = submit(service, sample, "1.0.0", download=downloads)
    elapsed = time.monotonic() - started
    assert result.returncode == 0, explain(result, service)
    bake_id, folder = result.stdout.split()
    assert Path(folder) == downloads / "sample-walker" / "1.0.0"
    assert "succeeded" in result.stderr and "bundle verified" in result.stderr
    # Not a terminal: plain progress lines, one per change, naming the bake
    assert any(line.startswith(f"bake {bake_id}: running") for line in result.stderr.splitlines())
    print(f"\ne2e: upload + bake + publish + download + verify in {elapsed:.1f} s")

    bundle = verify_bundle(Path(folder))  # schema, every size and sha256, binary headers, cross-checks
    manifest_bytes = (Path(folder) / "manifest.json").read_bytes()
    manifest = bundle.manifest
    assert manifest["name"] == "sample-walker" and manifest["version"] == "1.0.0"
    assert len(manifest["impostor"]["frame_indices"]) == 2 and manifest["impostor"]["tile_size"] == 32
    for entry in manifest["files"]:
        assert hashlib.sha256((Path(folder) / entry["path"]).read_bytes()).hexdigest() == entry["sha256"]
    # What was published on the server is byte for byte what was downloaded.
    published = published_files(service["settings"], "sample-walker", "1.0.0")
    assert published["manifest.json"] == manifest_bytes
    assert published == {path: (Path(folder) / path).read_bytes() for path in published}

    headers = {"Authorization": f"Bearer {service['key']}"}
    with httpx.Client(base_url=service["url"], headers=headers, timeout=30) as client:
        bake = client.get(f"/v1/bakes/{bake_id}").json()
        assert bake["state"] == "succeeded" and bake["progress"] == 1.0
        # One clip: the per-clip loops stage has nothing to do (the cycle stage searches the one loop).
        assert [(stage["stage"], stage["state"]) for stage in bake["stages"]] == [
            ("validate", "succeeded"), ("loops", "skipped"), *((name, "succeeded") for name in ("cycle", "probes", "poses", "impostors", "pack", "publish"))]
        probes = next(stage for stage in bake["stages"] if stage["stage"] == "probes")
        assert probes["done"] == probes["total"] == 2  # the layout's probe and the clip's, fanned out
        impostors = next(stage for stage in bake["stages"] if stage["stage"] == "impostors")
        assert impostors["done"] == impostors["total"] == 2 * 2  # frames x elevation rings, fanned out
        assert bake["bundle_url"] == "/v1/bundles/sample-walker/1.0.0/manifest.json"
        entry = max(manifest["files"], key=lambda item: item["size"])
        data = (Path(folder) / entry["path"]).read_bytes()
        piece = client.get(f"/v1/bundles/sample-walker/1.0.0/files/{entry['path']}", headers={"Range": "bytes=100-199"})
        assert piece.status_code == 206 and piece.content == data[100:200]
        assert piece.headers["etag"] == f'"{entry["sha256"]}"' and "immutable" in piece.headers["cache-control"]
        # `latest` is resolved once: a redirect to the concrete version, whose bytes are the manifest.
        latest = client.get("/v1/bundles/sample-walker/latest/manifest.json")
        assert latest.status_code == 307 and latest.headers["location"] == "/v1/bundles/sample-walker/1.0.0/manifest.json"
        assert client.get(latest.headers["location"]).content == manifest_bytes
        # What the page shows comes from the store too: the cycle report the cycle stage wrote (as blobs
        # when work folders are private), an atlas preview and the whole bundle as one zip.
        report = client.get(f"/v1/bakes/{bake_id}/cycle/report.html")
        assert report.status_code == 200 and "<html" in report.text.lower(), report.text[:300]
        cycle_json = client.get(f"/v1/bakes/{bake_id}/cycle/cycle.json")
        assert cycle_json.status_code == 200 and isinstance(cycle_json.json(), dict)
        preview = client.get("/v1/bundles/sample-walker/1.0.0/preview/uv")
        assert preview.status_code == 200 and preview.content.startswith(b"\x89PNG")
        archive = client.get("/v1/bundles/sample-walker/1.0.0/archive.zip")
        with zipfile.ZipFile(io.BytesIO(archive.content)) as bundle_zip:
            assert bundle_zip.read("sample-walker/1.0.0/manifest.json") == manifest_bytes
            assert len(bundle_zip.namelist()) == len(manifest["files"]) + 1
        # The engine export was published beside the bundle, in the same store (folders or bucket).
        listed = client.get("/v1/bundles/sample-walker/1.0.0").json()
        assert listed["export_url"] == "/v1/bundles/sample-walker/1.0.0/export/"
        sidecar = client.get(f"{listed['export_url']}export.json")
        assert sidecar.status_code == 200 and sidecar.json()["bundle"] == {"name": "sample-walker", "version": "1.0.0"}
        export_zip = client.get("/v1/bundles/sample-walker/1.0.0/export.zip")
        with zipfile.ZipFile(io.BytesIO(export_zip.content)) as exported:
            assert "sample-walker-1.0.0/export.json" in exported.namelist()

    # Idempotent resubmission: the same inputs and parameters give back the same bake, already done.
    again = submit(service, sample, "1.0.0", download=tmp_path / "again")
    assert again.returncode == 0, explain(again, service)
    assert again.stdout.split()[0] == bake_id and "reusing it" in again.stderr
    assert (tmp_path / "again" / "sample-walker" / "1.0.0" / "manifest.json").read_bytes() == manifest_bytes


@pytest.mark.slow
def test_cancel_then_retry_on_real_workers(service, sample):
    """A cancelled bake's queued tasks are dropped by the workers; a retry is a new attempt that finishes."""
    headers = {"Authorization": f"Bearer {service['key']}"}
    with httpx.Client(base_url=service["url"], headers=headers, timeout=30) as client:
        character = client.post("/v1/assets/characters", files={"file": ("character.glb", (sample / "character.glb").read_bytes())}).json()
        cloth = client.post("/v1/assets/cloth", files={"cache": ("cloth.pc2", (sample / "cloth.pc2").read_bytes()),
                                                        "mesh": ("cloth.obj", (sample / "cloth.obj").read_bytes())}).json()
        params = {"impostor_frames": 2, "azimuths": 4, "elevations_deg": [0, 30], "tile_size": 32, "candidates": 2, "cycle_views": 2}
        created = client.post("/v1/bakes", json={"name": "sample-walker", "version": "2.0.0", "character": character["id"], "cloth": cloth["id"], "params": params})
        assert created.status_code == 202, created.text
        location = created.headers["location"]
        assert client.post(f"{location}/cancel").json()["state"] == "cancelled"
        time.sleep(2)  # time for a worker to receive (and drop) the validate task
        bake = client.get(location).json()
        assert bake["state"] == "cancelled" and not any(stage["state"] == "succeeded" for stage in bake["stages"])
        retried = client.post(f"{location}/retry")
        assert retried.status_code == 202 and retried.json()["attempt"] == 1
        deadline = time.monotonic() + BAKE_TIMEOUT_S
        while (bake := client.get(location).json())["state"] not in ("succeeded", "failed", "cancelled"):
            assert time.monotonic() < deadline, service["worker"].tail()
            time.sleep(0.5)
        assert bake["state"] == "succeeded", bake["error"]
        manifest = client.get("/v1/bundles/sample-walker/2.0.0/manifest.json").json()
        assert manifest["version"] == "2.0.0" and len(manifest["impostor"]["frame_indices"]) == 2
        assert client.get("/v1/bundles/sample-walker/latest").json()["version"] == "2.0.0"


def test_bad_upload_through_the_real_server_stores_nothing(service, sample, tmp_path):
    before = stored_blobs(service["settings"])
    cache = (sample / "cloth.pc2").read_bytes()
    headers = {"Authorization": f"Bearer {service['key']}"}
    with httpx.Client(base_url=service["url"], headers=headers, timeout=30) as client:
        response = client.post("/v1/assets/cloth", files={"cache": ("cloth.pc2", cache[:-12]), "mesh": ("cloth.obj", (sample / "cloth.obj").read_bytes())})
        assert response.status_code == 422 and response.headers["content-type"] == "application/problem+json"
        problem = response.json()
        assert problem["errors"][0]["field"] == "cache" and problem["errors"][0]["where"] == f"byte {len(cache) - 12}"
    # A client announcing more than CROWDBAKE_MAX_UPLOAD_BYTES is answered 413 before its body is read.
    port = int(service["url"].rsplit(":", 1)[1])
    answer = raw_http(port, (f"POST /v1/assets/characters HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {service['key']}\r\n"
                             f"Content-Type: multipart/form-data; boundary=x\r\nContent-Length: {17 << 20}\r\n\r\n--x\r\n").encode())
    assert answer.startswith(b"HTTP/1.1 413") and b"application/problem+json" in answer
    assert stored_blobs(service["settings"]) == before


def test_a_bake_failing_in_a_worker_is_one_line_and_a_non_zero_exit(service, sample):
    result = submit(service, sample, "9.9.9", "--lod-triangles", "100000000")
    assert result.returncode == 1, explain(result, service)
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("crowdbake submit: error: bake ") and "failed in validate" in last and "lod_triangles" in last


def _processes_with(marker: str) -> list[int]:
    """Pids of live processes whose command line contains `marker`."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if marker in (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                    pids.append(int(entry.name))
            except OSError:
                pass
    return pids


@pytest.mark.slow
def test_serve_bakes_with_the_filesystem_broker_and_stops_its_workers(sample, tmp_path):
    """`crowdbake serve` alone (no Redis): the filesystem broker and prefork workers bake the sample,
    and stopping serve (SIGTERM) stops its workers, without a traceback."""
    data = tmp_path / "data"
    env = {key: value for key, value in service_env(data, "unused").items() if key != "CROWDBAKE_BROKER_URL"}
    minted = subprocess.run([sys.executable, "-m", "crowdbake", "keys", "create", "--data", str(data), "--scopes", "upload,bake,publish,read"],
                            env=env, capture_output=True, text=True, timeout=60)
    assert minted.returncode == 0, minted.stderr
    port = free_port()
    serve = start_process([sys.executable, "-m", "crowdbake", "serve", "--data", str(data), "--port", str(port), "--workers", "2"], env, tmp_path / "serve.log")
    marker = f"crowdbake-{serve.popen.pid}@"
    try:
        deadline = time.monotonic() + 60
        while True:
            assert serve.popen.poll() is None, serve.tail()
            try:
                if httpx.get(f"http://127.0.0.1:{port}/ready", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, serve.tail()
            time.sleep(0.3)
        service = {"url": f"http://127.0.0.1:{port}", "key": minted.stdout.strip(), "env": env, "worker": serve, "api": serve}
        result = submit(service, sample, "1.0.0", download=tmp_path / "downloads")
        assert result.returncode == 0, explain(result, service)
        verify_bundle(tmp_path / "downloads" / "sample-walker" / "1.0.0")
        assert (data / "broker" / "queue").is_dir() and _processes_with(marker)
    finally:
        serve.stop(timeout=40)
    assert serve.popen.returncode is not None
    assert "Traceback" not in serve.log.read_text(errors="replace"), serve.tail()
    deadline = time.monotonic() + 10
    while _processes_with(marker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _processes_with(marker) == [], "serve left its workers running"
