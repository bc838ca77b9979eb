"""Every stage of a bake in one process (`crowdbake bake`, the tests, the benchmarks).

The service runs the same stage functions as Celery tasks (crowdbake.jobs.tasks); this runner is the
sequential version: validate → cycle → poses → impostors → pack → publish.
"""
from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from crowdbake.stages.cycle import stage_cycle
from crowdbake.stages.impostors import impostor_statistics, stage_impostors
from crowdbake.stages.pack import stage_pack
from crowdbake.stages.poses import stage_poses
from crowdbake.stages.publish import stage_export, stage_publish
from crowdbake.stages.records import PosesRecord
from crowdbake.stages.validate import BakeInputs, stage_validate
from crowdbake.stages.workdir import Progress, read_json, report


@dataclass
class BakeSummary:
    """What run_bake did: where the bundle is, how big, how long each stage took, how faithful."""

    bundle: Path
    name: str
    version: str
    timings_s: dict[str, float]
    files: dict[str, int]
    meshes: list[dict[str, Any]]
    cycle: dict[str, Any]
    impostor: dict[str, Any]
    fidelity: dict[str, Any]
    compression: dict[str, Any]
    texture_memory: dict[str, Any]
    # Set when a texture variation is a JPEG (no alpha, so no colour-region codes): what that means.
    texture_note: str | None = None

    @property
    def total_bytes(self) -> int:
        return int(sum(self.files.values()))

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["bundle"] = str(self.bundle)
        data["total_bytes"] = self.total_bytes
        return data


def _mesh_summary(meshes: list[dict], poses: PosesRecord) -> list[dict]:
    """The manifest's meshes, low LODs with their target and meshoptimizer's error."""
    out = []
    for mesh in meshes:
        entry = {k: mesh[k] for k in ("part", "kind", "lod", "vertex_count", "triangle_count", "file")}
        if mesh["lod"] == 1:
            for part in poses.parts:
                if part.lod == 1 and part.part == mesh["part"]:
                    entry.update(target_triangles=part.target_triangles, relative_error=part.relative_error, locked_border=part.locked_border)
        out.append(entry)
    return out


def run_bake(inputs: BakeInputs, out_root: Path, work: Path | None = None, progress: Progress | None = None) -> BakeSummary:
    """Run every stage in this process and publish to out_root/<name>/<version>; returns a BakeSummary.

    work: the work directory (kept, so a rerun resumes); None = a temporary one, removed afterwards.
    """
    temporary = work is None
    work = Path(tempfile.mkdtemp(prefix="crowdbake-work-")) if temporary else Path(work)
    work.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    def timed(stage: str, run):
        clock = time.perf_counter()
        result = run()
        timings[stage] = time.perf_counter() - clock
        return result

    try:
        job = timed("validate", lambda: stage_validate(inputs, work)).record
        cycle = timed("cycle", lambda: stage_cycle(work, progress)).record
        poses = timed("poses", lambda: stage_poses(work, progress)).record
        timed("impostors", lambda: stage_impostors(work, progress))
        impostor = impostor_statistics(work)
        pack = timed("pack", lambda: stage_pack(work, progress)).record

        def publish() -> Path:
            # The engine export is part of publishing, as in the worker's publish task (None: export=false).
            published = stage_publish(work, Path(out_root))
            stage_export(work, Path(out_root))
            return published

        bundle = timed("publish", publish)
        report(progress, "publish", 1, 1)
    finally:
        if temporary:
            shutil.rmtree(work, ignore_errors=True)
    manifest = read_json(bundle / "manifest.json")
    return BakeSummary(
        bundle=bundle,
        name=manifest["name"],
        version=manifest["version"],
        timings_s=timings,
        files={entry["path"]: entry["size"] for entry in manifest["files"]},
        meshes=_mesh_summary(manifest["meshes"], poses),
        cycle={k: getattr(cycle, k) for k in ("start_frame", "end_frame", "cycle_frames", "closing", "position_jump_ratio", "velocity_jump_ratio", "fps")},
        impostor=asdict(impostor),
        fidelity=dict(pack.fidelity, uv_precision=pack.uv_precision),
        compression=pack.compression,
        texture_memory=pack.texture_memory,
        texture_note=(job.textures or {}).get("note"),
    )
