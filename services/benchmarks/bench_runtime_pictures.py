"""The pictures fidelity.json's `runtime` section scores, drawn by crowdview's own shader in the bake's GL
context (crowdbake.render.runtime_shader, what the pack stage does) and by its numpy copy
(crowdbake.reference.runtime_picture): seconds, and how far apart the pictures and their scores are.

    PYTHONPATH=services python services/benchmarks/bench_runtime_pictures.py --work WORK [--repeat 3]
        [--out out/bench/runtime_pictures.json]

WORK is a bake's work folder with its pack stage run (`crowdbake bake ... --work WORK`): the cameras, mesh
references and bundle maps are the pack stage's own (crowdbake.stages.runtime_fidelity.scored_cameras).
Seconds: the shader's wall and CPU (llvmpipe's threads included; the program compiled before timing) and
numpy's CPU, best of --repeat. Agreement per section: SSIM of the shader's picture against numpy's (worst
and mean), and each side's SSIM against the mesh reference (the score; mean).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.bake import fidelity  # noqa: E402
from crowdbake.reference import impostor_blend  # noqa: E402
from crowdbake.formats.bundle import verify_bundle  # noqa: E402
from crowdbake.render.impostor import BakeRenderer  # noqa: E402
from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, impostor_tasks, load_poses  # noqa: E402
from crowdbake.stages.pack import Parts  # noqa: E402
from crowdbake.reference.runtime_picture import AtlasTiles, numpy_picture  # noqa: E402
from crowdbake.stages.runtime_fidelity import runtime_atlas, runtime_textures, scored_cameras  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("out/bench/runtime_pictures.json"))
    args = parser.parse_args()

    poses = load_poses(args.work)
    layout = poses.atlas_layout()
    tasks = [task for task in impostor_tasks(args.work) if task.references]
    bundle = verify_bundle(args.work / "bundle")
    files = {kind: bundle.textures[path] for kind, path in bundle.manifest["impostor"]["maps"].items()}
    atlas = runtime_atlas(poses, layout, files["uv"], files["normal"], files.get("surface"), runtime_textures(args.work))
    scored = scored_cameras(args.work, poses, layout, tasks, Parts(args.work, tasks), FIDELITY_SUPERSAMPLE)
    pictures = [picture for *_, picture in scored]

    with BakeRenderer(layout.tile_size) as renderer:
        renderer.runtime_impostors(atlas, pictures[:1] + pictures[-1:])  # compile (most of) the programs
        shader_wall = shader_cpu = float("inf")
        for _ in range(args.repeat):
            wall, cpu = time.perf_counter(), time.process_time()
            drawn = renderer.runtime_impostors(atlas, pictures)
            shader_wall, shader_cpu = min(shader_wall, time.perf_counter() - wall), min(shader_cpu, time.process_time() - cpu)
    tiles = AtlasTiles(layout, atlas.uv_map, atlas.normal_map, atlas.surface_map, atlas.radius)
    chains = [impostor_blend.mip_chain(texture) for texture in atlas.diffuse]  # RGB only: the same with regions or without
    numpy_cpu = float("inf")
    for _ in range(args.repeat):
        cpu = time.process_time()
        copies = [numpy_picture(atlas, tiles, picture, chains) for picture in pictures]
        numpy_cpu = min(numpy_cpu, time.process_time() - cpu)

    sections: dict[str, dict[str, list[float]]] = {}
    for (section, _, reference, _), shader_picture, numpy_copy in zip(scored, drawn, copies):
        figures = sections.setdefault(section, {"against_numpy": [], "shader_score": [], "numpy_score": []})
        figures["against_numpy"].append(fidelity.compare(numpy_copy, shader_picture.astype(np.float64))["ssim"])
        figures["shader_score"].append(fidelity.compare(reference, shader_picture.astype(np.float64))["ssim"])
        figures["numpy_score"].append(fidelity.compare(reference, numpy_copy)["ssim"])
    report = {
        "work": str(args.work), "pictures": len(pictures), "tile": layout.tile_size,
        "seconds": {"shader_wall": shader_wall, "shader_cpu": shader_cpu, "numpy_cpu": numpy_cpu},
        "sections": {section: {"pictures": len(values["against_numpy"]),
                               "ssim_against_numpy_worst": min(values["against_numpy"]),
                               "ssim_against_numpy_mean": float(np.mean(values["against_numpy"])),
                               "score_ssim_mean_shader": float(np.mean(values["shader_score"])),
                               "score_ssim_mean_numpy": float(np.mean(values["numpy_score"]))}
                     for section, values in sections.items()},
    }
    print(f"{len(pictures)} pictures of {layout.tile_size}²: shader {shader_wall:.2f} s wall, {shader_cpu:.2f} s CPU; "
          f"numpy {numpy_cpu:.2f} s CPU")
    for section, row in report["sections"].items():
        print(f"  {section:17s} {row['pictures']:4d}: SSIM against numpy worst {row['ssim_against_numpy_worst']:.4f}, "
              f"mean {row['ssim_against_numpy_mean']:.4f}; score (SSIM against the mesh) shader {row['score_ssim_mean_shader']:.4f}, "
              f"numpy {row['score_ssim_mean_numpy']:.4f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
