"""A real service with a worker, for tests that bake through it (the submit client, the web page):
uvicorn and a Celery worker as subprocesses on the filesystem broker (no Redis needed), a key with
every scope and a read-only one, and the procedural sample character (the session's small_sample).

    with live_service(tmp_path, small_sample) as service:
        service.url, service.keys["all"], service.sample, service.restart_api(down_s=2)
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import httpx

from service_fixtures import Process, free_port, service_env, start_api, start_worker


@dataclass
class Service:
    url: str
    port: int
    keys: dict[str, str]
    env: dict[str, str]
    root: Path
    sample: Path
    api: Process
    worker: Process

    def client(self, key: str = "all") -> httpx.Client:
        return httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {self.keys[key]}"}, timeout=30)

    def asset_count(self) -> int:
        with self.client() as client:
            return client.get("/v1/assets", params={"limit": 1000}).json()["count"]

    def restart_api(self, down_s: float) -> None:
        """Stop uvicorn, leave the port closed for `down_s` seconds, start it again on the same port."""
        self.api.stop()
        time.sleep(down_s)
        self.api = start_api(self.env, self.port, self.root / "api-restarted.log")


@contextlib.contextmanager
def live_service(root: Path, sample: Path) -> Iterator[Service]:
    """`sample`: a generated sample folder (the session's `small_sample`)."""
    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
    from crowdbake.storage.keys import create_api_key

    data = root / "data"
    env = service_env(data, "filesystem://")
    settings = Settings(data_dir=data, broker_url="filesystem://")
    engine = make_engine(settings.database_url)
    migrate(engine)
    keys = {}
    with session_scope(make_sessionmaker(engine)) as session:
        keys["all"], _ = create_api_key(session, "upload,bake,publish,read", "ci")
        keys["read"], _ = create_api_key(session, "read", "viewer")
    port = free_port()
    api = start_api(env, port, root / "api.log")
    worker = start_worker(env, root / "worker.log", concurrency=1)
    running = Service(f"http://127.0.0.1:{port}", port, keys, env, root, sample, api, worker)
    try:
        yield running
    finally:
        running.worker.stop()
        running.api.stop()
