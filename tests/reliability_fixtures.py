"""Real processes for the reliability, load and security tests: a private redis-server, the API
(uvicorn) and Celery workers on a temporary data folder, the procedural sample, and the small helpers
that drive them (upload, bake, wait, find a worker's pool processes).

Everything listens on 127.0.0.1 only. Nothing here is mocked: faults are real signals sent to real
processes (SIGKILL, SIGTERM), real restarts and real file systems that fill up.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from service_fixtures import Process, free_port, service_env, start_api

REPO = Path(__file__).resolve().parents[1]
REDIS_SERVER = shutil.which("redis-server")

# Small bakes of the procedural sample (3 walk cycles, 64² textures): a few seconds each on one core.
FAST_PARAMS = {"impostor_frames": 2, "azimuths": 4, "elevations_deg": [0, 30], "tile_size": 32, "candidates": 2, "cycle_views": 2}
# Impostor tasks long enough for a signal to land in the middle of one: 3 frames x 2 rings of 16 views of
# 256² texels. (The map shader draws a ring of 8 views of 128² in 0.03 s: a pool process seen busy had
# often finished by the time the kill landed, and under the filesystem broker a pool process killed
# while it waits for its next task takes the pool's shared queue lock with it.) Laid out by the rule: the
# measured choice's probes at 256² tiles and above add about 9 s to every such bake, and these tests are
# about the impostor tasks, not the layout.
SLOW_IMPOSTOR_PARAMS = {"impostor_frames": 3, "azimuths": 16, "elevations_deg": [0, 30], "tile_size": 256, "candidates": 2, "cycle_views": 2,
                        "impostor_choice": "rule"}
FINAL_STATES = ("succeeded", "failed", "cancelled")


def require_redis_server() -> str:
    if REDIS_SERVER is None:
        pytest.skip("redis-server is not installed (scripts/setup.sh installs it; the fault tests start their own)")
    return REDIS_SERVER


# ------------------------------------------------------------------------------------------ redis


class RedisServer:
    """A private redis-server on a free loopback port, run in the foreground so its pid is ours.

    `durable=True` turns on the append-only file with an fsync per write, as a production broker must
    run: a restart then keeps every queued and unacknowledged message."""

    def __init__(self, folder: Path, durable: bool = False):
        self.binary = require_redis_server()
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.durable = durable
        self.popen: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 10) -> "RedisServer":
        persistence = ["--appendonly", "yes", "--appendfsync", "always"] if self.durable else ["--appendonly", "no"]
        log = open(self.folder / "redis.log", "ab")
        self.popen = subprocess.Popen(
            [self.binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--dir", str(self.folder),
             "--daemonize", "no", *persistence],
            stdout=log, stderr=subprocess.STDOUT,
        )
        log.close()
        deadline = time.monotonic() + timeout
        import redis

        while time.monotonic() < deadline:
            try:
                if redis.Redis(host="127.0.0.1", port=self.port, socket_timeout=0.5).ping():
                    return self
            except redis.RedisError:
                time.sleep(0.05)
        raise RuntimeError(f"redis-server did not answer on port {self.port}")

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10) -> None:
        if self.popen is not None and self.popen.poll() is None:
            self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
        self.popen = None


# ---------------------------------------------------------------------------------------- service


@dataclass
class Service:
    """API + workers on one data folder, one queue, one broker. Keys: 'all' and one per single scope."""

    root: Path
    env: dict[str, str]
    keys: dict[str, str]
    settings: Any
    port: int = 0
    api: Process | None = None
    workers: list[Process] = field(default_factory=list)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def auth(self, which: str = "all") -> dict[str, str]:
        return {"Authorization": f"Bearer {self.keys[which]}"}

    def client(self, which: str = "all", timeout: float = 30) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=self.auth(which), timeout=timeout)

    def start_api(self) -> Process:
        self.port = self.port or free_port()
        self.api = start_api(self.env, self.port, self.root / f"api-{len(list(self.root.glob('api-*.log')))}.log")
        return self.api

    def start_worker(self, concurrency: int = 1, extra_env: dict[str, str] | None = None, preexec_fn=None, own_group: bool = False) -> Process:
        """A Celery worker (prefork) on the service's queue; `preexec_fn` runs in the child before exec
        (to set resource limits); `own_group` starts it in a process group of its own (its pid), so a
        test can SIGKILL the worker and its pool at once, as a lost machine."""
        index = len(self.workers)
        env = dict(self.env, **(extra_env or {}))
        command = [sys.executable, "-m", "celery", "-A", "crowdbake.jobs.celery_app", "worker", "--loglevel", "INFO", "--pool", "prefork",
                   "--concurrency", str(concurrency), "--queues", env["CROWDBAKE_QUEUE"], "--hostname", f"rel{index}-{uuid.uuid4().hex[:6]}@%h",
                   "--without-gossip", "--without-mingle"]
        log = self.root / f"worker-{index}.log"
        with open(log, "wb") as handle:
            popen = subprocess.Popen(command, env=env, stdout=handle, stderr=subprocess.STDOUT, cwd=str(self.root), preexec_fn=preexec_fn,
                                     start_new_session=own_group)
        worker = Process(popen, log)
        self.workers.append(worker)
        return worker

    def worker_logs(self) -> str:
        return "\n".join(worker.log.read_text(errors="replace") for worker in self.workers if worker.log.exists())

    def sessions(self):
        from crowdbake.storage.db import make_engine, make_sessionmaker

        return make_sessionmaker(make_engine(self.settings.database_url))

    def stop(self) -> None:
        for worker in self.workers:
            worker.stop(timeout=30)
        if self.api is not None:
            self.api.stop()


def make_service(root: Path, broker_url: str, **settings_env: str) -> Service:
    """A migrated database with keys, and the environment of its API and workers (nothing started).

    The keys are one team's roles handing each other assets and bundles, so the service runs as a
    shared workspace unless CROWDBAKE_SHARED_WORKSPACE is given (services/tests/test_ownership.py
    checks the default, where a key sees only what it created)."""
    settings_env.setdefault("CROWDBAKE_SHARED_WORKSPACE", "true")
    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
    from crowdbake.storage.keys import create_api_key

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    data = root / "data"
    queue = f"crowdbake-rel-{uuid.uuid4().hex[:8]}"
    env = service_env(data, broker_url, CROWDBAKE_QUEUE=queue, CROWDBAKE_MAX_UPLOAD_BYTES=str(16 << 20), **settings_env)
    overrides = {key.removeprefix("CROWDBAKE_").lower(): value for key, value in settings_env.items() if key.startswith("CROWDBAKE_")}
    settings = Settings(data_dir=data, **overrides)
    settings.ensure_dirs()
    engine = make_engine(settings.database_url)
    migrate(engine)
    keys = {}
    with session_scope(make_sessionmaker(engine)) as session:
        for name, scopes in {"all": "upload,bake,publish,read", "upload": "upload", "bake": "bake", "read": "read", "publish": "publish"}.items():
            keys[name], _ = create_api_key(session, scopes, f"reliability {name}")
    engine.dispose()
    return Service(root=root, env=env, keys=keys, settings=settings)


# ------------------------------------------------------------------------------------ requests


def upload_sample(client: httpx.Client, sample: Path, textures: int = 2) -> dict[str, Any]:
    """Upload the sample's character, cloth and the first `textures` diffuse maps; returns asset ids."""
    character = client.post("/v1/assets/characters", files={"file": ("character.glb", (sample / "character.glb").read_bytes())})
    assert character.status_code in (200, 201), character.text
    cloth = client.post("/v1/assets/cloth", files={"cache": ("cloth.pc2", (sample / "cloth.pc2").read_bytes()),
                                                   "mesh": ("cloth.obj", (sample / "cloth.obj").read_bytes())})
    assert cloth.status_code in (200, 201), cloth.text
    ids = {"character": character.json()["id"], "cloth": cloth.json()["id"], "textures": {}}
    for path in sorted((sample / "textures").glob("diffuse_*.png"))[:textures]:
        texture = client.post("/v1/assets/textures", files={"file": (path.name, path.read_bytes())})
        assert texture.status_code in (200, 201), texture.text
        ids["textures"][path.name] = texture.json()["id"]
    return ids


def bake_body(ids: dict[str, Any], name: str, version: str, params: dict[str, Any] | None = None, publish: bool = True) -> dict[str, Any]:
    return {"name": name, "version": version, "character": ids["character"], "cloth": ids["cloth"], "textures": ids["textures"],
            "params": dict(params or FAST_PARAMS), "publish": publish}


def wait_for_bake(client: httpx.Client, bake_id: str, timeout: float, states=FINAL_STATES, explain=lambda: "") -> dict[str, Any]:
    """Poll a bake until its state is one of `states`; fails the test with `explain()` on timeout."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            bake = client.get(f"/v1/bakes/{bake_id}").json()
            if bake["state"] in states:
                return bake
        except httpx.HTTPError:
            pass  # the API may be restarting
        if time.monotonic() > deadline:
            pytest.fail(f"bake {bake_id} not {'/'.join(states)} within {timeout} s:\n{explain()}")
        time.sleep(0.25)


def tree_bytes(root: Path) -> dict[str, bytes]:
    """Every file under `root` by relative path (a bundle, compared byte for byte)."""
    return {path.relative_to(root).as_posix(): path.read_bytes() for path in sorted(Path(root).rglob("*")) if path.is_file()}


def files_under(root: Path) -> list[str]:
    return sorted(path.relative_to(root).as_posix() for path in Path(root).rglob("*") if path.is_file())


# ----------------------------------------------------------------------------------- processes


def child_pids(pid: int) -> list[int]:
    """Direct children of `pid` (a Celery worker's pool processes), from /proc."""
    children = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                children.append(int(entry.name))
    return children


def cpu_ticks(pid: int) -> int:
    """User + system CPU clock ticks used by `pid` so far (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0
    return int(fields[11]) + int(fields[12])


def busy_children(pid: int, window_s: float = 0.3, min_ticks: int = 5) -> list[int]:
    """Pool processes of worker `pid` that used at least `min_ticks` of CPU within `window_s`: the ones
    running a task right now (an idle pool process sleeps on its pipe)."""
    before = {child: cpu_ticks(child) for child in child_pids(pid)}
    time.sleep(window_s)
    return [child for child, ticks in before.items() if cpu_ticks(child) - ticks >= min_ticks]


def kill(pid: int, sig: int = signal.SIGKILL) -> bool:
    try:
        os.kill(pid, sig)
        return True
    except ProcessLookupError:
        return False


def run_sample_command(out: Path) -> Path:
    """The procedural sample (`crowdbake sample`, 3 walk cycles, 64² textures), in a subprocess."""
    command = [sys.executable, "-m", "crowdbake", "sample", str(out), "--cycles", "3", "--texture-size", "64"]
    result = subprocess.run(command, env=service_env(out / "unused", "unused"), capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return out


REFERENCE_BAKE = """
import json, sys
from pathlib import Path
from crowdbake.params import BakeParams
from crowdbake.stages.runner import run_bake
from crowdbake.stages.validate import BakeInputs
sources, out, name, version, params, created = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], sys.argv[4], json.loads(sys.argv[5]), sys.argv[6]
textures = sources / "textures"
character = next(sources.glob("character.*"))
run_bake(BakeInputs(character=character, cloth=sources / "cloth.pc2", cloth_mesh=sources / "cloth.obj",
                  textures=textures if textures.is_dir() else None, cycle=None, name=name, version=version,
                  params=BakeParams.from_dict(params), created=created), out)
"""


def materialize_sources(service: Service, bake: dict[str, Any], sources: Path) -> Path:
    """The bake's input files linked from the blob store as the worker links them (crowdbake.jobs.tasks.
    crowdbake.jobs.inputs.materialize_inputs: the same names)."""
    from crowdbake.storage.models import Asset
    from crowdbake.storage.store import open_store

    blobs = open_store(service.settings).blobs  # the local folder or the bucket, as the service stores them
    with service.sessions()() as session:
        character = session.get(Asset, bake["inputs"]["character"])
        cloth = session.get(Asset, bake["inputs"]["cloth"])
        blobs.materialize(character.files["file"]["sha256"], sources / f"character.{character.info.get('format', 'glb')}")
        blobs.materialize(cloth.files["cache"]["sha256"], sources / "cloth.pc2")
        blobs.materialize(cloth.files["mesh"]["sha256"], sources / "cloth.obj")
        for name, asset_id in sorted((bake["inputs"].get("textures") or {}).items()):
            blobs.materialize(session.get(Asset, asset_id).files["file"]["sha256"], sources / "textures" / name)
    return sources


def inputs_created(sessions, bake: dict[str, Any]) -> str:
    """The `created` a service bake gives its manifest: when its newest input asset was uploaded
    (crowdbake.jobs.inputs.inputs_created), read from the asset records."""
    from crowdbake.jobs.inputs import inputs_created as created_of
    from crowdbake.storage.models import Asset

    ids = [bake["inputs"]["character"], bake["inputs"]["cloth"], *(bake["inputs"].get("textures") or {}).values()]
    with sessions() as session:
        return created_of([session.get(Asset, asset_id) for asset_id in ids])


def run_reference_bake(sources: Path, env: dict[str, str], bake: dict[str, Any], created: str, out: Path) -> Path:
    """Bake `sources` (character.*, cloth.pc2, cloth.obj, textures/) undisturbed in one process
    (crowdbake.stages.runner.run_bake) with the bake's name, version, parameters and `created`.
    Returns the bundle folder."""
    import json

    result = subprocess.run([sys.executable, "-c", REFERENCE_BAKE, str(sources), str(out), bake["name"], bake["version"], json.dumps(bake["params"]), created],
                            env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return out / bake["name"] / bake["version"]


def reference_bake(service: Service, bake: dict[str, Any], out: Path) -> Path:
    """The same bake run undisturbed in one process from the very files the service baked (linked from
    the blob store: a published bake's work folder is gone) with the same `created`. Returns the
    bundle folder."""
    sources = materialize_sources(service, bake, out / "sources")
    return run_reference_bake(sources, service.env, bake, inputs_created(service.sessions(), bake), out)
