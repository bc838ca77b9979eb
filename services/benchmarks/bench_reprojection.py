"""What reprojection buys: fidelity.json's `runtime` scores of one bake, drawn as crowdview draws with
`--impostor-blend full` (samples unmoved, weighed by the surface map's coverage) and with `warp` (the
default: every sample reprojected by the bundle's surface map, crowdbake.reference.impostor_warp).

    PYTHONPATH=services python services/benchmarks/bench_reprojection.py --work WORK [--out out/bench/reprojection.json]

WORK is a bake's work folder with its pack stage run (`crowdbake bake ... --work WORK`); the cameras and mesh
references are the pack stage's own (crowdbake.stages.runtime_fidelity), so the `warp` row is the bundle's
fidelity.json.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, impostor_tasks, load_poses  # noqa: E402
from crowdbake.stages.pack import Parts  # noqa: E402
from crowdbake.stages.runtime_fidelity import score_runtime  # noqa: E402

CASES = ("at_views", "between_views", "between_azimuths")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("out/bench/reprojection.json"))
    args = parser.parse_args()

    poses = load_poses(args.work)
    tasks = impostor_tasks(args.work)
    bundle = args.work / "bundle"
    maps = json.loads((bundle / "manifest.json").read_text())["impostor"]["maps"]
    if "surface" not in maps:
        parser.error(f"{bundle} has no surface map: bake it again with this version")
    files = {kind: (bundle / path).read_bytes() for kind, path in maps.items()}
    result: dict = {"work": str(args.work), "normal_map": json.loads((bundle / "fidelity.json").read_text())["normal_map_format"], "modes": {}}
    print(f"{'blend':<6} " + " ".join(f"{case + ' mean/worst':>28}" for case in CASES))
    with np.load(args.work / "poses" / "textures.npz") as textures:
        for mode in ("full", "warp"):
            clock = time.perf_counter()
            runtime = score_runtime(args.work, poses, poses.atlas_layout(), tasks, Parts(args.work, tasks), files["uv"], files["normal"],
                                    textures, FIDELITY_SUPERSAMPLE, files["surface"], warp=mode == "warp")
            result["modes"][mode] = {case: {k: runtime[case][k] for k in ("ssim_mean", "ssim_worst")} for case in CASES}
            result["modes"][mode]["seconds"] = time.perf_counter() - clock
            print(f"{mode:<6} " + " ".join(f"{runtime[c]['ssim_mean']:>19.4f} / {runtime[c]['ssim_worst']:.4f}" for c in CASES), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
