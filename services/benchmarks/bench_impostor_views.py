"""Impostor memory against what crowdview draws: SSIM of the blended impostor for a grid of view counts,
elevation rings, baked frames and tile sizes, to choose the bake's defaults.

    PYTHONPATH=services python services/benchmarks/bench_impostor_views.py --work W32 W64 W128 \\
        [--cameras 8] [--out out/bench/impostor_views.json]

Each WORK is the work folder of one dense bake of the sample at one tile size, for example

    crowdbake bake sample/character.glb --cloth sample/cloth.pc2 --cloth-mesh sample/cloth.obj \\
        --textures sample/textures --cycle CYCLE.json --azimuths 32 --elevations 0,10,20,30,40 \\
        --frames 20 --tile 64 --uv-format uvblock --name dense --version t64 --out B --work W64

A coarser bake's views and frames are a subset of the dense bake's (the same orthographic cameras and
poses), so every coarser setting is scored from the dense atlases, as crowdview would blend that subset
(crowdbake.reference.impostor_blend): no bake per setting. Per setting, `--cameras` cameras halfway between
the setting's neighbouring azimuths, elevations and baked frames (around the fidelity frame), against
the mesh rendered there (crowdbake.stages.runtime_fidelity). At the baked views the picture does not
depend on the subset, so `at_views` is the dense bake's own (fidelity.json runtime.at_views).
Memory: the UV-mapped impostor's resident bytes (normal map bc1 + UV map), per format, for the setting.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.bake import fidelity, impostor_views, shading, view_blend  # noqa: E402
from crowdbake.reference import impostor_blend  # noqa: E402
from crowdbake.formats.binary import layer_size  # noqa: E402
from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, load_poses  # noqa: E402
from crowdbake.reference.runtime_picture import AtlasTiles  # noqa: E402
from crowdbake.stages.runtime_fidelity import render_mesh_references  # noqa: E402

MIB = 1024 * 1024
AZIMUTH_COUNTS = (8, 16, 32)
ELEVATION_SETS = ((0.0, 20.0, 40.0), (0.0, 10.0, 20.0, 30.0, 40.0))
FRAME_COUNTS = (5, 10, 20)


def impostor_bytes(tile: int, views: int, frames: int, uv_format: str) -> int:
    """Resident bytes of a UV-mapped impostor: every frame's normal (bc1) and UV atlas layers."""
    return frames * views * (layer_size("bc1", tile, tile) + layer_size(uv_format, tile, tile))


def score_setting(work: Path, poses, tiles: AtlasTiles, diffuse, chains, outfit_row, azimuths: list[float], elevations: list[float],
                  frame_count: int, cameras: int) -> dict:
    """Mean and worst SSIM of crowdview's blend of this subset of the dense bake, halfway between its views and frames."""
    dense = poses.atlas_layout()
    dense_frames = list(poses.frame_indices)
    stride = max(1, len(dense_frames) // frame_count)
    start = dense_frames.index(poses.fidelity_frame) % stride
    frames = dense_frames[start::stride]
    k = frames.index(poses.fidelity_frame)
    following = frames[(k + 1) % len(frames)]
    span = following - frames[k] if following > frames[k] else following + poses.cycle_frames - frames[k]
    frame = (frames[k] + span // 2) % poses.cycle_frames
    frame_weights = view_blend.blend_frame_weights(frame, frames, poses.cycle_frames)
    step = 360.0 / len(azimuths)
    mid_elevations = [(a + b) / 2.0 for a, b in zip(elevations, elevations[1:])] or list(elevations)
    spread = np.linspace(0, len(azimuths), cameras, endpoint=False).astype(int)
    chosen = [(azimuths[i] + step / 2.0, mid_elevations[n % len(mid_elevations)]) for n, i in enumerate(spread)]
    references = render_mesh_references(work, poses, frame, chosen, FIDELITY_SUPERSAMPLE)
    size = dense.tile_size
    scores = []
    for (azimuth, elevation), reference in zip(chosen, references):
        weights = view_blend.blend_view_weights(azimuth, elevation, azimuths, elevations)
        samples = []
        for w, tile, layer in impostor_blend.samples_for(weights, frame_weights):
            a = dense.azimuths_deg.index(azimuths[tile % len(azimuths)])
            e = dense.elevations_deg.index(elevations[tile // len(azimuths)])
            samples.append((w, tiles.tile(a + e * len(dense.azimuths_deg), dense_frames.index(frames[layer]))))
        view = impostor_views.ortho_view(poses.center, poses.radius, azimuth, elevation, size)
        image = impostor_blend.blend_image(samples, diffuse, outfit_row, shading.camera_light(view), size, chains, reprojected=False)
        scores.append(fidelity.compare(reference, image)["ssim"])
    return {"between_frame_weight": frame_weights.weight, "ssim_mean": float(np.mean(scores)), "ssim_worst": float(np.min(scores))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, nargs="+", required=True, help="work folders of dense bakes, one per tile size")
    parser.add_argument("--cameras", type=int, default=8, help="between-view cameras per setting")
    parser.add_argument("--out", type=Path, default=Path("out/bench/impostor_views.json"))
    args = parser.parse_args()
    rows = []
    for work in args.work:
        poses = load_poses(work)
        dense = poses.atlas_layout()
        bundle = work / "bundle"
        manifest = json.loads((bundle / "manifest.json").read_text())
        maps = manifest["impostor"]["maps"]
        tiles = AtlasTiles(dense, (bundle / maps["uv"]).read_bytes(), (bundle / maps["normal"]).read_bytes())
        textures = dict(np.load(work / "poses" / "textures.npz"))
        diffuse = [textures[f"material_{m}_decoded"][0] for m in range(len(poses.materials))]
        chains = [impostor_blend.mip_chain(texture) for texture in diffuse]
        at_views = json.loads((bundle / "fidelity.json").read_text())["runtime"]["at_views"]
        for azimuth_count in AZIMUTH_COUNTS:
            stride = len(dense.azimuths_deg) // azimuth_count
            if stride < 1 or len(dense.azimuths_deg) % azimuth_count:
                continue
            azimuths = list(dense.azimuths_deg[::stride])
            for elevations in ELEVATION_SETS:
                if not set(elevations) <= set(dense.elevations_deg):
                    continue
                for frame_count in FRAME_COUNTS:
                    if frame_count > len(poses.frame_indices):
                        continue
                    clock = time.perf_counter()
                    score = score_setting(work, poses, tiles, diffuse, chains, textures["outfits"][0], azimuths, list(elevations),
                                          frame_count, args.cameras)
                    views = azimuth_count * len(elevations)
                    row = {"tile": dense.tile_size, "azimuths": azimuth_count, "elevations": list(elevations), "frames": frame_count,
                           "at_views_ssim_mean": at_views["ssim_mean"], "between_ssim_mean": score["ssim_mean"],
                           "between_ssim_worst": score["ssim_worst"], "between_frame_weight": score["between_frame_weight"],
                           "impostor_mib": {fmt: impostor_bytes(dense.tile_size, views, frame_count, fmt) / MIB for fmt in ("uvblock", "uv32")},
                           "seconds": time.perf_counter() - clock}
                    rows.append(row)
                    print(f"tile {row['tile']:4d} azimuths {azimuth_count:2d} elevations {len(elevations)} frames {frame_count:2d}: "
                          f"at views {row['at_views_ssim_mean']:.3f}, between {row['between_ssim_mean']:.3f} (worst {row['between_ssim_worst']:.3f}), "
                          f"{row['impostor_mib']['uvblock']:.1f} MiB uvblock / {row['impostor_mib']['uv32']:.1f} MiB uv32", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"description": __doc__.splitlines()[0], "cameras": args.cameras, "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
