"""The paper's figures 3 and 4, and the service's bake throughput, plotted from this project's own runs.

    PYTHONPATH=services python services/benchmarks/plot_figures.py [--bench out/bench] [--bundle DIR] [--out docs/img]

Reads what the benchmark scripts wrote under --bench and writes PNGs under --out:

- figure3.png: humans at 30 fps per representation, from crowdview's `--benchmark --report` JSON
  (any *.json under --bench holding `results` with `n_at_30fps`; one bar group per report), next to
  the paper's numbers (Dobbyn et al. 2006, section 6: 90 high-resolution meshes, 655 low-resolution,
  about 6,600 UV-mapped impostors, 6,000 in the hybrid; detail-mapped impostors "higher", no number).
- figure4.png: texture memory against texture variations, detail-mapped and UV-mapped impostors, for
  the paper's assumptions (crowdbake.bake.texture_memory.paper_map_bytes) and, with --bundle, for the
  layer sizes of a real bundle (its texture_memory.json, written by the pack stage).
- throughput.png: bakes per minute with 1 and 2 workers, from bench_throughput.py's JSON.
- bake_stages.png: per stage of a default bake, wall, CPU and OpenGL seconds, from bench_bake.py's JSON
  (bake.json; with bake-before.json beside it, that run's CPU seconds too, for a before/after).
- impostor_views.png: crowdview's blended impostor against the mesh (SSIM halfway between views and
  frames, and at the baked views) against the impostor's memory, per tile size and view/frame count,
  from bench_impostor_views.py's impostor_views.json.

A figure whose input is missing is not drawn (and any old PNG of it is left alone); each one drawn is
listed with the file it came from.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

SERVICES_DIR = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(SERVICES_DIR))

from crowdbake.bake import texture_memory  # noqa: E402

# Section 6 of the paper: humans displayed at 30 fps (figure 3). The detail-mapped impostor count is
# only said to be higher than the UV-mapped one.
PAPER_FIGURE3 = {"high_mesh": 90, "low_mesh": 655, "uv_impostor": 6600, "hybrid": 6000}
MODE_LABELS = {"high_mesh": "high mesh", "low_mesh": "low mesh", "uv_impostor": "UV impostor",
               "detail_impostor": "detail impostor", "hybrid": "hybrid"}
MAX_VARIATIONS = 16  # twice the paper's 8 diffuse textures (figure 2b), as the pack stage's figure-4 series


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def load_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def crowdview_reports(bench: Path) -> list[tuple[Path, dict]]:
    found = []
    for path in sorted(bench.glob("*.json")):
        document = load_json(path)
        if isinstance(document, dict) and isinstance(document.get("results"), dict) and any(
            isinstance(entry, dict) and "n_at_30fps" in entry for entry in document["results"].values()
        ):
            found.append((path, document))
    return found


def plot_figure3(reports: list[tuple[Path, dict]], out: Path) -> None:
    import numpy as np

    plt = pyplot()
    modes = [mode for mode in MODE_LABELS if any(mode in report["results"] for _, report in reports) or mode in PAPER_FIGURE3]
    series = [("paper: ATI Radeon X850 XT, Pentium 4 (2006)", [PAPER_FIGURE3.get(mode) for mode in modes], [True] * len(modes))]
    for path, report in reports:
        entries = [report["results"].get(mode, {}) for mode in modes]
        counts = [entry.get("n_at_30fps") for entry in entries]
        converged = [bool(entry.get("converged_30", True)) for entry in entries]
        device = re.split(r"[,(]", str(report.get("device", "?")).split(": ", 1)[-1])[0].strip()
        series.append((f"{path.stem}: {report.get('bundle', '?')} on {device}, {report.get('cpu_threads', '?')} CPU threads, "
                       f"load {report.get('load_average_1min_start', '?')}", counts, converged))
    fig, ax = plt.subplots(figsize=(10, 5.6), dpi=110)
    width = 0.8 / len(series)
    x = np.arange(len(modes))
    for k, (label, counts, converged) in enumerate(series):
        positions = x + (k - (len(series) - 1) / 2) * width
        heights = [count if count else 0 for count in counts]
        bars = ax.bar(positions, heights, width, label=label)
        for bar, count, done in zip(bars, counts, converged):
            if count:
                text = f"{count:,}" + ("" if done else "+")
                ax.annotate(text, (bar.get_x() + bar.get_width() / 2, count), ha="center", va="bottom", fontsize=7, xytext=(0, 2),
                            textcoords="offset points")
    ax.set_yscale("log")
    ax.set_xticks(x, [MODE_LABELS[mode] for mode in modes])
    ax.set_ylabel("humans at 30 fps (log scale)")
    ax.set_title("Figure 3: humans displayed at 30 fps per representation (+: lower bound, time budget hit)")
    ax.set_ylim(top=ax.get_ylim()[1] * 1.6)  # room for the labels over the tallest bars
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=1, frameon=False)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def plot_figure4(bundle_report: dict | None, bundle_label: str, out: Path) -> dict:
    """Returns the plotted series (MiB), for the caption."""
    plt = pyplot()
    paper = texture_memory.series(texture_memory.paper_map_bytes(), MAX_VARIATIONS)
    fig, ax = plt.subplots(figsize=(8, 4.6), dpi=110)
    n = paper["variations"]
    ax.plot(n, paper["detail_mapped_mib"], "o-", color="tab:red", label="detail-mapped impostor, paper's assumptions")
    ax.plot(n, paper["uv_mapped_mib"], "o-", color="tab:blue", label="UV-mapped impostor, paper's assumptions")
    plotted = {"paper": paper}
    if bundle_report is not None:
        bundle = bundle_report["bundle"]
        held = bundle.get("variations_in_bundle")
        ax.plot(bundle["variations"], bundle["detail_mapped_mib"], "s--", color="tab:red", alpha=0.6, ms=4,
                label=f"detail-mapped, {bundle_label}")
        ax.plot(bundle["variations"], bundle["uv_mapped_mib"], "s--", color="tab:blue", alpha=0.6, ms=4,
                label=f"UV-mapped ({bundle['map_bytes']['uv'] / 2**20:.0f} MiB of UV maps, break-even "
                      f"{bundle['break_even_variations']:g}), {bundle_label}")
        if held:
            ax.axvline(held, color="0.5", lw=0.8, ls=":")
            ax.annotate(f" {held} variations in the bundle", (held, ax.get_ylim()[0]), fontsize=8, ha="right", va="bottom", rotation=90)
        plotted["bundle"] = bundle
    ax.set_xlabel("texture variations (diffuse textures) per character")
    ax.set_ylabel("texture memory (MiB)")
    ax.set_title("Figure 4: texture memory of one clothed character")
    ax.set_xticks(n)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return plotted


def plot_throughput(report: dict, out: Path) -> None:
    plt = pyplot()
    runs = report["runs"]
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    labels = [f"{run['workers']} worker{'s' if run['workers'] > 1 else ''}" for run in runs]
    rates = [run["bakes_per_minute"] for run in runs]
    bars = ax.bar(labels, rates, color="tab:green")
    for bar, run in zip(bars, runs):
        ax.annotate(f"{run['bakes_per_minute']:.2f}/min\n({run['bakes']} bakes in {run['seconds']:.0f} s)",
                    (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom", fontsize=8,
                    xytext=(0, 2), textcoords="offset points")
    ratio = report.get("ratio_2_to_1")
    title = "Bake throughput" + (f": 2 workers / 1 = {ratio:.2f}x" if ratio else "")
    ax.set_title(f"{title}\n({report['machine']['cpus']} CPUs, {report['broker']} broker, small bakes)", fontsize=10)
    ax.set_ylabel("bakes per minute")
    ax.set_ylim(0, max(rates) * 1.3)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def plot_bake_stages(report: dict, before: dict | None, out: Path) -> None:
    """One panel per case: grouped bars per stage (wall, CPU, render; CPU before when given)."""
    plt = pyplot()
    cases = report["cases"]
    earlier = {case["case"]: case for case in (before or {}).get("cases", [])}
    fig, axes = plt.subplots(1, len(cases), figsize=(6 * len(cases), 4.2), dpi=110, squeeze=False)
    for ax, case in zip(axes[0], cases):
        stages = list(case["stages"])
        series = [("wall", "wall_s", "tab:blue"), ("CPU", "cpu_s", "tab:orange"), ("in OpenGL", "render_s", "tab:green")]
        if case["case"] in earlier:
            series.append(("CPU before", "cpu_before", "tab:gray"))
        width = 0.8 / len(series)
        for k, (label, key, colour) in enumerate(series):
            if key == "cpu_before":
                values = [earlier[case["case"]]["stages"].get(stage, {}).get("cpu_s", 0.0) for stage in stages]
            else:
                values = [case["stages"][stage][key] for stage in stages]
            ax.bar([i + (k - (len(series) - 1) / 2) * width for i in range(len(stages))], values, width, label=label, color=colour)
        timings = case["timings"]
        ax.set_xticks(range(len(stages)), stages, fontsize=8)
        ax.set_ylabel("seconds")
        ax.set_title(f"{case['case']}: {timings['wall_s']:.1f} s wall, {timings['cpu_s']:.1f} s CPU, "
                     f"{timings['render_s']:.1f} s OpenGL\n({timings.get('workers', 1)} worker processes; poses and impostors overlap)", fontsize=9)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def plot_impostor_views(report: dict, out: Path) -> None:
    plt = pyplot()
    rows = report["rows"]
    fig, ax = plt.subplots(figsize=(9, 5.2), dpi=110)
    colours = {32: "tab:green", 64: "tab:orange", 128: "tab:blue"}
    for tile in sorted({row["tile"] for row in rows}):
        chosen = sorted((row for row in rows if row["tile"] == tile), key=lambda row: row["impostor_mib"]["uvblock"])
        colour = colours.get(tile, "0.4")
        ax.scatter([row["impostor_mib"]["uvblock"] for row in chosen], [row["between_ssim_mean"] for row in chosen], color=colour,
                   s=18, label=f"tile {tile}: halfway between views and frames")
        ax.axhline(chosen[0]["at_views_ssim_mean"], color=colour, lw=0.8, ls=":", label=f"tile {tile}: at the baked views")
        for row in chosen:
            if row["azimuths"] >= 16 and row["frames"] >= 10:
                ax.annotate(f"{row['azimuths']}x{len(row['elevations'])}x{row['frames']}",
                            (row["impostor_mib"]["uvblock"], row["between_ssim_mean"]), fontsize=6, xytext=(3, -3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("UV-mapped impostor memory per character (MiB: bc1 normal + uvblock UV maps)")
    ax.set_ylabel("SSIM against the mesh at the 1:1 switch")
    ax.set_title("Impostor views against memory (labels: azimuths x elevation rings x baked frames)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bench", type=Path, default=Path("out/bench"), help="folder of the benchmarks' JSON (default out/bench)")
    parser.add_argument("--bundle", type=Path, help="a baked bundle folder whose texture_memory.json figure 4 also plots")
    parser.add_argument("--out", type=Path, default=Path("docs/img"), help="folder for the PNGs (default docs/img)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    reports = crowdview_reports(args.bench)
    if reports:
        plot_figure3(reports, args.out / "figure3.png")
        print(f"figure3.png from {', '.join(str(path) for path, _ in reports)}")
    else:
        print(f"figure3.png not drawn: no crowdview --benchmark report under {args.bench}")

    bundle_report = None
    label = ""
    if args.bundle is not None:
        bundle_report = load_json(args.bundle / "texture_memory.json")
        if bundle_report is None:
            print(f"{args.bundle}/texture_memory.json is missing or unreadable", file=sys.stderr)
            return 1
        manifest = load_json(args.bundle / "manifest.json") or {}
        impostor = manifest.get("impostor", {})
        label = (f"{manifest.get('name', args.bundle.name)} ({len(impostor.get('frame_indices', []))} frames of "
                 f"{impostor.get('tile_size', 0) * len(impostor.get('azimuths_deg', []))}x"
                 f"{impostor.get('tile_size', 0) * len(impostor.get('elevations_deg', []))})")
    plotted = plot_figure4(bundle_report, label, args.out / "figure4.png")
    paper = plotted["paper"]
    print(f"figure4.png: paper model {paper['detail_mapped_mib'][0]:.0f}/{paper['uv_mapped_mib'][0]:.0f} MiB at 1 variation, "
          f"{paper['detail_mapped_mib'][7]:.0f}/{paper['uv_mapped_mib'][7]:.0f} MiB at 8 (detail/UV)"
          + (f"; bundle {args.bundle}" if bundle_report else ""))

    bake = load_json(args.bench / "bake.json")
    if bake and bake.get("cases"):
        plot_bake_stages(bake, load_json(args.bench / "bake-before.json"), args.out / "bake_stages.png")
        print(f"bake_stages.png from {args.bench / 'bake.json'}")
    else:
        print(f"bake_stages.png not drawn: no {args.bench / 'bake.json'}")

    views = load_json(args.bench / "impostor_views.json")
    if views and views.get("rows"):
        plot_impostor_views(views, args.out / "impostor_views.png")
        print(f"impostor_views.png from {args.bench / 'impostor_views.json'}")
    else:
        print(f"impostor_views.png not drawn: no {args.bench / 'impostor_views.json'}")

    throughput = load_json(args.bench / "throughput.json")
    if throughput and throughput.get("runs"):
        plot_throughput(throughput, args.out / "throughput.png")
        print(f"throughput.png from {args.bench / 'throughput.json'}")
    else:
        print(f"throughput.png not drawn: no {args.bench / 'throughput.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
