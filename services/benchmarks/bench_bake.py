"""Speed of the bake: seconds per stage and impostor renders per second for the sample character.

    PYTHONPATH=services python services/benchmarks/bench_bake.py [--sample DIR] [--out out/bench/bake.json]

Bakes the procedural sample (`crowdbake sample`: a walking character in a loose skirt, 8 diffuse
variations of 1024², generated into out/bench/sample unless --sample names one) with the bake's defaults
(10 frames x 16 azimuths x 3 elevations of 128² texels) stage by stage in one process, as `crowdbake bake`
does, and reports:

- seconds per stage (validate, cycle, poses, impostors, pack, publish);
- impostor views per second: GL only (pyrender visibility buffer) and end to end (GL + exact maps);
- the renderer's share of the impostor stage, and what the rest went to (maps, fidelity references);
- the machine: CPU count, GL platform and renderer.

Prints the figures and writes them as JSON. The figures are for this machine's cores (the project's
reference machine has 2) under OSMesa (llvmpipe) unless PYOPENGL_PLATFORM=egl.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.params import BakeParams  # noqa: E402
from crowdbake.stages.cycle import stage_cycle  # noqa: E402
from crowdbake.stages.impostors import impostor_statistics, impostor_tasks, stage_impostor_views  # noqa: E402
from crowdbake.stages.pack import stage_pack  # noqa: E402
from crowdbake.stages.poses import stage_poses  # noqa: E402
from crowdbake.stages.publish import stage_publish  # noqa: E402
from crowdbake.stages.validate import BakeInputs, stage_validate  # noqa: E402


def gl_renderer() -> str:
    """The GL renderer string of an offscreen context (llvmpipe under OSMesa, the GPU under EGL)."""
    import pyrender
    from OpenGL.GL import GL_RENDERER, glGetString

    renderer = pyrender.OffscreenRenderer(8, 8)
    try:
        renderer._platform.make_current()
        name = glGetString(GL_RENDERER)
        return name.decode() if isinstance(name, bytes) else str(name)
    finally:
        renderer.delete()


def ensure_sample(folder: Path) -> Path:
    if (folder / "sample.json").is_file():
        return folder
    from crowdbake.sample.generate import generate_sample

    print(f"generating the sample into {folder} ...", flush=True)
    generate_sample(folder)
    return folder


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sample", type=Path, help="a `crowdbake sample` folder (default: generate out/bench/sample)")
    parser.add_argument("--out", type=Path, default=Path("out/bench/bake.json"), help="JSON report (default out/bench/bake.json)")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--azimuths", type=int, default=16)
    parser.add_argument("--elevations", default="0,20,40")
    parser.add_argument("--tile", type=int, default=128)
    args = parser.parse_args()

    sample = ensure_sample(args.sample or args.out.parent / "sample")
    params = BakeParams(
        impostor_frames=args.frames,
        azimuths=args.azimuths,
        elevations_deg=tuple(float(e) for e in args.elevations.split(",")),
        tile_size=args.tile,
    )
    inputs = BakeInputs(
        sample / "character.glb", sample / "cloth.pc2", sample / "cloth.obj", sample / "textures", None, "bench", "1", params,
        created="2006-09-04T12:00:00Z",
    )
    scratch = Path(tempfile.mkdtemp(prefix="crowdbake-bench-"))
    work, bundles = scratch / "work", scratch / "bundles"
    seconds: dict[str, float] = {}
    try:
        clock = time.perf_counter()
        stage_validate(inputs, work)
        seconds["validate"] = time.perf_counter() - clock
        clock = time.perf_counter()
        cycle = stage_cycle(work).record
        seconds["cycle"] = time.perf_counter() - clock
        clock = time.perf_counter()
        poses = stage_poses(work).record
        seconds["poses"] = time.perf_counter() - clock
        clock = time.perf_counter()
        tasks = impostor_tasks(work)
        task_seconds = []
        for task in tasks:
            started = time.perf_counter()
            stage_impostor_views(work, task)
            task_seconds.append(time.perf_counter() - started)
        seconds["impostors"] = time.perf_counter() - clock
        impostor = impostor_statistics(work).to_json()
        clock = time.perf_counter()
        pack = stage_pack(work).record
        seconds["pack"] = time.perf_counter() - clock
        clock = time.perf_counter()
        bundle = stage_publish(work, bundles)
        seconds["publish"] = time.perf_counter() - clock
        total_bytes = sum(p.stat().st_size for p in bundle.rglob("*") if p.is_file())
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    views = impostor["views"]
    stage = seconds["impostors"]
    report = {
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "gl_platform": os.environ.get("PYOPENGL_PLATFORM"),
            "gl_renderer": gl_renderer(),
        },
        "sample": str(sample),
        "params": params.to_dict(),
        "stage_seconds": seconds,
        "total_seconds": sum(seconds.values()),
        "impostor": {
            "tasks": len(tasks),
            "views": views,
            "task_seconds_mean": sum(task_seconds) / len(task_seconds),
            "task_seconds_max": max(task_seconds),
            "render_seconds": impostor["render_seconds"],
            "maps_seconds": impostor["maps_seconds"],
            "fidelity_reference_seconds": impostor["reference_seconds"],
            "renders_per_second_gl": views / impostor["render_seconds"],
            "views_per_second_end_to_end": views / (impostor["render_seconds"] + impostor["maps_seconds"]),
            "renderer_share_of_stage": impostor["render_seconds"] / stage,
            "maps_share_of_stage": impostor["maps_seconds"] / stage,
            "references_share_of_stage": impostor["reference_seconds"] / stage,
        },
        "cycle": {k: getattr(cycle, k) for k in ("start_frame", "cycle_frames", "closing")},
        "meshes": poses.summary()["meshes"],
        "fidelity": pack.fidelity,
        "compression": pack.compression,
        "bundle_bytes": total_bytes,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")

    print(f"machine: {report['machine']['cpus']} CPUs, {report['machine']['gl_platform']} ({report['machine']['gl_renderer']})")
    print(f"bake of {sample} with {params.impostor_frames} frames x {params.azimuths} x {len(params.elevations_deg)} views of {params.tile_size}²")
    for name, value in seconds.items():
        print(f"  {name:10s} {value:8.2f} s")
    print(f"  {'total':10s} {report['total_seconds']:8.2f} s, bundle {total_bytes / 2**20:.1f} MiB")
    i = report["impostor"]
    print(
        f"impostors: {views} views in {len(tasks)} tasks; GL {i['renders_per_second_gl']:.0f} renders/s, "
        f"end to end {i['views_per_second_end_to_end']:.0f} views/s"
    )
    print(
        f"  stage share: renderer {100 * i['renderer_share_of_stage']:.0f}%, maps {100 * i['maps_share_of_stage']:.0f}%, "
        f"fidelity references {100 * i['references_share_of_stage']:.0f}%, other (loading, writing) "
        f"{100 * (1 - i['renderer_share_of_stage'] - i['maps_share_of_stage'] - i['references_share_of_stage']):.0f}%"
    )
    f = report["fidelity"]["impostor"]
    print(f"fidelity: SSIM mean {f['ssim_mean']:.3f} worst {f['ssim_worst']:.3f}, PSNR mean {f['psnr_db_mean']:.1f} dB")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
