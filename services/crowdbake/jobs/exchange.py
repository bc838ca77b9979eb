"""Stage outputs between machines: what each unit's nodes write in the work folder (crowdbake.stages.plan:
Node.writes), stored as blobs after it runs and fetched before a unit that reads them (Node.needs and
reads), through crowdbake.storage.work_outputs, so workers with private data folders can share a bake. With the local store every worker shares one
work folder and nothing travels, except what must outlive the work folder (the cycle report).

The functions take the running stage's context (crowdbake.jobs.deliveries.StageContext).
"""
from __future__ import annotations

import logging

from crowdbake.stages import plan
from crowdbake.storage import work_outputs
from crowdbake.storage.models import BakePart, BakeStage

logger = logging.getLogger(__name__)


def push_outputs(ctx, roots: tuple[str, ...], kept: tuple[str, ...] = ()) -> str | None:
    """Store what the stage wrote under `roots` of its work folder; the listing's digest. Where work does
    not travel between machines, only the roots in `kept` (files read after the work folder is deleted:
    the cycle report the jobs page shows), or None when there are none."""
    if not ctx.services.exchanges_work:
        roots = tuple(root for root in roots if root in kept)
        if not roots:
            return None
    return work_outputs.push(ctx.services.blobs, ctx.work, roots)


def pull_inputs(ctx, stage: str) -> None:
    """Fetch into this machine's work folder what `stage`'s nodes read from the earlier units
    (plan.unit_reads), a fan-out unit's from every part's listing, from the listings their rows name."""
    if not ctx.services.exchanges_work:
        return
    with ctx.session() as session:
        ctx.check_live(session)
        earlier = plan.unit_reads(stage)
        wanted = tuple(unit for unit in earlier if not plan.runs_in_parallel(unit))
        rows = session.query(BakeStage).filter(BakeStage.bake_id == ctx.bake_id, BakeStage.stage.in_(wanted)).all()
        listings = {row.stage: (row.result or {}).get("outputs") for row in rows}
        missing = [name for name in wanted if not listings.get(name)]
        digests = [listings[name] for name in wanted]
        for unit in (unit for unit in earlier if plan.runs_in_parallel(unit)):
            parts = session.query(BakePart).filter(BakePart.bake_id == ctx.bake_id, BakePart.stage == unit).all()
            missing += [part.part for part in parts if not part.spec.get("outputs")]
            digests += [part.spec["outputs"] for part in sorted(parts, key=lambda part: part.part) if part.spec.get("outputs")]
        if missing:  # a stage only starts after the ones it reads have recorded their outputs
            raise RuntimeError(f"the outputs of {', '.join(missing)} are not recorded, so {stage} cannot run on this machine")
    fetched = sum(work_outputs.pull(ctx.services.blobs, ctx.work, digest) for digest in digests)
    if fetched:
        logger.info("bake %s: fetched %d files of earlier stages for %s", ctx.bake_id, fetched, stage)
