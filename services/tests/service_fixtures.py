"""Shared helpers of the service tests: an app on a temporary data folder with keys of every scope,
tiny valid inputs made with the project's own writers, snapshots of what is stored, and the real
processes (uvicorn, Celery worker) of the end-to-end test."""
from __future__ import annotations

import io
import os
import socket
import subprocess
import sys
import tempfile
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select

REPO_ROOT = Path(__file__).resolve().parents[2]
SERVICES_DIR = REPO_ROOT / "services"
GOOD_BUNDLE = REPO_ROOT / "shared_formats" / "vectors" / "v1" / "good" / "bundle"


# ------------------------------------------------------------------------------------ tiny inputs


def tiny_character(animated: bool = True):
    """A skinned tetrahedron on one joint that bobs up and down in a quarter second (a valid character;
    6 frames per cycle at crowdbake.params.BASE_FPS (24 fps), so a 12-frame cloth cache holds two cycles)."""
    from crowdbake.geometry import vertex_normals
    from crowdbake.formats.gltf import AnimationChannel, Character

    positions = np.array([[0, 0, 0], [0.5, 0, 0], [0, 1.7, 0], [0, 0, 0.5]], np.float32)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.uint32)
    channels = []
    if animated:
        times = np.array([0.0, 0.125, 0.25], np.float32)
        values = np.array([[0, 0, 0], [0, 0.05, 0], [0, 0, 0]], np.float32)
        channels = [AnimationChannel(joint=0, path="translation", times=times, values=values)]
    return Character(
        positions=positions, normals=vertex_normals(positions, faces).astype(np.float32),
        uvs=np.array([[0, 0], [1, 0], [0.5, 1], [0, 1]], np.float32), faces=faces,
        joints=np.zeros((4, 4), np.uint16), weights=np.tile(np.array([1, 0, 0, 0], np.float32), (4, 1)),
        joint_names=["root"], joint_parents=np.array([-1]), joint_parent_transforms=np.eye(4)[None],
        inverse_bind_matrices=np.eye(4, dtype=np.float32)[None], rest_translations=np.zeros((1, 3)),
        rest_rotations=np.array([[0, 0, 0, 1.0]]), rest_scales=np.ones((1, 3)),
        channels=channels, animation_duration=0.25 if animated else 0.0,
    )


def tiny_character_glb(animated: bool = True) -> bytes:
    from crowdbake.formats.gltf import encode_character

    return encode_character(tiny_character(animated))


def tiny_cloth(frames: int = 12, grid: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A grid x grid sheet waving over `frames` frames: points (frames, grid*grid, 3), faces (T, 3)."""
    xs, ys = np.meshgrid(np.linspace(0, 1, grid), np.linspace(0, 1, grid))
    rest = np.stack([xs.ravel(), ys.ravel(), np.zeros(grid * grid)], axis=1)
    phase = np.linspace(0, 2 * np.pi, frames, endpoint=False)[:, None]
    points = np.repeat(rest[None], frames, axis=0)
    points[:, :, 2] = 0.1 * np.sin(phase + rest[None, :, 0] * 3 + seed)
    faces = []
    for row in range(grid - 1):
        for column in range(grid - 1):
            a = row * grid + column
            faces += [[a, a + 1, a + grid + 1], [a, a + grid + 1, a + grid]]
    return points.astype(np.float32), np.asarray(faces)


def pc2_bytes(points: np.ndarray, sample_rate: float = 1.0) -> bytes:
    from crowdbake.formats.pc2 import encode_pc2

    return encode_pc2(points, sample_rate=sample_rate)


def obj_bytes(positions: np.ndarray, faces: np.ndarray, tmp: Path) -> bytes:
    from crowdbake.formats.obj import write_obj

    handle = tempfile.NamedTemporaryFile(dir=tmp, suffix=".obj", delete=False)
    handle.close()
    write_obj(handle.name, positions, faces)
    data = Path(handle.name).read_bytes()
    os.unlink(handle.name)
    return data


def obj_sequence_zip(points: np.ndarray, faces: np.ndarray, tmp: Path, folder: str = "frames") -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for index, frame in enumerate(points):
            archive.writestr(f"{folder}/frame{index}.obj", obj_bytes(frame, faces, tmp))
    return buffer.getvalue()


def png_bytes(width: int = 8, height: int = 8, mode: str = "RGBA") -> bytes:
    from PIL import Image

    image = Image.new(mode, (width, height), (200, 100, 50, 255) if mode == "RGBA" else (200, 100, 50))
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


# ------------------------------------------------------------------------------------ app fixture


@dataclass
class Api:
    """A real app on a temporary data folder: TestClient, settings, and one key per scope set."""

    client: object
    settings: object
    keys: dict[str, str]

    def auth(self, which: str = "all") -> dict[str, str]:
        return {"Authorization": f"Bearer {self.keys[which]}"}

    @property
    def sessions(self):
        return self.client.app.state.services.sessions

    def snapshot(self) -> tuple[list[str], dict[str, int]]:
        """Every blob and staging file of the store and the row count of every table except api_keys."""
        from crowdbake.storage.models import Base

        files = stored_blobs(self.settings)
        with self.sessions() as session:
            counts = {table.name: session.scalar(select(func.count()).select_from(table)) for table in Base.metadata.sorted_tables}
        return files, counts


KEY_SCOPES = {
    "all": "upload,bake,publish,read",
    "upload": "upload",
    "bake": "bake",
    "ci": "upload,bake,publish",
    "read": "read",
    "publish": "publish",
}


def fresh_test_database(server_url: str) -> str:
    """A new, empty database on the PostgreSQL server of `server_url` (CROWDBAKE_TEST_DATABASE_URL,
    optional: the API tests then run on PostgreSQL instead of SQLite files)."""
    import uuid

    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    name = f"crowdbake_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    admin.dispose()
    return make_url(server_url).set(database=name).render_as_string(hide_password=False)


# The stores the service tests run on: local folders always, an S3 server when scripts/test.sh started
# one (CROWDBAKE_TEST_S3_URL); `pytest.mark.parametrize("store", STORES)` or a fixture's params.
STORES = ("local", pytest.param("s3", marks=pytest.mark.skipif(not os.environ.get("CROWDBAKE_TEST_S3_URL"),
                                                               reason="CROWDBAKE_TEST_S3_URL is not set (scripts/test.sh starts an S3 server)")))


def store_env(store: str) -> dict[str, str]:
    """CROWDBAKE_* variables of `store` for a test: none for local folders; for "s3" the test server's
    bucket (created if missing) under a fresh key prefix, so tests never see each other's objects."""
    if store == "local":
        return {}
    import uuid

    from crowdbake.storage.s3 import ensure_bucket, make_client

    url = os.environ.get("CROWDBAKE_TEST_S3_URL")
    if not url:
        pytest.skip("CROWDBAKE_TEST_S3_URL is not set (scripts/test.sh starts an S3 server)")
    env = {
        "CROWDBAKE_STORE": "s3", "CROWDBAKE_S3_ENDPOINT_URL": url,
        "CROWDBAKE_S3_BUCKET": os.environ.get("CROWDBAKE_TEST_S3_BUCKET", "crowdbake-test"),
        "CROWDBAKE_S3_PREFIX": f"test-{uuid.uuid4().hex[:12]}",
        "CROWDBAKE_S3_ACCESS_KEY_ID": os.environ.get("CROWDBAKE_TEST_S3_ACCESS_KEY_ID", "crowdbake-test"),
        "CROWDBAKE_S3_SECRET_ACCESS_KEY": os.environ.get("CROWDBAKE_TEST_S3_SECRET_ACCESS_KEY", "crowdbake-test-secret"),
    }
    ensure_bucket(make_client(url, "us-east-1", env["CROWDBAKE_S3_ACCESS_KEY_ID"], env["CROWDBAKE_S3_SECRET_ACCESS_KEY"]), env["CROWDBAKE_S3_BUCKET"])
    return env


def database_env() -> dict[str, str]:
    """CROWDBAKE_DATABASE_URL of a fresh PostgreSQL database when CROWDBAKE_TEST_DATABASE_URL is set, else none
    (a SQLite file in the data folder)."""
    server = os.environ.get("CROWDBAKE_TEST_DATABASE_URL")
    return {"CROWDBAKE_DATABASE_URL": fresh_test_database(server)} if server else {}


def settings_overrides(env: dict[str, str]) -> dict[str, str]:
    """Settings keyword arguments of CROWDBAKE_* variables."""
    return {key.removeprefix("CROWDBAKE_").lower(): value for key, value in env.items() if key.startswith("CROWDBAKE_")}


def stored_blobs(settings) -> list[str]:
    """Every digest in the blob store of `settings` and every staging file left beside it."""
    from crowdbake.storage.store import open_store

    blobs = open_store(settings).blobs
    staging = sorted(f".incoming/{path.name}" for path in Path(blobs.staging_dir).glob("*"))
    return sorted(blobs.digests()) + staging


def published_files(settings, name: str, version: str) -> dict[str, bytes]:
    """manifest.json and every listed file of a published bundle, read from the store of `settings`."""
    from crowdbake.storage.store import open_store

    store = open_store(settings).bundles
    published = store.manifest(name, version)
    files = {"manifest.json": published.data}
    for path in published.files:
        with store.open_file(name, version, path) as handle:
            files[path] = handle.read()
    return files


def make_api(tmp_path: Path, store: str = "local", **overrides) -> Api:
    """The real app on a temporary data folder, with one key per entry of KEY_SCOPES.

    The keys are one team's roles (an upload key, a bake key, a read key...) that hand each other
    assets and bundles, so the app runs as a shared workspace unless `shared_workspace=False` is given
    (tests/test_ownership.py runs the default, where every key sees only what it created)."""
    from fastapi.testclient import TestClient

    from crowdbake.api.app import create_app
    from crowdbake.settings import Settings
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.keys import create_api_key

    if "database_url" not in overrides and os.environ.get("CROWDBAKE_TEST_DATABASE_URL"):
        overrides["database_url"] = fresh_test_database(os.environ["CROWDBAKE_TEST_DATABASE_URL"])
    overrides = {**settings_overrides(store_env(store)), **overrides}
    overrides.setdefault("shared_workspace", True)
    settings = Settings(data_dir=tmp_path / "data", **overrides)
    app = create_app(settings)
    keys = {}
    with session_scope(app.state.services.sessions) as session:
        for name, scopes in KEY_SCOPES.items():
            keys[name], _ = create_api_key(session, scopes, name)
    return Api(TestClient(app), settings, keys)


def publish_vector_bundle(api: Api, name: str | None = None, version: str | None = None, public: bool = False) -> tuple[str, str]:
    """Publish the good bundle vector through the app's bundle store (as name/version) and record it."""
    import json

    from crowdbake.storage.bundles import register_bundle
    from crowdbake.storage.db import session_scope

    manifest = json.loads((GOOD_BUNDLE / "manifest.json").read_bytes())
    name, version = name or manifest["name"], version or manifest["version"]
    store = api.client.app.state.services.bundles
    store.publish(GOOD_BUNDLE, name, version)
    with session_scope(api.sessions) as session:
        register_bundle(session, store, name, version, public, None)
    return name, version


# ---------------------------------------------------------------------------------- real processes


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def local_api_key(data_dir: Path, scopes: str, name: str) -> str:
    """An API key with `scopes` in data_dir's SQLite database, made (folders, migrations) as a service
    started on data_dir (service_env) reads it."""
    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
    from crowdbake.storage.keys import create_api_key

    settings = Settings(data_dir=data_dir)
    settings.ensure_dirs()
    engine = make_engine(settings.database_url)
    try:
        migrate(engine)
        with session_scope(make_sessionmaker(engine)) as session:
            key, _ = create_api_key(session, scopes, name)
    finally:
        engine.dispose()
    return key


def service_env(data_dir: Path, broker_url: str, **extra: str) -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if not key.startswith("CROWDBAKE_") or key == "CROWDBAKE_SHARED_ASSETS"}
    env.update({
        "CROWDBAKE_DATA_DIR": str(data_dir), "CROWDBAKE_BROKER_URL": broker_url,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(SERVICES_DIR), env.get("PYTHONPATH", "")])),
        "PYOPENGL_PLATFORM": env.get("PYOPENGL_PLATFORM", "osmesa"),
    })
    env.update(extra)
    return env


@dataclass
class Process:
    popen: subprocess.Popen
    log: Path

    def tail(self, lines: int = 40) -> str:
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:]) if self.log.exists() else ""

    def stop(self, timeout: float = 20) -> None:
        if self.popen.poll() is None:
            self.popen.terminate()
            try:
                self.popen.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()


def start_process(command: list[str], env: dict[str, str], log: Path) -> Process:
    handle = open(log, "wb")
    popen = subprocess.Popen(command, env=env, stdout=handle, stderr=subprocess.STDOUT, cwd=str(log.parent))
    handle.close()
    return Process(popen, log)


def start_api(env: dict[str, str], port: int, log: Path, timeout: float = 60) -> Process:
    """uvicorn with the app factory on 127.0.0.1:port; returns once /health answers."""
    import httpx

    process = start_process(
        [sys.executable, "-m", "uvicorn", "--factory", "crowdbake.api.app:create_app", "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning",
         "--http", "crowdbake.api.slow_clients:HeaderTimeoutProtocol", "--timeout-keep-alive", "5"],
        env, log,
    )
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.popen.poll() is not None:
            raise RuntimeError(f"uvicorn exited with {process.popen.returncode}:\n{process.tail()}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200:
                return process
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    process.stop()
    raise RuntimeError(f"uvicorn did not answer within {timeout} s:\n{process.tail()}")


def start_worker(env: dict[str, str], log: Path, concurrency: int = 2, queue: str = "crowdbake") -> Process:
    return start_process(
        [sys.executable, "-m", "celery", "-A", "crowdbake.jobs.celery_app", "worker", "--loglevel", "INFO", "--pool", "prefork",
         "--concurrency", str(concurrency), "--queues", queue, "--hostname", f"e2e-{os.getpid()}-{queue}@%h", "--without-gossip", "--without-mingle"],
        env, log,
    )


def raw_http(port: int, request: bytes, timeout: float = 10) -> bytes:
    """Send `request` as is (headers that may lie) and return what the server answers before closing."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(request)
        answer = b""
        while b"\r\n\r\n" not in answer or len(answer) < 12:
            chunk = sock.recv(65536)
            if not chunk:
                break
            answer += chunk
        return answer


def redis_url_or_skip() -> str:
    url = os.environ.get("CROWDBAKE_TEST_REDIS_URL")
    if not url:
        pytest.skip("CROWDBAKE_TEST_REDIS_URL is not set (scripts/test.sh starts redis-server on loopback and sets it)")
    return url


def upload_small_assets(api: Api, tmp_path: Path) -> dict[str, str]:
    """A tiny character, a 12-frame cloth and one texture uploaded with the upload key: their asset ids."""
    points, faces = tiny_cloth(frames=12)
    upload = api.auth("upload")
    character = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", tiny_character_glb())}, headers=upload).json()
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))}, headers=upload).json()
    texture = api.client.post("/v1/assets/textures", files={"file": ("d.png", png_bytes())}, headers=upload).json()
    return {"character": character["id"], "cloth": cloth["id"], "texture": texture["id"]}


def bake_body(assets: dict[str, str], **changes) -> dict:
    """A small bake request of `assets` (upload_small_assets), with `changes` applied."""
    body = {"name": "walker", "version": "1.0.0", "character": assets["character"], "cloth": assets["cloth"],
            "textures": {"diffuse_0.png": assets["texture"]}, "params": {"impostor_frames": 2, "azimuths": 4, "tile_size": 32}}
    body.update(changes)
    return body
