"""Stage outputs between machines: what each stage writes in its work folder, stored as blobs after it
runs and fetched before the next one (crowdbake.storage.work_outputs), so workers with private data
folders can share a bake. With the local store every worker shares one work folder and nothing travels,
except what must outlive the work folder (the cycle report).

The functions take the running stage's context (crowdbake.jobs.tasks.StageContext).
"""
from __future__ import annotations

import logging

from crowdbake.storage import records, work_outputs
from crowdbake.storage.models import BakePart, BakeStage

logger = logging.getLogger(__name__)

# What each stage writes in the work folder (crowdbake.stages.workdir), pushed to the blob store when
# work travels between machines, and the earlier stages whose outputs it reads. An impostor task writes
# impostor/parts/<id>.npz and .json (`_part_outputs`); pack reads every part. The poses task also writes
# the impostor plan, which is all an impostor task reads.
IMPOSTOR_PLAN = ("impostor/record.json", "impostor/stage.json", "impostor/scene.npz")
STAGE_OUTPUTS = {"validate": ("validate", "inputs"), "cycle": ("cycle",), "poses": ("poses", "textures", *IMPOSTOR_PLAN), "pack": ("pack", "bundle")}
STAGE_READS = {"cycle": ("validate",), "poses": ("validate", "cycle"), "impostors": ("poses",),
               "pack": ("validate", "cycle", "poses"), "publish": ("pack",)}


def part_outputs(part_id: str) -> tuple[str, ...]:
    task_id = part_id.removeprefix(records.IMPOSTOR_PART_PREFIX)
    return (f"impostor/parts/{task_id}.npz", f"impostor/parts/{task_id}.json")


def push_outputs(ctx, roots: tuple[str, ...], keep: bool = False) -> str | None:
    """Store what the stage wrote under `roots` of its work folder; the listing's digest, or None when
    work does not travel between machines and `keep` is false. `keep`: store it anyway, because the files
    are read after the work folder is deleted (the cycle report the jobs page shows)."""
    if not (ctx.services.exchanges_work or keep):
        return None
    return work_outputs.push(ctx.services.blobs, ctx.work, roots)


def pull_inputs(ctx, stage: str) -> None:
    """Fetch into this machine's work folder what `stage` reads from the earlier stages (STAGE_READS),
    and for pack every impostor part, from the listings their rows name."""
    if not ctx.services.exchanges_work:
        return
    with ctx.session() as session:
        ctx.check_live(session)
        wanted = STAGE_READS.get(stage, ())
        rows = session.query(BakeStage).filter(BakeStage.bake_id == ctx.bake_id, BakeStage.stage.in_(wanted)).all()
        listings = {row.stage: (row.result or {}).get("outputs") for row in rows}
        missing = [name for name in wanted if not listings.get(name)]
        digests = [listings[name] for name in wanted]
        if stage == "pack":
            parts = session.query(BakePart).filter(BakePart.bake_id == ctx.bake_id, BakePart.stage == "impostors").all()
            missing += [part.part for part in parts if not part.spec.get("outputs")]
            digests += [part.spec["outputs"] for part in sorted(parts, key=lambda part: part.part) if part.spec.get("outputs")]
        if missing:  # a stage only starts after the ones it reads have recorded their outputs
            raise RuntimeError(f"the outputs of {', '.join(missing)} are not recorded, so {stage} cannot run on this machine")
    fetched = sum(work_outputs.pull(ctx.services.blobs, ctx.work, digest) for digest in digests)
    if fetched:
        logger.info("bake %s: fetched %d files of earlier stages for %s", ctx.bake_id, fetched, stage)
