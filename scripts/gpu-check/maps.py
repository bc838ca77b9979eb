#!/usr/bin/env python3
"""The bake's impostor maps as the GL draws them, on two renderers: the GPU check's second mode.

    PYOPENGL_PLATFORM=osmesa PYTHONPATH=services python scripts/gpu-check/maps.py draw WORK MAPS.npz
    PYOPENGL_PLATFORM=egl PYTHONPATH=SITE:services python3 scripts/gpu-check/maps.py compare WORK MAPS.npz
        REPORT.json [--gl-device auto|software|N]

WORK holds a sample bake's impostor plan and scene as `crowdbake bake --work` leaves them
(impostor/stage.json, record.json, scene.npz). `draw` runs every task's GL passes with the bake's own
code (crowdbake.stages.impostors.draw_task: the maps, each texel's footprint (the mesh's share of it and
its mean normal), the fidelity frame's shaded references) and keeps what they drew; `prepare.py --maps` runs it here under OSMesa.
`compare` draws them again on an EGL device and compares each with the file's, channel by channel
(map_differences): what finish_task later does to them runs on the CPU, the same on any renderer, and
needs scipy, which the GPU machine does not carry. --gl-device: auto takes the first hardware device
(as the bake does), software Mesa's software device (a rehearsal), N the device of that index. Exits 3
with one line when auto or N lands on a software rasteriser, 2 on a WORK that holds no impostor plan.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

# Texels whose values differ by more than this share of the channel's range count as differing.
DIFFERING_SHARE = 0.01


def map_differences(reference: np.ndarray, drawn: np.ndarray) -> dict:
    """How one map drawn twice differs: reference, drawn (..., C) arrays of one dtype (uint8, uint16 or
    float in 0..1). Per channel the mean and largest absolute difference as a share of the channel's
    range (1 for floats, the dtype's maximum for integers), and the share of texels where any channel
    differs by more than DIFFERING_SHARE of it."""
    if reference.shape != drawn.shape:
        raise ValueError(f"maps of shapes {reference.shape} and {drawn.shape} cannot be compared")
    scale = float(np.iinfo(reference.dtype).max) if np.issubdtype(reference.dtype, np.integer) else 1.0
    difference = np.abs(reference.astype(np.float64) - drawn.astype(np.float64)) / scale
    channels = difference.reshape(-1, difference.shape[-1])
    return {"mean_abs": [round(float(v), 6) for v in channels.mean(axis=0)],
            "max_abs": [round(float(v), 6) for v in channels.max(axis=0)],
            "texels_differing": round(float((channels > DIFFERING_SHARE).any(axis=1).mean()), 6)}


def silhouette_agreement(reference_coverage: np.ndarray, drawn_coverage: np.ndarray) -> float:
    """Intersection over union of the texels two coverage maps (any shape, 0 = empty) cover."""
    ours, theirs = reference_coverage > 0, drawn_coverage > 0
    union = np.logical_or(ours, theirs).sum()
    return 1.0 if union == 0 else round(float(np.logical_and(ours, theirs).sum() / union), 6)


def pooled(per_task: list[dict]) -> dict:
    """Every task's map_differences of one map as one: means averaged, maxima and shares at their largest."""
    channels = len(per_task[0]["mean_abs"])
    return {"mean_abs": [round(float(np.mean([t["mean_abs"][c] for t in per_task])), 6) for c in range(channels)],
            "max_abs": [max(t["max_abs"][c] for t in per_task) for c in range(channels)],
            "texels_differing_worst_task": max(t["texels_differing"] for t in per_task)}


def choose_device(requested: str) -> None:
    """Sets EGL_DEVICE_ID for --gl-device before any context is made (auto: the bake's own choice)."""
    from crowdbake.render import gl_device

    if requested == "software":
        software = [d.index for d in gl_device.query_egl_devices() if d.software]
        if not software:
            raise SystemExit("maps: EGL lists no Mesa software device")
        os.environ[gl_device.DEVICE_VARIABLE] = str(software[0])
    elif requested != "auto":
        os.environ[gl_device.DEVICE_VARIABLE] = str(int(requested))


class SoftwareRasteriser(Exception):
    """The context drawing the maps is a software rasteriser where a GPU was wanted."""


def drawn_maps(work: Path, refuse_software: bool) -> tuple[dict[str, np.ndarray], dict, float]:
    """Every task's GL passes: arrays "<task id>/<map>" (normal, uv, detail, surface, coverage, footprint_normal and, for
    the fidelity frame, references), the context's GL strings and the passes' seconds. SoftwareRasteriser
    before any drawing where refuse_software and the context is one."""
    from crowdbake.render.impostor import shared_renderer
    from crowdbake.stages.impostors import draw_task, impostor_tasks, load_plan, task_scene

    plan = load_plan(work)
    renderer = shared_renderer(int(plan.layout["tile_size"]))  # the context is made before the clock starts
    if refuse_software and renderer.gl.software_rasteriser:
        raise SoftwareRasteriser(renderer.gl.renderer)
    arrays, seconds = {}, 0.0
    for task in impostor_tasks(work):
        scene, next_positions = task_scene(work, plan, task)
        clock = time.perf_counter()
        drawn = draw_task(scene, plan, task, {"render": 0.0, "references": 0.0}, next_positions)
        seconds += time.perf_counter() - clock
        maps = {"normal": drawn.maps.normal, "uv": drawn.maps.uv, "detail": drawn.maps.detail, "surface": drawn.maps.surface,
                # The footprints' mean normal (-1..1) as 0..1, as every float map compared here.
                "coverage": drawn.footprints[..., 3:], "footprint_normal": (drawn.footprints[..., :3] + 1.0) / 2.0,
                "references": drawn.references}
        arrays.update({f"{task.id}/{name}": array for name, array in maps.items() if array is not None})
    return arrays, renderer.gl.to_json(), seconds


def comparison(reference: dict[str, np.ndarray], drawn: dict[str, np.ndarray]) -> dict:
    """map_differences of every map the two hold, pooled over tasks per map, and the worst task's
    silhouette agreement (coverage)."""
    per_map: dict[str, list[dict]] = {}
    for key in sorted(set(reference) & set(drawn)):
        per_map.setdefault(key.split("/")[1], []).append(map_differences(reference[key], drawn[key]))
    silhouettes = [silhouette_agreement(reference[k], drawn[k]) for k in reference if k.endswith("/coverage") and k in drawn]
    return {"maps": {name: pooled(tasks) for name, tasks in per_map.items()},
            "silhouette_iou_worst_task": min(silhouettes) if silhouettes else None, "differing_share": DIFFERING_SHARE}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=("draw", "compare"))
    parser.add_argument("work", type=Path)
    parser.add_argument("maps", type=Path, help="draw: the file to write; compare: the file draw wrote")
    parser.add_argument("report", type=Path, nargs="?", help="compare: the JSON to write")
    parser.add_argument("--gl-device", default="auto")
    args = parser.parse_args()
    if args.command == "compare" and (os.environ.get("PYOPENGL_PLATFORM") != "egl" or args.report is None):
        raise SystemExit("maps: compare needs PYOPENGL_PLATFORM=egl and a REPORT.json to write")
    from crowdbake.stages.workdir import StageOrderError

    if args.command == "compare":
        choose_device(args.gl_device)
    try:
        arrays, gl, seconds = drawn_maps(args.work, refuse_software=args.command == "compare" and args.gl_device != "software")
    except (StageOrderError, OSError) as e:
        print(f"maps: {args.work} holds no impostor plan and scene ({e})", file=sys.stderr)
        return 2
    except SoftwareRasteriser as e:
        print(f"maps: the context is a software rasteriser ({e}), not a GPU", file=sys.stderr)
        return 3
    if args.command == "draw":
        np.savez_compressed(args.maps, gl=np.array(json.dumps(gl)), seconds=np.array(seconds), **arrays)
        print(f"maps: drew {len(arrays)} maps in {seconds:.2f} s on {gl['renderer']} ({gl['platform']}) into {args.maps}")
        return 0
    with np.load(args.maps) as stored:
        reference = {k: stored[k] for k in stored.files if "/" in k}
        reference_gl, reference_seconds = json.loads(str(stored["gl"])), float(stored["seconds"])
    report = {"gl": gl, "reference_gl": reference_gl, "python": sys.version.split()[0], **comparison(reference, arrays),
              "seconds": {"drawn": round(seconds, 3), "reference": round(reference_seconds, 3)}}
    args.report.write_text(json.dumps(report, indent=2) + "\n")
    worst = max(max(m["max_abs"]) for m in report["maps"].values())
    print(f"maps: {len(arrays)} maps on {gl['renderer']} against {reference_gl['renderer']} ({reference_gl['platform']}): "
          f"silhouette IoU >= {report['silhouette_iou_worst_task']}, largest difference {worst:.4f} of a channel's range; "
          f"GL passes {seconds:.2f} s against {reference_seconds:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
