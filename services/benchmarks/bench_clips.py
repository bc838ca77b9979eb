"""A loop per clip and a transition per change of clip on real cloth: the robot_clips cape.

    PYTHONPATH=services python services/benchmarks/bench_clips.py [--assets ../shared/assets] [--no-edge-pass]

Reads robot_clips/ (a cape simulated by Blender across Idle -> Walking -> Running -> Walking, with
timeline.json), runs the cycle search per clip (crowdbake.bake.clips) and the transitions between the
loops (crowdbake.bake.transitions), prints a table of every loop's and every join's quality figures against
the bounds (stretch <= 1.10, deviation <= 1.5 seam jumps, seam acceleration <= 1.5) and writes
out/bench/clips.json. The cycle side only: no body (no penetration figures), no impostors.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "services"))

from crowdbake.bake.cycle import CycleParams  # noqa: E402
from crowdbake.bake.clips import find_clip_loops  # noqa: E402
from crowdbake.bake.loop_quality import QUALITY_BOUNDS  # noqa: E402
from crowdbake.bake.transitions import find_transitions  # noqa: E402
from crowdbake.formats.obj import read_obj  # noqa: E402
from crowdbake.formats.pc2 import read_pc2  # noqa: E402
from crowdbake.ingest.timeline import read_timeline  # noqa: E402

FIGURES = ("stretch_ratio", "deviation_ratio", "seam_acceleration_ratio")


def _figures(quality) -> dict:
    return {name: getattr(quality, name) for name in FIGURES} | {"within_bounds": quality.within_bounds}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--assets", type=Path, default=Path(os.environ.get("CROWDBAKE_SHARED_ASSETS", REPO.parent / "shared" / "assets")))
    parser.add_argument("--no-edge-pass", action="store_true", help="skip pass 2 (no rendering)")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench" / "clips.json")
    args = parser.parse_args()
    folder = args.assets / "robot_clips"
    if not (folder / "timeline.json").is_file():
        print(f"skipped: {folder} is absent (set CROWDBAKE_SHARED_ASSETS)")
        return 0
    cache = read_pc2(folder / "garment.pc2")
    mesh = read_obj(folder / "garment.obj")
    faces = mesh.source_index[mesh.faces.astype(np.int64)]
    timeline = read_timeline(folder / "timeline.json")
    params = CycleParams()
    render_views = None
    if not args.no_edge_pass:
        from crowdbake.render.cloth_views import ClothViewRenderer

        render_views = ClothViewRenderer(faces, None, params.views, params.image_size, params.elevation_deg)

    started = time.perf_counter()
    loops = find_clip_loops(cache.points, faces, timeline, params, render_views)
    loop_seconds = time.perf_counter() - started
    started = time.perf_counter()
    transitions = find_transitions(cache.points, faces, timeline, loops)
    transition_seconds = time.perf_counter() - started

    rows, report = [], {"cache": {"frames": int(cache.sample_count), "vertices": int(cache.point_count)}, "bounds": QUALITY_BOUNDS,
                        "edge_pass": render_views is not None, "loops": [], "transitions": [],
                        "seconds": {"loops": round(loop_seconds, 2), "transitions": round(transition_seconds, 2)}}
    for loop in loops:
        quality = loop.result.closing.quality
        report["loops"].append({"clip": loop.clip, "period": loop.period, "segment": loop.segment,
                                "start_frame": loop.start_frame, "end_frame": loop.end_frame, **_figures(quality)})
        rows.append((f"loop {loop.clip}", f"cache {loop.start_frame}..{loop.end_frame - 1}", quality))
    for transition in transitions:
        entry = {"from_clip": transition.from_clip, "to_clip": transition.to_clip, "frames": int(len(transition.frames)),
                 "source_frames": list(transition.source_frames), "leave_loop_frame": transition.leave_loop_frame,
                 "arrive_loop_frame": transition.arrive_loop_frame}
        for side, join in (("leave", transition.leave), ("arrive", transition.arrive)):
            entry[side] = {"cache_frame": join.cache_frame, "loop_frame": join.loop_frame, "distance_m": join.distance,
                           "crossfade_frames": join.half_width, **_figures(join.quality)}
            where = f"cache {join.cache_frame} = loop frame {join.loop_frame}, D {join.distance:.3f} m"
            rows.append((f"{transition.from_clip}->{transition.to_clip} {side}", where, join.quality))
        report["transitions"].append(entry)

    print(f"robot_clips: {cache.sample_count} frames x {cache.point_count} vertices; pass 2 {'on' if render_views else 'off'}; "
          f"loops {loop_seconds:.1f} s, transitions {transition_seconds:.1f} s")
    print(f"{'':32} {'where':42} {'stretch':>8} {'deviation':>10} {'seam acc':>9}  bounds")
    for name, where, quality in rows:
        print(f"{name:32} {where:42} {quality.stretch_ratio:8.3f} {quality.deviation_ratio:10.3f} "
              f"{quality.seam_acceleration_ratio:9.3f}  {'ok' if quality.within_bounds else 'OVER ' + ','.join(quality.exceeded)}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
