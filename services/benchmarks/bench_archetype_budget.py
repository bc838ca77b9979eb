#!/usr/bin/env python3
"""Impostor memory against fidelity for characters of several clips: what each archetype budget buys.

    PYTHONPATH=services python services/benchmarks/bench_archetype_budget.py LABEL=BUNDLE ... \
        [--budgets 8,12,16,24,32,40,48,64] [--plot docs/img/archetype_budget.png] [--out out/bench/archetype_budget.json]

Each BUNDLE was baked with the archetype budget (`impostor_archetype_mib`), so its texture_memory.json holds
the probes' scores per clip and transition and frame count (crowdbake.stages.impostor_probe). For every
budget, crowdbake.bake.impostor_allocation.allocate splits the frames as a bake at that budget would, and the
table gives the MiB it stores and the probes' SSIM between baked frames: the worst range and the mean over
ranges. No baking: the scores are the ones the bake measured. Then the bundle as baked: its tile, azimuths
and frames, and per range crowdview's shader halfway between views and frames against the mesh (the
bundle's fidelity.json `runtime.ranges`), which also counts what the views lose. Prints tables, writes
JSON and the plot.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "services"))

from crowdbake.bake import impostor_allocation  # noqa: E402
from crowdbake.formats.ranges import read_ranges  # noqa: E402

MIB = 1024 * 1024


def budget_curve(bundle: Path, budgets: list[float]) -> dict:
    """Per budget (MiB) the allocation's MiB, worst and mean probe score, and frames per range."""
    manifest = json.loads((bundle / "manifest.json").read_text())
    memory = json.loads((bundle / "texture_memory.json").read_text())
    account = memory["impostor"]["budget"].get("allocation")
    if account is None:
        raise SystemExit(f"bench_archetype_budget: {bundle} was not baked with an archetype budget (no impostor.budget.allocation)")
    ranges = read_ranges(manifest)
    # As the bake: the probed counts, and those between interpolated (impostor_allocation.interpolated).
    ladders = impostor_allocation.ladders(ranges, memory["impostor"]["budget"]["asked"]["frames"])
    scores = [impostor_allocation.interpolated({int(n): float(s) for n, s in entry["probed"].items()}, ladder)
              for entry, ladder in zip(account["ranges"], ladders)]
    frame_bytes = account["frame_mib"] * MIB

    def row(budget: float) -> dict:
        chosen = impostor_allocation.allocate(ranges, scores, frame_bytes, budget * MIB)
        return {"budget_mib": budget, "mib": chosen.bytes / MIB, "fits": chosen.fits, "worst": min(chosen.scores),
                "mean": sum(chosen.scores) / len(chosen.scores),
                "frames": {entry["name"]: len(frames) for entry, frames in zip(account["ranges"], chosen.frames)}}

    return {"bundle": str(bundle), "baked": row(account["budget_mib"]), "curve": [row(budget) for budget in budgets]}


def baked_fidelity(bundle: Path) -> dict:
    """The bundle's chosen layout and, per range, crowdview's SSIM at baked views and halfway between views
    and frames (mean over the cameras), with the worst range and the mean over ranges of the latter."""
    memory = json.loads((bundle / "texture_memory.json").read_text())
    ranges = json.loads((bundle / "fidelity.json").read_text())["runtime"].get("ranges") or []
    between = {entry["name"]: round(entry["between_views"]["ssim_mean"], 4) for entry in ranges}
    return {"chosen": memory["impostor"]["budget"]["chosen"],
            "at_views": {entry["name"]: round(entry["at_views"]["ssim_mean"], 4) for entry in ranges},
            "between": between, "worst": min(between.values(), default=None),
            "mean": sum(between.values()) / len(between) if between else None}


def plot(results: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 4))
    for label, result in results.items():
        curve = result["curve"]
        line, = axis.plot([r["mib"] for r in curve], [r["mean"] for r in curve], marker="o", label=f"{label}: mean of ranges")
        axis.plot([r["mib"] for r in curve], [r["worst"] for r in curve], marker="v", linestyle="--", color=line.get_color(),
                  label=f"{label}: worst range")
        axis.scatter([result["baked"]["mib"]], [result["baked"]["mean"]], s=140, facecolors="none", edgecolors=line.get_color())
        baked = result.get("as_baked") or {}
        if baked.get("mean") is not None:  # what the views lose too: crowdview between views and frames
            axis.scatter([result["baked"]["mib"]] * 2, [baked["mean"], baked["worst"]], marker="x", color=line.get_color(),
                         label=f"{label} as baked, between views and frames: mean, worst")
    axis.axvline(32, color="grey", linewidth=0.8)
    axis.set_xlabel("impostor maps, MiB (every clip and transition)")
    axis.set_ylabel("SSIM against the mesh (lines: probes between baked frames)")
    axis.set_title("One impostor budget per archetype: memory against fidelity")
    axis.legend(fontsize=7)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bundles", nargs="+", metavar="LABEL=BUNDLE")
    parser.add_argument("--budgets", default="8,12,16,24,32,40,48,64")
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--out", type=Path, default=Path("out/bench/archetype_budget.json"))
    args = parser.parse_args()
    budgets = [float(b) for b in args.budgets.split(",")]
    results = {}
    for item in args.bundles:
        label, _, path = item.partition("=")
        if not path:
            raise SystemExit(f"bench_archetype_budget: {item!r} is not LABEL=BUNDLE")
        results[label] = budget_curve(Path(path), budgets)
        results[label]["as_baked"] = baked_fidelity(Path(path))
    print(f"{'archetype':<16}{'budget':>8}{'MiB':>8}{'worst':>8}{'mean':>8}  frames per range")
    for label, result in results.items():
        for row in result["curve"]:
            frames = ", ".join(f"{name} {n}" for name, n in row["frames"].items())
            print(f"{label:<16}{row['budget_mib']:>8g}{row['mib']:>8.1f}{row['worst']:>8.3f}{row['mean']:>8.3f}  {frames}")
    print("\nas baked: crowdview's shader halfway between views and frames, per range (fidelity.json)")
    for label, result in results.items():
        baked = result["as_baked"]
        if baked["worst"] is None:
            continue
        chosen = baked["chosen"]
        frames = chosen["frames"] if isinstance(chosen["frames"], int) else sum(chosen["frames"])
        ranges = ", ".join(f"{name} {ssim:.3f}" for name, ssim in baked["between"].items())
        print(f"{label:<16}{chosen['tile']}² x {chosen['azimuths']} azimuths x {frames} frames: worst {baked['worst']:.3f}, "
              f"mean {baked['mean']:.3f} ({ranges})")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))
    if args.plot:
        plot(results, args.plot)
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
