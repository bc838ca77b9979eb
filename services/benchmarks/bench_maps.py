"""Seconds to make impostor maps: from visibility buffers in numpy (view by view, and all views at once),
and drawn by the map shader.

    PYTHONPATH=services python services/benchmarks/bench_maps.py --work WORK [--frame 0] [--repeat 3]
        [--out out/bench/maps.json] [--save maps.npz]

WORK is a bake's work folder (`crowdbake bake ... --work WORK`). One frame's scene is loaded and every
view of the layout (default 16 x 3 of 128²) rendered once; then the map resolution is timed apart from
the renderer: the test oracle's resolve_coverage + view_maps called per view, and resolve_coverage_views +
view_maps_views over each elevation ring at once (crowdbake.reference); the visibility renders
themselves; the map shader (what the impostor stage does: crowdbake.render.map_shader over each ring, then
fill_background), with how far its maps are from the numpy ones; and the fidelity references of the first
ring (3 x 3 samples a texel): the shader's reference pass against id renders, exact coverage and
mesh_reference in numpy. CPU seconds of the process (llvmpipe's threads included), best of --repeat.
--save writes the per-view maps, so that two checkouts' outputs can be compared texel for texel
(PYTHONPATH pointing at the other one).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, fill_background, load_plan, load_scene  # noqa: E402
from crowdbake.bake import impostor_views, shading  # noqa: E402
from crowdbake.reference import coverage as exact_coverage  # noqa: E402
from crowdbake.reference import impostor_maps  # noqa: E402
from crowdbake.reference import mesh_reference  # noqa: E402
from crowdbake.render.impostor import BakeRenderer  # noqa: E402
from crowdbake.reference.triangle_ids import TriangleIdRenderer  # noqa: E402


def best_cpu(function, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        started = time.process_time()
        function()
        best = min(best, time.process_time() - started)
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--frame", type=int, help="baked frame (default: the first)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("out/bench/maps.json"))
    parser.add_argument("--save", type=Path, help="write the per-view maps here (.npz)")
    args = parser.parse_args()

    poses = load_plan(args.work)  # the impostor plan: framing, baked frames, scene
    frame = poses.frame_indices[0] if args.frame is None else args.frame
    scene = load_scene(args.work, poses, frame)
    layout = poses.layout
    tile = int(layout["tile_size"])
    centre, radius = poses.bounds["center"], poses.bounds["radius"]
    rings = []
    report = {"work": str(args.work), "frame": frame, "tile": tile, "cpu_seconds": {}}
    with TriangleIdRenderer(tile) as ids_renderer:
        ids_renderer.set_mesh(scene.positions, scene.faces)
        for elevation in layout["elevations_deg"]:
            views = [impostor_views.ortho_view(centre, radius, azimuth, elevation, tile) for azimuth in layout["azimuths_deg"]]
            rings.append((views, [ids_renderer.render(view) for view in views]))
        report["cpu_seconds"]["visibility_renders"] = best_cpu(lambda: [ids_renderer.render(view) for views, _ in rings for view in views],
                                                               args.repeat)
    with BakeRenderer(tile) as renderer:
        def shaded() -> list:
            out = []
            for views, _ in rings:
                drawn = renderer.shader_maps(views, scene.positions, scene.normals, scene.uvs, scene.positions, scene.faces,
                                             scene.triangle_material, scene.diffuse)
                fill_background(drawn.mask, [drawn.normal, drawn.detail], unflattened=[drawn.surface])
                out.append(drawn)
            return out

        report["cpu_seconds"]["shader"] = best_cpu(shaded, args.repeat)
        shader_maps = shaded()
    report["views"] = view_count = sum(len(views) for views, _ in rings)
    arguments = (scene.positions, scene.normals, scene.uvs, scene.faces, scene.triangle_material, scene.diffuse)

    def per_view() -> list:
        out = []
        for views, images in rings:
            for view, image in zip(views, images):
                coverage = exact_coverage.resolve_coverage(view, image.ids, scene.positions, scene.faces, image.depth)
                out.append(impostor_maps.view_maps(view, coverage, *arguments))
        return out

    def batched() -> list:
        out = []
        for views, images in rings:
            ids = np.stack([image.ids for image in images])
            depth = np.stack([image.depth for image in images])
            coverages = exact_coverage.resolve_coverage_views(views, ids, scene.positions, scene.faces, depth)
            out.extend(impostor_maps.view_maps_views(views, coverages, *arguments))
        return out

    report["cpu_seconds"]["per_view"] = best_cpu(per_view, args.repeat)
    report["cpu_seconds"]["batched"] = best_cpu(batched, args.repeat)
    report["batched_equals_per_view"] = all(
        np.array_equal(a.normal, b.normal) and np.array_equal(a.uv, b.uv) and np.array_equal(a.detail, b.detail)
        for a, b in zip(per_view(), batched())
    )
    exact = batched()
    report["shader_against_numpy"] = agreement = {}
    for kind in ("normal", "uv", "detail"):
        want = np.stack([getattr(m, kind) for m in exact]).astype(np.int64)
        got = np.concatenate([getattr(drawn, kind) for drawn in shader_maps]).astype(np.int64)
        agreement[f"{kind}_share_over_one_code"] = float((np.abs(got - want) > 1).any(axis=-1).mean())
    mask = np.concatenate([drawn.mask for drawn in shader_maps])
    agreement["coverage_differs"] = int((mask != np.stack([m.coverage.mask for m in exact])).sum())

    supersample = FIDELITY_SUPERSAMPLE
    ring = [impostor_views.ortho_view(centre, radius, view.azimuth_deg, view.elevation_deg, tile * supersample) for view in rings[0][0]]
    with BakeRenderer(tile * supersample) as renderer, TriangleIdRenderer(tile * supersample) as ids_renderer:
        def shaded_references() -> np.ndarray:
            return renderer.shader_references(ring, scene.positions, scene.normals, scene.uvs, scene.faces, scene.triangle_material,
                                              scene.diffuse_runtime, scene.outfit_row, supersample)

        def numpy_references() -> np.ndarray:
            ids_renderer.set_mesh(scene.positions, scene.faces)
            return np.stack([mesh_reference.mesh_reference(view, ids_renderer.coverage(view, scene.positions, scene.faces), supersample,
                                                           scene.positions, scene.normals, scene.uvs, scene.faces, scene.triangle_material,
                                                           scene.diffuse_runtime, scene.outfit_row, shading.camera_light(view))
                             for view in ring])

        report["cpu_seconds"]["references_shader"] = best_cpu(shaded_references, args.repeat)
        report["cpu_seconds"]["references_numpy"] = best_cpu(numpy_references, args.repeat)
        difference = np.abs(shaded_references() - numpy_references())
    report["references"] = {"views": len(ring), "size": tile * supersample, "max_difference": float(difference.max()),
                            "mean_difference": float(difference.mean())}
    if args.save:
        maps = per_view()
        np.savez_compressed(args.save, **{kind: np.stack([getattr(m, kind) for m in maps]) for kind in ("normal", "uv", "detail")})
    for name, seconds in report["cpu_seconds"].items():
        views, size = (report["references"]["views"], report["references"]["size"]) if name.startswith("references") else (view_count, tile)
        print(f"{name:18s} {seconds:7.3f} s CPU for {views} views of {size}²: {1000 * seconds / views:6.2f} ms a view")
    print(f"references, shader against numpy: max difference {report['references']['max_difference']:.2g}, "
          f"mean {report['references']['mean_difference']:.2g} (colours 0..1)")
    print(f"batched maps equal the per-view maps: {report['batched_equals_per_view']}")
    print("shader maps against numpy's:", ", ".join(f"{k} {v:.2g}" for k, v in report["shader_against_numpy"].items()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
