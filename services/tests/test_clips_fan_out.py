"""A bake of several clips fans out per clip: the plan's loops stage has one clip_loop item per clip of the
timeline, the service runs them as parallel Celery tasks (one part each), and the bundle is the local
runner's, byte for byte but the manifest's `created` (the cycle stage joins the loops exactly as a search
of every clip in one go).

The service side is a real uvicorn and a Celery worker of two processes on the filesystem broker; the
local side is the session's clips bake (clips_fixtures.clips_bake, `crowdbake bake --timeline`).
"""
from __future__ import annotations

import datetime as dt
import json
import re
import shutil
import signal
import time
from pathlib import Path

import httpx
import pytest

from clips_fixtures import CLIPS_BAKE_PARAMS, CLIPS_NAME, CLIPS_VERSION
from crowdbake.stages import plan

BAKE_TIMEOUT_S = 240
# A Celery worker's log line for a finished task: "[2026-01-01 10:00:00,123: INFO/ForkPoolWorker-1] Task
# crowdbake.stage.clip_loop[<id>] succeeded in 2.5s: None".
SUCCEEDED = re.compile(r"^\[(?P<at>[\d-]+ [\d:]+,\d+): INFO/[^\]]+\] Task crowdbake\.stage\.clip_loop\[[^\]]+\] succeeded in (?P<s>[\d.]+)s")


def _files(folder: Path) -> dict[str, bytes]:
    return {path.relative_to(folder).as_posix(): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_a_timeline_bake_lists_one_loop_item_per_clip(clips_sample, tmp_path):
    """The loops node's items come from the checked job: one per clip of the timeline, in its order."""
    from crowdbake.params import BakeParams
    from crowdbake.stages.validate import BakeInputs

    s = clips_sample
    inputs = BakeInputs(s / "character.glb", s / "cloth.pc2", s / "cloth.obj", s / "textures", None, CLIPS_NAME, CLIPS_VERSION,
                        BakeParams.from_dict(CLIPS_BAKE_PARAMS), timeline=s / "timeline.json")
    plan.NODES["validate"].run(plan.Call(tmp_path, inputs=inputs))
    items = plan.NODES["clip_loop"].items(tmp_path)
    assert [item["clip"] for item in items] == ["Idle", "Walking", "Running"]
    assert len({item["id"] for item in items}) == 3  # one part each
    assert plan.runs_in_parallel("loops") and plan.unit_reads("cycle") == ("validate", "loops")


def test_a_stored_loop_reads_back_exactly_and_a_tree_naming_other_code_is_refused():
    """result_files keeps every bit (NaN, float32 scalars, tuples, dict order) and rebuilds crowdbake's
    dataclasses only: a file from the object store runs no code."""
    import numpy as np

    from crowdbake.bake.cycle import Candidate, CycleParams
    from crowdbake.stages.result_files import from_tree, to_tree

    value = {"z": [Candidate(3, 19, 1, float("nan"), 0.1 + 0.2, (1.5, np.float32(2.25)))], "a": (CycleParams(), np.arange(6).reshape(2, 3))}
    tree, arrays = to_tree(value)
    back = from_tree(json.loads(json.dumps(tree)), arrays)
    assert list(back) == ["z", "a"] and back["a"][0] == CycleParams()
    candidate = back["z"][0]
    assert np.isnan(candidate.vertex_distance) and candidate.edge_distance == 0.1 + 0.2
    assert type(candidate.edge_distance_per_view[1]) is np.float32 and candidate.edge_distance_per_view == (1.5, 2.25)
    np.testing.assert_array_equal(back["a"][1], np.arange(6).reshape(2, 3))
    with pytest.raises(ValueError, match="not a crowdbake dataclass"):
        from_tree({"__dataclass__": "os:system", "fields": {}}, {})
    with pytest.raises(TypeError):
        to_tree(object())


def _ran_at_once(worker_log: str) -> bool:
    """True when two clip_loop tasks' spans (from the worker's "succeeded in" lines) overlap."""
    spans = []
    for line in worker_log.splitlines():
        found = SUCCEEDED.match(line)
        if found:
            end = dt.datetime.strptime(found["at"], "%Y-%m-%d %H:%M:%S,%f").timestamp()
            spans.append((end - float(found["s"]), end))
    spans.sort()
    return any(later[0] < earlier[1] for earlier, later in zip(spans, spans[1:]))


@pytest.mark.integration
def test_the_service_searches_each_clip_in_its_own_task_and_publishes_the_runners_bytes(clips_sample, clips_bake, tmp_path):
    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
    from crowdbake.storage.keys import create_api_key
    from crowdbake.storage.models import BakePart
    from service_fixtures import free_port, service_env, start_api, start_worker

    code, local_bundle = clips_bake
    assert code == 0
    data, s = tmp_path / "data", clips_sample
    settings = Settings(data_dir=data, broker_url="filesystem://")
    migrate(make_engine(settings.database_url))
    sessions = make_sessionmaker(make_engine(settings.database_url))
    with session_scope(sessions) as session:
        key, _ = create_api_key(session, "upload,bake,publish,read", "tests")
    env, port = service_env(data, "filesystem://"), free_port()
    api = start_api(env, port, tmp_path / "api.log")
    worker = start_worker(env, tmp_path / "worker.log", concurrency=2)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
            def upload(url: str, **files: Path) -> str:
                answer = client.post(url, files={field: (path.name, path.read_bytes()) for field, path in files.items()})
                assert answer.status_code == 201, answer.text
                return answer.json()["id"]

            body = {"name": CLIPS_NAME, "version": CLIPS_VERSION, "params": CLIPS_BAKE_PARAMS,
                    "character": upload("/v1/assets/characters", file=s / "character.glb"),
                    "cloth": upload("/v1/assets/cloth", cache=s / "cloth.pc2", mesh=s / "cloth.obj"),
                    "timeline": upload("/v1/assets/timelines", timeline=s / "timeline.json"),
                    "textures": {path.name: upload("/v1/assets/textures", file=path) for path in sorted((s / "textures").glob("*.png"))}}
            created = client.post("/v1/bakes", json=body)
            assert created.status_code == 202, created.text
            deadline = time.monotonic() + BAKE_TIMEOUT_S
            while (bake := client.get(f"/v1/bakes/{created.json()['id']}").json())["state"] not in ("succeeded", "failed", "cancelled"):
                assert time.monotonic() < deadline and worker.popen.poll() is None, worker.tail(60)
                time.sleep(0.5)
        assert bake["state"] == "succeeded", (bake["error"], worker.tail(60))
        # Celery's cold shutdown (SIGQUIT): nothing is left to finish, and a warm one waits seconds for the pool.
        worker.popen.send_signal(signal.SIGQUIT)
        worker.stop()
        stages = {stage["stage"]: stage for stage in bake["stages"]}
        assert (stages["loops"]["state"], stages["loops"]["done"], stages["loops"]["total"]) == ("succeeded", 3, 3)
        with session_scope(sessions) as session:
            parts = session.query(BakePart).filter(BakePart.bake_id == bake["id"], BakePart.stage == "loops").all()
            ran = sorted((part.spec["clip"], part.spec["ran"]["node"], bool(part.spec["ran"]["key"])) for part in parts)
        assert ran == [("Idle", "clip_loop", True), ("Running", "clip_loop", True), ("Walking", "clip_loop", True)]
        assert _ran_at_once(worker.log.read_text(errors="replace")), worker.tail(80)
        served, local = _files(settings.bundles_dir / CLIPS_NAME / CLIPS_VERSION), _files(local_bundle)
        # `created` comes from the inputs' modification times (crowdbake.stages.validate), which the uploads
        # do not keep; the manifest is otherwise the same, and so is every file it lists the digest of.
        manifests = [json.loads(files.pop("manifest.json")) for files in (served, local)]
        assert [manifest.pop("created") for manifest in manifests][0] != ""
        assert manifests[0] == manifests[1] and served == local
    finally:
        worker.stop()
        api.stop()
        shutil.rmtree(data / "work", ignore_errors=True)
