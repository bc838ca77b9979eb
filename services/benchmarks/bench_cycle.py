"""Speed of the cycle search: pass 1 over a long dense cache, pass 2 over the paper's 5 candidates x 5 views.

    PYTHONPATH=services python services/benchmarks/bench_cycle.py [--out out/bench/cycle.json]

Targets: pass 1 over 1,000 frames x 10,000 vertices in under 1 s; pass 2 for 5 candidates x
5 views in under 5 s, on 2 cores. Prints the figures and writes them as JSON. The cache is synthetic: a
skirt-like cone of 10,000 vertices swinging with the walk, plus slow non-periodic motion, so pass 1 has
real minima to find and pass 2 renders real folds, around a 5,000-vertex cylinder standing in for the body.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.bake import cycle_search, edge_metric  # noqa: E402
from crowdbake.bake.cycle import CycleParams, find_cycle  # noqa: E402


def grid_faces(rings: int, segments: int) -> np.ndarray:
    """(T, 3) triangles of a ring-by-segment grid closed around its segments."""
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c = (i + 1) * segments + j
    d = (i + 1) * segments + (j + 1) % segments
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])


def synthetic_skirt_cache(frames: int, rings: int, segments: int, cycle_frames: int, seed: int = 0) -> np.ndarray:
    """(frames, rings * segments, 3) float32: a cone skirt whose folds swing with the walk, plus drift."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, rings)[:, None]
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    cache = np.empty((frames, rings * segments, 3), dtype=np.float32)
    drift_phase = rng.uniform(0, 2 * np.pi, size=3)
    for f in range(frames):
        walk = 2 * np.pi * f / cycle_frames
        # Non-periodic: slow modes whose periods are not multiples of the walk cycle.
        drift = sum(0.01 * np.sin(0.031 * (k + 1) * f + drift_phase[k]) * np.cos((k + 2) * angle) for k in range(3))
        radius = 0.15 + 0.15 * t + t * (0.02 * np.sin(9 * angle + 0.4 * np.sin(walk)) + drift)
        swirl = angle + 0.15 * t * np.sin(walk)
        cache[f, :, 0] = (radius * np.sin(swirl)).ravel()
        cache[f, :, 1] = np.broadcast_to(1.0 - 0.6 * t, radius.shape).ravel()
        cache[f, :, 2] = (radius * np.cos(swirl)).ravel()
    return cache


def cylinder_body(frames: int, rings: int = 50, segments: int = 100) -> np.ndarray:
    """(frames, rings * segments, 3) float32: a still upright cylinder inside the skirt (the body's stand-in)."""
    t = np.linspace(0.0, 1.0, rings)[:, None]
    angle = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    points = np.stack(
        [0.12 * np.sin(angle + 0 * t), np.broadcast_to(1.6 - 1.6 * t, (rings, segments)), 0.12 * np.cos(angle + 0 * t)], -1
    ).reshape(-1, 3)
    return np.broadcast_to(points.astype(np.float32), (frames, *points.shape))


def best_of(repeats: int, run) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        times.append(time.perf_counter() - started)
    return min(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="out/bench/cycle.json", help="JSON output (default out/bench/cycle.json)")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--vertices", type=int, default=10000, help="rounded to rings x 100 segments")
    parser.add_argument("--cycle-frames", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    segments = 100
    rings = max(2, args.vertices // segments)
    cache = synthetic_skirt_cache(args.frames, rings, segments, args.cycle_frames)
    faces = grid_faces(rings, segments)
    body = cylinder_body(args.frames)
    body_faces = grid_faces(50, 100)
    l = args.cycle_frames

    pass1 = best_of(
        args.repeats,
        lambda: cycle_search.search_vertex_candidates(cache, l, settle_frames=l),
    )
    candidates, _ = cycle_search.search_vertex_candidates(cache, l, settle_frames=l)

    from crowdbake.render.cloth_views import ClothViewRenderer

    params = CycleParams()
    renderer = ClothViewRenderer(faces, body_faces, params.views, params.image_size, params.elevation_deg)
    frames = sorted({c.start_frame for c in candidates} | {c.start_frame + c.gap for c in candidates})
    row = {f: i for i, f in enumerate(frames)}
    render_seconds: list[float] = []
    edge_seconds: list[float] = []

    def pass2() -> None:
        started = time.perf_counter()
        images = renderer(cache[frames], body[frames])
        middle = time.perf_counter()
        for c in candidates:
            edge_metric.compare_views(images[row[c.start_frame]], images[row[c.start_frame + c.gap]])
        render_seconds.append(middle - started)
        edge_seconds.append(time.perf_counter() - middle)

    pass2_total = best_of(args.repeats, pass2)
    # The whole search end to end, penetration measure and push-out included.
    whole = best_of(1, lambda: find_cycle(cache, faces, body, body_faces, l, params, renderer))

    figures = {
        "benchmark": "cycle",
        "frames": args.frames,
        "vertices": int(cache.shape[1]),
        "body_vertices": int(body.shape[1]),
        "cycle_frames": l,
        "candidates": len(candidates),
        "views": params.views,
        "image_size": params.image_size,
        "rendered_frames": len(frames),
        "pass1_seconds": round(pass1, 4),
        "pass1_target_seconds": 1.0,
        "pass2_seconds": round(pass2_total, 4),
        "pass2_render_seconds": round(min(render_seconds), 4),
        "pass2_edge_seconds": round(min(edge_seconds), 4),
        "pass2_target_seconds": 5.0,
        "find_cycle_seconds": round(whole, 4),
        "gl_platform": os.environ.get("PYOPENGL_PLATFORM"),
        "cpu_count": os.cpu_count(),
        "affinity_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "python": sys.version.split()[0],
        "machine": platform.machine(),
        "numpy": np.__version__,
    }
    for name, value in figures.items():
        print(f"{name:>22}: {value}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(figures, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
