"""A real service with finished bakes, for the tests of what the service shows about them (/metrics,
the web page): uvicorn and a Celery worker as subprocesses on the filesystem broker (no Redis needed),
the procedural sample baked with small parameters, and a second bake that fails in a worker.

    with baked_service(tmp_path, small_sample) as service:
        service.url, service.key, service.bake, service.failed_bake
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import httpx

from service_fixtures import Process, free_port, service_env, start_api, start_worker

# Small enough to bake in seconds on 2 cores (as test_service_e2e): 3 walk cycles of 24 frames, 64²
# textures, 2 impostor frames x 4 azimuths x 2 elevations of 32² tiles, 2 cycle candidates from 2 views.
PARAMS = {"impostor_frames": 2, "azimuths": 4, "elevations_deg": [0, 30], "tile_size": 32, "candidates": 2, "cycle_views": 2}
# A parameter the API accepts and the validate stage refuses (more triangles than the mesh has).
FAILING_PARAMS = dict(PARAMS, lod_triangles=100_000_000)
NAME = "sample-walker"
BAKE_TIMEOUT_S = 240


@dataclass
class BakedService:
    url: str
    key: str
    settings: Any
    sample: Path
    bake: dict  # the finished bake, as GET /v1/bakes/{id} answered
    failed_bake: dict
    uploads: dict[str, tuple[int, int]]  # asset kind -> (bytes of the uploaded files, how many files)
    api: Process
    worker: Process

    def client(self, **kwargs) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {self.key}"}, timeout=60, **kwargs)


def _wait(client: httpx.Client, bake_id: str, worker: Process) -> dict:
    deadline = time.monotonic() + BAKE_TIMEOUT_S
    while (bake := client.get(f"/v1/bakes/{bake_id}").json())["state"] not in ("succeeded", "failed", "cancelled"):
        if time.monotonic() > deadline or worker.popen.poll() is not None:
            raise AssertionError(f"bake {bake_id} did not finish ({bake['state']}):\n{worker.tail(60)}")
        time.sleep(0.5)
    return bake


@contextlib.contextmanager
def baked_service(root: Path, sample: Path, public: bool = False) -> Iterator[BakedService]:
    """sample: the procedural sample's folder (the `small_sample` fixture), read only."""
    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
    from crowdbake.storage.keys import create_api_key

    data = root / "data"
    env = service_env(data, "filesystem://")
    settings = Settings(data_dir=data, broker_url="filesystem://")
    migrate(make_engine(settings.database_url))
    with session_scope(make_sessionmaker(make_engine(settings.database_url))) as session:
        key, _ = create_api_key(session, "upload,bake,publish,read", "tests")
    port = free_port()
    api = start_api(env, port, root / "api.log")
    worker = start_worker(env, root / "worker.log", concurrency=1)
    try:
        url = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
            files = {"character": sample / "character.glb", "cache": sample / "cloth.pc2", "mesh": sample / "cloth.obj"}
            character = client.post("/v1/assets/characters", files={"file": ("character.glb", files["character"].read_bytes())})
            cloth = client.post("/v1/assets/cloth", files={"cache": ("cloth.pc2", files["cache"].read_bytes()),
                                                            "mesh": ("cloth.obj", files["mesh"].read_bytes())})
            assert character.status_code == 201 and cloth.status_code == 201, (character.text, cloth.text)
            textures, texture_bytes = {}, 0
            for path in sorted((sample / "textures").glob("*.png")):
                answer = client.post("/v1/assets/textures", files={"file": (path.name, path.read_bytes())})
                assert answer.status_code == 201, answer.text
                textures[path.name] = answer.json()["id"]
                texture_bytes += path.stat().st_size
            body = {"name": NAME, "version": "1.0.0", "character": character.json()["id"], "cloth": cloth.json()["id"],
                    "textures": textures, "params": PARAMS, "public": public}
            created = client.post("/v1/bakes", json=body)
            assert created.status_code == 202, created.text
            failing = client.post("/v1/bakes", json=dict(body, version="0.0.1-broken", params=FAILING_PARAMS))
            assert failing.status_code == 202, failing.text
            bake = _wait(client, created.json()["id"], worker)
            failed = _wait(client, failing.json()["id"], worker)
            assert bake["state"] == "succeeded", (bake["error"], worker.tail(60))
            assert failed["state"] == "failed", failed
        worker.stop()  # nothing more to bake: leave the CPU to the test
        uploads = {"character": (files["character"].stat().st_size, 1),
                   "cloth": (files["cache"].stat().st_size + files["mesh"].stat().st_size, 2), "texture": (texture_bytes, len(textures))}
        yield BakedService(url, key, settings, sample, bake, failed, uploads, api, worker)
    finally:
        worker.stop()
        api.stop()
