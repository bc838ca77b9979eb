"""Impostor fidelity against memory on real characters: which views, frames and tile sizes a clip needs.

    PYTHONPATH=services python services/benchmarks/bench_impostor_budget.py [--cases sample cesium robot_walk robot_run]
        [--configs default f10t128 ...] [--out out/bench/impostor_budget.json] [--plot docs/img/impostor_budget.png]

Bakes each case once per impostor setting of CONFIGS (crowdbake.stages.runner.run_bake, the bake's
defaults otherwise: cropped tiles, no detail maps; `default` is the defaults, the character's motion
and the 16 MiB budget choosing the counts; the tuples ask for their counts, with no budget unless they
name one) and reads what the bundle itself records:

- memory: the impostor maps the bundle stores for its one clip (normal, UV and surface map layers,
  texture_memory.json `map_bytes`: what a GPU holds, no mipmaps), in MiB;
- fidelity: fidelity.json's `runtime` section, crowdview's blended and reprojected impostor against the
  mesh at 1:1: SSIM at the baked views, and halfway between views and frames (mean and worst).

Cases: the procedural sample (generated into a scratch folder); CesiumMan in the shared long skirt;
the robot of ../shared/assets/robot_clips in its first Walking segment (cache frames 320..492, where
the timeline plays Walking alone), baked with its Walking clip; `robot_run`, its Running segment (498..624). Cases whose assets are absent are
skipped. Prints a table and writes JSON; with --plot draws SSIM between views and frames against MiB.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

ASSETS = Path(__file__).resolve().parents[2].parent / "shared" / "assets"
MIB = 1024 * 1024
# name: (azimuths, elevations, impostor frames, tile, memory budget in MiB or None: the counts as given);
# or a dict: the bake's defaults (BakeParams()) with these changes; tuples bake their counts (no frames from motion).
CONFIGS = {
    "default": {},
    "rule": {"impostor_choice": "rule"},  # tile as asked; azimuths, then frames, cut until the budget holds
    "m9": {"impostor_motion_texels": 9.0},
    "m10": {"impostor_motion_texels": 10.0},
    "b10": {"impostor_budget_mib": 10.0},  # the defaults at other budgets: the trade-off curve
    "b24": {"impostor_budget_mib": 24.0},
    "r2": {"elevations_deg": (0.0, 30.0)},  # two rings
    # The defaults at 112² tiles, the frames' motion the same in metres (9 texels).
    "t112": {"tile_size": 112, "impostor_motion_texels": 9.0},
    "a20f12": (20, (0.0, 20.0, 40.0), 12, 96),
    "a16f14": (16, (0.0, 20.0, 40.0), 14, 96),
    "f10t128": (32, (0.0, 20.0, 40.0), 10, 128, 16.0),  # 10 frames asked, 128² tiles, the budget's azimuths
    "a32": (32, (0.0, 20.0, 40.0), 10, 128),
    "a24": (24, (0.0, 20.0, 40.0), 10, 128),
    "a16f16": (16, (0.0, 20.0, 40.0), 16, 128),
    "a24f16": (24, (0.0, 20.0, 40.0), 16, 128),
    "a16f24": (16, (0.0, 20.0, 40.0), 24, 128),
    "rings2": (32, (0.0, 30.0), 10, 128),
    "t96": (32, (0.0, 20.0, 40.0), 10, 96),
    "a8f24": (8, (0.0, 20.0, 40.0), 24, 128),
    "a8r2f36": (8, (0.0, 30.0), 36, 128),
    "a12r2f24": (12, (0.0, 30.0), 24, 128),
    "a12f16": (12, (0.0, 20.0, 40.0), 16, 128),
    "t112a12f20": (12, (0.0, 20.0, 40.0), 20, 112),
    "a16f12": (16, (0.0, 20.0, 40.0), 12, 128),
    "a16r2f16": (16, (0.0, 30.0), 16, 128),
    "t112r2f24": (16, (0.0, 30.0), 24, 112),
    "t96r2f32": (16, (0.0, 30.0), 32, 96),
    "t112a12r2f32": (12, (0.0, 30.0), 32, 112),
    "t112f16": (16, (0.0, 20.0, 40.0), 16, 112),
    "t112f16b": (32, (0.0, 20.0, 40.0), 16, 112, 16.0),
    "t112a20f12": (20, (0.0, 20.0, 40.0), 12, 112),
    "t112a24f10": (24, (0.0, 20.0, 40.0), 10, 112),
}
# robot_clips/timeline.json: the first Walking segment and the Running segment, without blends.
ROBOT_SEGMENTS = {"robot_walk": ("Walking", (320, 493)), "robot_run": ("Running", (498, 625))}


def case_inputs(case: str, scratch: Path):
    """(character, cloth cache, cloth mesh, textures, params changes) of a case, or None when its assets are missing."""
    if case == "sample":
        from crowdbake.sample.generate import generate_sample

        folder = scratch / "sample"
        if not (folder / "sample.json").is_file():
            generate_sample(folder)
        return folder / "character.glb", folder / "cloth.pc2", folder / "cloth.obj", folder / "textures", {}
    if case == "cesium":
        skirt = ASSETS / "long_skirt"
        if not (ASSETS / "CesiumMan.glb").is_file() or not (skirt / "long_skirt.pc2").is_file():
            return None
        return ASSETS / "CesiumMan.glb", skirt / "long_skirt.pc2", skirt / "long_skirt.obj", None, {}
    if case in ROBOT_SEGMENTS:
        from crowdbake.formats.pc2 import read_pc2, write_pc2

        robot = ASSETS / "robot_clips"
        if not (robot / "robot.glb").is_file() or not (robot / "garment.pc2").is_file():
            return None
        clip, (first, end) = ROBOT_SEGMENTS[case]
        segment = scratch / f"{case}.pc2"
        if not segment.is_file():
            write_pc2(segment, read_pc2(robot / "garment.pc2").points[first:end])
        return robot / "robot.glb", segment, robot / "garment.obj", None, {"animation": clip, "fps": 24.0}
    raise ValueError(f"unknown case {case!r}")


def bake_once(case: str, config: str, scratch: Path) -> dict | None:
    from crowdbake.params import BakeParams
    from crowdbake.stages.runner import run_bake
    from crowdbake.stages.validate import BakeInputs

    found = case_inputs(case, scratch)
    if found is None:
        return None
    character, cloth, mesh, textures, changes = found
    if isinstance(CONFIGS[config], dict):
        params = replace(BakeParams(), export=False, **CONFIGS[config], **changes)
    else:
        azimuths, elevations, frames, tile, *budget = CONFIGS[config]
        params = replace(BakeParams(), azimuths=azimuths, elevations_deg=elevations, impostor_frames=frames, tile_size=tile, export=False,
                         impostor_motion_texels=None, impostor_budget_mib=budget[0] if budget else None, impostor_choice="rule", **changes)
    folder = Path(tempfile.mkdtemp(prefix=f"{case}-{config}-", dir=scratch))
    started = time.perf_counter()
    summary = run_bake(BakeInputs(character, cloth, mesh, textures, None, case.replace("_", "-"), "1", params), folder / "bundles", folder / "work")
    seconds = time.perf_counter() - started
    runtime = json.loads((summary.bundle / "fidelity.json").read_text())["runtime"]
    memory = json.loads((summary.bundle / "texture_memory.json").read_text())["bundle"]["map_bytes"]
    manifest = json.loads((summary.bundle / "manifest.json").read_text())
    stored = sum(memory[kind] for kind in manifest["impostor"]["maps"] if kind in memory)
    return {
        "case": case, "config": config, "azimuths": len(manifest["impostor"]["azimuths_deg"]),
        "elevations_deg": list(params.elevations_deg), "frames": len(manifest["impostor"]["frame_indices"]), "tile": manifest["impostor"]["tile_size"], "budget_mib": params.impostor_budget_mib,
        "crop": manifest["impostor"].get("crop"), "cycle_frames": manifest["clips"][0]["frames"],
        "impostor_mib": stored / MIB, "maps_mib": {kind: memory[kind] / MIB for kind in manifest["impostor"]["maps"]},
        "at_views": {k: runtime["at_views"][k] for k in ("ssim_mean", "ssim_worst")},
        "between_views": {k: runtime["between_views"][k] for k in ("ssim_mean", "ssim_worst")},
        "between_azimuths": {k: runtime["between_azimuths"][k] for k in ("ssim_mean", "ssim_worst")},
        "bake_seconds": seconds,
    }


def row_line(row: dict) -> str:
    """One row of the printed table."""
    a, b = row["at_views"], row["between_views"]
    return (f"{row['case']:<11} {row['config']:<8} {row['azimuths']:>3} {len(row['elevations_deg']):>5} {row['frames']:>3} {row['tile']:>4} "
            f"{row['impostor_mib']:>6.1f}  {a['ssim_mean']:.3f} / {a['ssim_worst']:.3f}  {b['ssim_mean']:.3f} / {b['ssim_worst']:.3f}")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True)
    for case in dict.fromkeys(row["case"] for row in rows):
        mine = sorted((row for row in rows if row["case"] == case), key=lambda row: row["impostor_mib"])
        for axis, section in zip(axes, ("at_views", "between_views")):
            line, = axis.plot([r["impostor_mib"] for r in mine], [r[section]["ssim_mean"] for r in mine], "o", label=case)  # settings, not a curve
            for r in (r for r in mine if r["config"] == "default"):  # the bake's defaults stand out
                axis.plot(r["impostor_mib"], r[section]["ssim_mean"], "*", markersize=15, color=line.get_color(), markeredgecolor="black")
            for r in mine:
                axis.annotate(r["config"], (r["impostor_mib"], r[section]["ssim_mean"]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    for axis, section, target in zip(axes, ("at baked views", "between views and frames"), (0.95, 0.90)):
        axis.axhline(target, color="grey", linestyle="--", linewidth=0.8)
        axis.axvline(16, color="grey", linestyle=":", linewidth=0.8)
        axis.set_title(f"SSIM {section} (mean)")
        axis.set_xlabel("impostor maps of one clip, MiB")
        axis.grid(alpha=0.3)
    axes[0].set_ylabel("SSIM against the mesh")
    axes[0].legend()
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=["sample", "cesium", "robot_walk"], choices=["sample", "cesium", *ROBOT_SEGMENTS])
    parser.add_argument("--configs", nargs="+", default=["default", "f10t128"], choices=list(CONFIGS))
    parser.add_argument("--out", type=Path, default=Path("out/bench/impostor_budget.json"))
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--scratch", type=Path, default=None, help="keep the bakes here (default: a temporary folder)")
    parser.add_argument("--replot", type=Path, nargs="+", default=None,
                        help="bake nothing: table and --plot of the rows of these earlier --out files (later rows of a case and config win)")
    args = parser.parse_args(argv)
    if args.replot:
        merged = {}
        for path in args.replot:
            for row in json.loads(path.read_text())["rows"]:
                merged[(row["case"], row["config"])] = row
        rows = list(merged.values())
        for row in rows:
            print(row_line(row))
        if args.plot:
            plot(rows, args.plot)
        return 0
    scratch = args.scratch or Path(tempfile.mkdtemp(prefix="impostor-budget-"))
    scratch.mkdir(parents=True, exist_ok=True)
    rows = []
    print(f"{'case':<11} {'config':<8} {'az':>3} {'rings':>5} {'fr':>3} {'tile':>4} {'MiB':>6}  {'at views':>13}  {'between':>13}", flush=True)
    for case in args.cases:
        for config in args.configs:
            row = bake_once(case, config, scratch)
            if row is None:
                print(f"{case:<11} skipped: its assets are not in {ASSETS}", flush=True)
                break
            rows.append(row)
            print(row_line(row), flush=True)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps({"machine": os.uname().machine, "cpus": os.cpu_count(), "rows": rows}, indent=1) + "\n")
    if args.plot and rows:
        plot(rows, args.plot)
        print(f"wrote {args.plot}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
