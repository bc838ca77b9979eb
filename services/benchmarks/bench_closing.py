"""Every loop closing on real and sample cloth: how far each strays from the simulation, and pass 2's winner.

    PYTHONPATH=services python services/benchmarks/bench_closing.py [--assets ../shared/assets]
        [--sample-cycles 20] [--out out/bench/closing.json] [--pictures docs/img]

Two caches:
- the long skirt (`long_skirt.pc2` + `.obj`, Blender's cloth solver on CesiumMan walking in place, 48-frame
  cycle, faces wound inward), skipped with a note when the shared assets are absent;
- the procedural sample's loose skirt (`crowdbake sample`'s default: 20 cycles of 40 frames, seed 0).

For each: the cycle search with pass 2 (OSMesa pictures, the default closing) on the cache as it is and with
every face's winding reversed (the chosen start, its pass-1 distance against the best pass-1 distance); then
each closing at the chosen start: the three bounded loop-quality ratios (crowdbake.bake.loop_closing.LoopQuality),
penetrating vertex-frames, vertex-frames the push-out moved, and the peak per-vertex acceleration of the
closed loop before and after the push-out (cache units per frame squared, x 1000: mm/frame^2 for metres).
Prints a table and writes JSON. With --pictures, also renders the cloth at mid-loop as simulated, closed with
hermite and closed with crossfade (docs/img/closing_<cache>.png).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.bake import loop_closing  # noqa: E402
from crowdbake.bake.cycle import CycleParams, find_cycle  # noqa: E402
from crowdbake.render.cloth_views import ClothViewRenderer  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def peak_vertex_acceleration(loop: np.ndarray) -> float:
    """Largest |x(i+1) - 2 x(i) + x(i-1)| over vertices and frames of a (l, V, 3) loop played cyclically."""
    loop = np.asarray(loop, dtype=np.float64)
    second = np.roll(loop, -1, axis=0) - 2.0 * loop + np.roll(loop, 1, axis=0)
    return float(np.linalg.norm(second, axis=-1).max())


def per_frame_push_peak(cloth, start, cycle_frames, method, body, body_normals, faces) -> float:
    """Peak per-vertex acceleration after the former per-frame push-out (each frame pushed on its own)."""
    closed = loop_closing.close_loop(cloth, start, cycle_frames, method, None, loop_closing.unique_edges(faces))
    rows = slice(start, start + cycle_frames)
    frames = loop_closing.BodyFrames(body[rows], body_normals[rows])
    settings = loop_closing.PenetrationSettings.for_body(body)
    raw = loop_closing.looped_frames(loop_closing.close_loop(cloth, start, cycle_frames, "none"))
    looped = loop_closing.looped_frames(closed)
    new = loop_closing.penetration_mask(looped, frames, settings) & ~loop_closing.penetration_mask(raw, frames, settings)
    pushed, _ = loop_closing.push_out(looped, frames, settings, only=new)
    return peak_vertex_acceleration(pushed)


def search(cloth, faces, body, body_faces, body_normals, cycle_frames):
    """find_cycle with pass 2 on OSMesa pictures: (result, seconds)."""
    started = time.perf_counter()
    result = find_cycle(
        cloth, faces, body, body_faces, cycle_frames, CycleParams(), ClothViewRenderer(faces, body_faces), body_normals=body_normals
    )
    return result, time.perf_counter() - started


def measure(name: str, cloth, faces, body, body_faces, body_normals, cycle_frames) -> dict:
    result, seconds = search(cloth, faces, body, body_faces, body_normals, cycle_frames)
    flipped, _ = search(cloth, faces[:, ::-1], body, body_faces, body_normals, cycle_frames)
    best = min(c.vertex_distance for c in result.candidates)
    chosen = result.candidates[result.chosen]
    chosen_flipped = flipped.candidates[flipped.chosen]
    start = result.start_frame
    closings = {}
    for method in loop_closing.CLOSE_METHODS:
        closed = loop_closing.close_cycle(cloth, start, cycle_frames, method, body=body, body_normals=body_normals, cloth_faces=faces)
        unpushed = loop_closing.looped_frames(
            loop_closing.close_loop(cloth, start, cycle_frames, method, None, loop_closing.unique_edges(faces))
        )
        quality = closed.quality
        closings[method] = {
            "stretch_ratio": quality.stretch_ratio,
            "deviation_ratio": quality.deviation_ratio,
            "seam_acceleration_ratio": quality.seam_acceleration_ratio,
            "within_bounds": quality.within_bounds,
            "exceeded": list(quality.exceeded),
            "penetrating_vertex_frames": {"raw": int(closed.penetrating_before.sum()), "closed": int(closed.penetrating_closed.sum()),
                                          "after_push_out": int(closed.penetrating_after.sum())},
            "pushed_vertex_frames": closed.pushed_vertices,
            "pushed_fraction": closed.pushed_vertices / closed.looped.shape[0] / closed.looped.shape[1],
            "largest_push": float(np.linalg.norm(closed.looped - unpushed, axis=-1).max()),
            "peak_vertex_acceleration": {
                "closed": peak_vertex_acceleration(unpushed),
                "smooth_push_out": peak_vertex_acceleration(closed.looped),
                "per_frame_push_out": per_frame_push_peak(cloth, start, cycle_frames, method, body, body_normals, faces),
            },
        }
    return {
        "cache": name,
        "frames": int(cloth.shape[0]),
        "vertices": int(cloth.shape[1]),
        "cycle_frames": int(cycle_frames),
        "search_seconds": round(seconds, 2),
        "chosen_start": start,
        "chosen_vertex_distance": chosen.vertex_distance,
        "best_vertex_distance": best,
        "chosen_over_best": chosen.vertex_distance / best,
        "candidates": [{"start": c.start_frame, "vertex_distance": c.vertex_distance, "edge_distance": c.edge_distance} for c in result.candidates],
        "winding_reversed": {
            "chosen_start": flipped.start_frame,
            "chosen_vertex_distance": chosen_flipped.vertex_distance,
            "same_start": flipped.start_frame == start,
            "distance_change": abs(chosen_flipped.vertex_distance - chosen.vertex_distance) / chosen.vertex_distance,
        },
        "closings": closings,
    }


def long_skirt(assets: Path):
    from crowdbake.stages.cycle_inputs import load_cycle_inputs

    folder = assets / "long_skirt"
    inputs = load_cycle_inputs(folder / "long_skirt.pc2", folder / "long_skirt.obj", character=assets / "CesiumMan.glb")
    return inputs.cloth, inputs.cloth_faces, inputs.body, inputs.body_faces, inputs.body_normals, inputs.cycle_frames


def sample_skirt(cycles: int):
    from crowdbake.bake.skinning import pose_character
    from crowdbake.sample.generate import simulate_sample
    from crowdbake.sample.walk import FPS

    run = simulate_sample("loose", cycles=cycles, seed=0)
    posed, normals = pose_character(run.character, FPS, run.cycle_frames)
    tile = np.arange(run.frame_count) % run.cycle_frames
    faces = np.asarray(run.garment.faces, dtype=np.int64)
    return run.points, faces, posed[tile], np.asarray(run.body.faces, dtype=np.int64), normals[tile], run.cycle_frames


def pictures(name: str, cloth, faces, body, body_faces, start: int, cycle_frames: int, folder: Path) -> Path:
    """The cloth at mid-loop from the front: as simulated, closed with hermite, closed with crossfade."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    middle = cycle_frames // 2
    frames = [np.asarray(cloth[start + middle], dtype=np.float64)]
    labels = ["as simulated"]
    for method in ("hermite", "crossfade"):
        looped = loop_closing.close_cycle(cloth, start, cycle_frames, method, body=body, body_faces=body_faces, cloth_faces=faces).looped
        frames.append(looped[middle].astype(np.float64))
        quality = loop_closing.close_cycle(cloth, start, cycle_frames, method, cloth_faces=faces).quality
        labels.append(f"{method}: stretch x{quality.stretch_ratio:.2f}, deviation {quality.deviation_ratio:.2f} jumps")
    renderer = ClothViewRenderer(faces, body_faces, views=1, size=384, elevation_deg=10.0)
    body_frame = np.asarray(body[start + middle], dtype=np.float64)
    images = renderer(np.stack(frames), np.stack([body_frame] * len(frames)))
    fig, axes = plt.subplots(1, len(frames), figsize=(4 * len(frames), 4.4), dpi=100)
    for ax, image, label in zip(axes, images[:, 0], labels):
        ax.imshow(image, cmap="gray", vmin=0, vmax=255)
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"{name}: frame Fs + {middle} of the loop [{start}, {start + cycle_frames}), from the front")
    fig.tight_layout()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"closing_{name}.png"
    fig.savefig(path)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--assets", type=Path, default=Path(os.environ.get("CROWDBAKE_SHARED_ASSETS", REPO.parent / "shared" / "assets")))
    parser.add_argument("--sample-cycles", type=int, default=20)
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench" / "closing.json")
    parser.add_argument("--pictures", type=Path, default=None, help="folder for the mid-loop pictures (e.g. docs/img)")
    args = parser.parse_args(argv)

    caches = []
    if (args.assets / "long_skirt" / "long_skirt.pc2").is_file() and (args.assets / "CesiumMan.glb").is_file():
        caches.append(("long_skirt", lambda: long_skirt(args.assets)))
    else:
        print(f"long skirt skipped: no long_skirt/ and CesiumMan.glb under {args.assets}", file=sys.stderr)
    caches.append(("sample_loose", lambda: sample_skirt(args.sample_cycles)))

    report = {"bounds": loop_closing.QUALITY_BOUNDS, "default_close": loop_closing.DEFAULT_CLOSE_METHOD, "caches": []}
    for name, load in caches:
        cloth, faces, body, body_faces, body_normals, cycle_frames = load()
        figures = measure(name, cloth, faces, body, body_faces, body_normals, cycle_frames)
        report["caches"].append(figures)
        flip = figures["winding_reversed"]
        print(
            f"\n{name}: {figures['frames']} frames x {figures['vertices']} vertices, cycle {cycle_frames}; chosen Fs {figures['chosen_start']} "
            f"(pass-1 distance {figures['chosen_vertex_distance']:.4g} = {figures['chosen_over_best']:.2f} x best); "
            f"winding reversed: Fs {flip['chosen_start']} (distance changes {100 * flip['distance_change']:.1f} %)"
        )
        print(f"{'closing':10s} {'stretch':>8s} {'deviation':>9s} {'seam acc':>8s}  {'pen raw/closed/after':>22s} {'pushed':>7s} {'peak acc closed/smooth/per-frame':>34s}")
        for method, c in figures["closings"].items():
            peak = c["peak_vertex_acceleration"]
            pen = c["penetrating_vertex_frames"]
            print(
                f"{method:10s} {c['stretch_ratio']:8.3f} {c['deviation_ratio']:9.3f} {c['seam_acceleration_ratio']:8.3f}  "
                f"{pen['raw']:>6d}/{pen['closed']:>6d}/{pen['after_push_out']:>6d}   {100 * c['pushed_fraction']:5.2f}% "
                f"{1000 * peak['closed']:10.0f}/{1000 * peak['smooth_push_out']:.0f}/{1000 * peak['per_frame_push_out']:.0f}"
                + ("" if c["within_bounds"] else f"   OVER: {', '.join(c['exceeded'])}")
            )
        if args.pictures is not None:
            path = pictures(name, cloth, faces, body, body_faces, figures["chosen_start"], cycle_frames, args.pictures)
            print(f"picture: {path}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(f"\nwritten {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
