"""One bake plan, two executors: the local runner (`crowdbake bake`) and the service's Celery tasks run the
same nodes of crowdbake.stages.plan with the same keys (so the same records) and publish the same bytes.

The service side is a real uvicorn and Celery worker on the filesystem broker (baked_service); the local
side is run_bake with two worker processes on the same inputs, parameters and `created`.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from baked_service import NAME, PARAMS, baked_service
from crowdbake.stages import STAGES, plan

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_the_plan_is_runnable_by_both_executors():
    """Every need and read names an earlier node, and the units run in STAGES order: the service runs a
    unit's nodes in plan order, the runner anything whose needs are done."""
    assert plan.plan_problems() == []
    assert [node.unit for node in plan.BAKE_PLAN] == sorted((node.unit for node in plan.BAKE_PLAN), key=STAGES.index)
    assert {node.unit for node in plan.BAKE_PLAN} == set(STAGES)
    assert [unit for unit in STAGES if plan.runs_in_parallel(unit)] == ["loops", "probes", "impostors"]


def test_a_plan_with_a_need_on_a_later_node_is_refused():
    first, second = plan.BAKE_PLAN[:2]
    swapped = (second, first, *plan.BAKE_PLAN[2:])
    assert any("not an earlier node" in problem for problem in plan.plan_problems(swapped))


def _service_trace(settings, bake_id: str) -> list[dict]:
    from crowdbake.storage.db import make_engine, make_sessionmaker, session_scope
    from crowdbake.storage.models import BakePart, BakeStage

    with session_scope(make_sessionmaker(make_engine(settings.database_url))) as session:
        stages = session.query(BakeStage).filter(BakeStage.bake_id == bake_id).all()
        parts = session.query(BakePart).filter(BakePart.bake_id == bake_id).all()
        entries = [entry for row in stages for entry in (row.result or {}).get("nodes", [])]
        entries += [part.spec["ran"] for part in parts]
    return entries


def _files(folder: Path) -> dict[str, bytes]:
    return {path.relative_to(folder).as_posix(): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def test_the_runner_and_the_celery_tasks_run_the_same_nodes_and_publish_the_same_bytes(small_sample, tmp_path):
    from crowdbake.formats.bundle import verify_bundle
    from crowdbake.params import BakeParams
    from crowdbake.stages.runner import run_bake
    from crowdbake.stages.validate import BakeInputs

    with baked_service(tmp_path / "service", small_sample) as service:
        served = service.settings.bundles_dir / NAME / "1.0.0"
        created = verify_bundle(served).manifest["created"]
        celery_nodes = _service_trace(service.settings, service.bake["id"])
        served_files = _files(served)

    inputs = BakeInputs(small_sample / "character.glb", small_sample / "cloth.pc2", small_sample / "cloth.obj",
                        small_sample / "textures", None, NAME, "1.0.0", BakeParams.from_dict(PARAMS), created=created)
    summary = run_bake(inputs, tmp_path / "local" / "bundles", tmp_path / "local" / "work", workers=2)

    def as_set(entries: list[dict]) -> set[tuple]:
        return {(entry["node"], entry["item"], entry["key"]) for entry in entries}

    # Every node of the plan ran in both, each item once, with the same keys; a bake of one clip has no
    # clip loops to search apart (tests/test_clips_fan_out.py bakes several).
    assert {entry["node"] for entry in summary.nodes} == set(plan.NODES) - {"clip_loop"}
    assert len(summary.nodes) == len(as_set(summary.nodes)) and len(celery_nodes) == len(as_set(celery_nodes))
    assert as_set(celery_nodes) == as_set(summary.nodes)
    assert all(entry["key"] for entry in summary.nodes if entry["node"] not in ("export", "commit_export"))
    assert _files(summary.bundle) == served_files
