"""The bake's Celery tasks: the bake plan (crowdbake.stages.plan) run unit by unit.

A task takes the bake's id and attempt (and, for a fan-out part, its part id), runs the nodes of its
unit in plan order on the bake's work folder, records the outcome and queues the next unit:

    validate -> clip_loop x clips (in parallel) -> cycle -> impostor_probe x probes (in parallel) -> poses
             -> impostor_views x N (in parallel) -> pack -> publish

A unit that is one fan-out node alone (a timeline's clip loops, the impostor views) runs as one task
per item, its parts registered by the unit before it; the last part to finish queues the next unit (a
barrier in the database: records.complete_part and claim_fan_in). A fan-out without items (a bake of
one clip has no clip loops to search apart) is skipped. Claims, heartbeats, retries and cancellation are
crowdbake.jobs.deliveries's.

The work folder is named by the bake's input key (hash of inputs, parameters and code version), and the
nodes are idempotent, so a redelivered or retried task finds their outputs and returns at once.
With an object store (CROWDBAKE_STORE=s3) every machine has its own data folder: each unit then stores
what its nodes wrote as blobs (crowdbake.jobs.exchange.push_outputs, the listing's digest goes into its
stage row, or into its part row for a fan-out part) and the next unit, on whichever machine, first
fetches what its nodes read (pull_inputs), so a bake fans out over machines that share only the database,
the broker and the bucket.
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from crowdbake.jobs.celery_app import TASK_NAMES, app
from crowdbake.jobs.deliveries import (
    TASK_OPTIONS, BakeStopped, StageContext, finish, run_stage, send_queued,
)
from crowdbake.jobs.exchange import pull_inputs, push_outputs
from crowdbake.jobs.inputs import materialize_inputs
from crowdbake.stages import STAGES, plan
from crowdbake.storage import records
from crowdbake.storage.bundles import register_bundle
from crowdbake.storage.models import Bake, BakePart

logger = logging.getLogger(__name__)


class ServiceDestination:
    """Publishing into the service's stores: the bundle under the bake's name and version, then its engine
    export (unless export=false), in folders or the bucket."""

    def __init__(self, ctx: StageContext):
        self.ctx = ctx

    def publish(self, work: Path) -> dict[str, Any]:
        with self.ctx.session() as session:
            bake = self.ctx.check_live(session)
            name, version = bake.name, bake.version
        published = self.ctx.services.bundles.publish(Path(work) / "bundle", name, version)  # BundleConflict: other bytes
        return {"name": name, "version": version, "manifest_sha256": published.sha256}

    def export(self, work: Path) -> bool:
        from crowdbake.stages.publish import stage_export

        return stage_export(work, self.ctx.services.exports)

    def commit_export(self, work: Path) -> None:
        """Nothing: the export store published the export whole."""


def _materialize_inputs(ctx: StageContext, bake: Bake, session: Session):
    """The bake's inputs in this stage's work folder (crowdbake.jobs.inputs)."""
    return materialize_inputs(ctx.services.blobs, ctx.work, bake, session)


def run_unit(ctx: StageContext, unit: str) -> dict[str, Any]:
    """Every node of `unit` in plan order (a fan-out node's items one after another): the unit's own node's
    result, the nodes that ran with their keys (`nodes`), and the listing of what they wrote (`outputs`)."""
    pull_inputs(ctx, unit)
    inputs = None
    if unit == "validate":  # the plan's first node reads the bake's inputs, which the executor brings
        with ctx.session() as session:
            inputs = _materialize_inputs(ctx, ctx.check_live(session), session)
    call = plan.Call(ctx.work, progress=ctx.progress, inputs=inputs, destination=ServiceDestination(ctx))
    trace, results = plan.Trace(), {}
    for node in plan.nodes_of(unit):
        for item in node.items(ctx.work) if node.fans_out else [None]:
            results[node.name] = node.run(replace(call, item=item))
            trace.add(node, ctx.work, item)
    own = results.get(unit)
    writes = plan.unit_writes(unit)
    outputs = push_outputs(ctx, writes, kept=("cycle",)) if writes else None
    return dict(own if isinstance(own, dict) else {}, nodes=trace.entries, outputs=outputs)


def _next_unit(unit: str) -> str | None:
    return STAGES[STAGES.index(unit) + 1] if unit != STAGES[-1] else None


def _queue_after(unit: str):
    """The `after` of a unit's task: record its success, then queue the next unit (or its fan-out parts,
    or finish the bake)."""

    def after(ctx: StageContext, result, seconds: float) -> None:
        following = _next_unit(unit)
        part_ids: list[str] = []
        with ctx.session() as session:
            bake = finish(ctx, session, result, seconds)
            while following is not None and plan.runs_in_parallel(following):
                fan_out = plan.nodes_of(following)[0]
                part_ids = records.record_fan_out(session, ctx.bake_id, fan_out.items(ctx.work), following)
                if part_ids:
                    records.append_log(session, ctx.bake_id, "INFO", following, f"fanning out {len(part_ids)} {fan_out.name} tasks")
                    break
                records.stage_row(session, ctx.bake_id, following).state = "skipped"
                records.append_log(session, ctx.bake_id, "INFO", following, f"no {fan_out.name} tasks: {following} skipped")
                following = _next_unit(following)
            if part_ids:
                pass  # the parts are queued; the last to finish queues the unit after them
            elif following is None:
                # The record, the stage's success and the bake's in one transaction; a cancel cannot come
                # between folder and record (records.cancel_bake refuses once publish has started).
                register_bundle(session, ctx.services.bundles, bake.name, bake.version, bake.public, bake.id)
                records.succeed_bake(session, bake)
            elif following == "publish" and not bake.publish:
                records.stage_row(session, ctx.bake_id, "publish").state = "skipped"
                records.succeed_bake(session, bake)
                following = None
            else:
                records.queue_stage(session, ctx.bake_id, following)
        if unit == STAGES[-1]:
            # Published: the work folder has served its purpose (an identical submit returns this bake).
            shutil.rmtree(ctx.work, ignore_errors=True)
        elif following is not None:
            send_queued(following, ctx.bake_id, ctx.attempt, *part_ids)

    return after


def _unit_task(unit: str):
    """The Celery task that runs `unit`."""

    @app.task(name=TASK_NAMES[unit], **TASK_OPTIONS)
    def task(self, bake_id: str, attempt: int) -> None:
        run_stage(self, bake_id, attempt, unit, lambda ctx: run_unit(ctx, unit), _queue_after(unit))

    return task


validate, cycle, poses, pack, publish = (_unit_task(unit) for unit in ("validate", "cycle", "poses", "pack", "publish"))


def _maybe_enqueue_fan_in(ctx: StageContext, parts_left: int, unit: str) -> None:
    """The last part of fan-out `unit` to finish queues the unit after it (the claim queues it in the same
    transaction; its message is sent after the commit, or by the sweeper if the broker is away)."""
    if parts_left:
        return
    following = _next_unit(unit)
    with ctx.session() as session:
        ctx.check_live(session)
        claimed = records.claim_fan_in(session, ctx.bake_id, ctx.attempt, following)
    if claimed:
        send_queued(following, ctx.bake_id, ctx.attempt)


# What a part's spec holds besides the node's item: the listing of its outputs and its trace entry.
PART_RECORD_KEYS = ("outputs", "ran")


def _part_task(unit: str):
    """The Celery task that runs one item (a part) of fan-out `unit`: its node on the item the part's spec holds."""
    node = plan.fan_out_of(unit)

    @app.task(name=TASK_NAMES[node.name], **TASK_OPTIONS)
    def task(self, bake_id: str, attempt: int, part_id: str) -> None:
        def body(ctx: StageContext):
            with ctx.session() as session:
                part = session.get(BakePart, (bake_id, part_id))
                if part is None:
                    raise BakeStopped(f"bake {bake_id} has no part {part_id} (superseded)")
                item = {key: value for key, value in part.spec.items() if key not in PART_RECORD_KEYS}
            pull_inputs(ctx, unit)
            node.run(plan.Call(ctx.work, item=item))
            ran = plan.Trace().add(node, ctx.work, item)
            return ran, push_outputs(ctx, node.item_writes(item))

        def after(ctx: StageContext, outcome, seconds: float) -> None:
            ran, outputs = outcome
            with ctx.session() as session:
                if records.still_owner(session, ctx.bake_id, ctx.attempt, unit, part_id, ctx.owner) is None:
                    raise BakeStopped(f"bake {ctx.bake_id} attempt {ctx.attempt}: {part_id} is no longer this delivery's")
                part = session.get(BakePart, (ctx.bake_id, part_id))
                if part is not None:  # what the next unit fetches from this part (see pull_inputs), and what ran
                    part.spec = dict(part.spec, ran=ran, **({"outputs": outputs} if outputs is not None else {}))
                parts_left = records.complete_part(session, ctx.bake_id, part_id)
                row = records.stage_row(session, ctx.bake_id, unit)
                row.seconds = round((row.seconds or 0.0) + seconds, 3)  # summed over parts
                if parts_left == 0:
                    row.state, row.finished_at = "succeeded", records.utcnow()
                    row.done = row.total
                    records.append_log(session, ctx.bake_id, "INFO", unit, f"all {row.total} {node.name} tasks finished ({row.seconds:.2f} s of work)")
            _maybe_enqueue_fan_in(ctx, parts_left, unit)

        run_stage(self, bake_id, attempt, unit, body, after, log_start=False, part=part_id)

    return task


# One task per clip of a timeline; one per impostor probe (the layout's, each clip's and transition's); one
# per impostor task (a frame's views of some elevations).
clip_loop, impostor_probe, impostor_views = _part_task("loops"), _part_task("probes"), _part_task("impostors")
