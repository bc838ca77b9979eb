"""The cycle search's report, for a person to read: report.html and its pictures.

    report.html     the chosen cycle, every candidate's scores, the closing and its quality bounds
      pass1.png       the pass-1 distance curve with the candidates marked
      edges.png       the winner's pictures and Canny edges at Fs and Fe from every view
      seam.png        penetrating vertices per frame before/after closing, and the seam ratios
      candidates.png  every candidate's pass-1 and pass-2 scores
    edges/          the winner's pictures and edge images, one PNG per view and frame

crowdbake.stages.cycle_job writes cycle.json and the looped cache and calls these. Plots with matplotlib
(Agg), edge images with OpenCV. The report of a timeline's clips, a section per loop and per transition,
is crowdbake.stages.clips_report.
"""
from __future__ import annotations

import html
import os
from pathlib import Path

import numpy as np

from crowdbake.bake.cycle import CycleResult


def write_cycle_plots(result: CycleResult, out_dir: str | os.PathLike, prefix: str = "",
                      searched: tuple[int, int] | None = None) -> None:
    """The report's plots: pass1.png, seam.png, candidates.png and, after pass 2, edges.png, each name
    after `prefix` (a several-clip report draws every loop's beside report.html). searched: the cache frames
    [first, end) the search ran over (a clip's stretch), which pass 1's plot spans; None: the whole cache."""
    out = Path(out_dir)
    _plot_pass1(result, out / f"{prefix}pass1.png", searched or (0, result.frame_count))
    _plot_seam(result, out / f"{prefix}seam.png")
    _plot_candidates(result, out / f"{prefix}candidates.png")
    if result.winner_images is not None and result.winner_edges is not None:
        _plot_edges(result, out / f"{prefix}edges.png")


# --- plots -------------------------------------------------------------------------------------------

def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # no display on workers
    import matplotlib.pyplot as plt

    return plt


def _plot_pass1(result: CycleResult, path: Path, searched: tuple[int, int]) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=100)
    for curve in result.curves:
        ax.plot(curve.start_frames, curve.distances, lw=1.2, label=f"gap {curve.gap} frames ({curve.cycle_count} cycle{'s' if curve.cycle_count > 1 else ''})")
    ax.axvspan(searched[0], result.settle_frames, color="0.9", label="settle-in")
    for rank, candidate in enumerate(result.candidates):
        chosen = rank == result.chosen
        ax.plot(candidate.start_frame, candidate.vertex_distance, "o" if not chosen else "*",
                ms=7 if not chosen else 14, color="tab:red" if chosen else "tab:orange", zorder=3)
        ax.annotate(str(rank + 1), (candidate.start_frame, candidate.vertex_distance), textcoords="offset points", xytext=(0, 7), ha="center", fontsize=8)
    if result.params.threshold is not None:
        ax.axhline(result.params.threshold, ls="--", color="0.4", lw=1, label="threshold")
    ax.set_xlabel("start frame Fs")
    ax.set_ylabel("vertex distance D (cache units)")
    ax.set_title("Pass 1: windowed position + velocity distance to Fs + gap (candidates numbered, winner starred)")
    ax.set_xlim(*searched)
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _edge_overlay(edges_start: np.ndarray, edges_end: np.ndarray) -> np.ndarray:
    """RGB image: Fs-only edges red, Fe-only edges cyan, shared edges white."""
    overlay = np.zeros((*edges_start.shape, 3), dtype=np.uint8)
    overlay[edges_start] = (255, 60, 60)
    overlay[edges_end] = (60, 220, 255)
    overlay[edges_start & edges_end] = (255, 255, 255)
    return overlay


def _plot_edges(result: CycleResult, path: Path) -> None:
    plt = _pyplot()
    images, edges = result.winner_images, result.winner_edges
    views = images.shape[1]
    fig, axes = plt.subplots(4, views, figsize=(2.2 * views, 9.2), dpi=100, squeeze=False)
    rows = [
        (f"Fs = {result.start_frame}", lambda j: images[0, j], "gray"),
        (f"Fe = {result.end_frame}", lambda j: images[1, j], "gray"),
        ("edges at Fs", lambda j: edges.edges_start[j], "gray"),
        ("Fs red / Fe cyan", lambda j: _edge_overlay(edges.edges_start[j], edges.edges_end[j]), None),
    ]
    for i, (label, picture, cmap) in enumerate(rows):
        for j in range(views):
            ax = axes[i, j]
            ax.imshow(picture(j), cmap=cmap, vmin=0, vmax=255 if i < 2 else 1, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"view {j + 1}: {edges.per_view[j]:.2f} px", fontsize=9)
            if j == 0:
                ax.set_ylabel(label, fontsize=9)
    fig.suptitle(f"Pass 2: the winner's edge distance {edges.total:.2f} px (sum over {views} views)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_edge_images(result: CycleResult, folder: Path) -> dict[str, Path]:
    """The winner's pictures and Canny edges at Fs and Fe, one PNG per view and frame, into `folder`."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    written = {}
    for j in range(result.winner_images.shape[1]):
        for label, picture in (
            ("fs", result.winner_images[0, j]),
            ("fe", result.winner_images[1, j]),
            ("fs_edges", result.winner_edges.edges_start[j].astype(np.uint8) * 255),
            ("fe_edges", result.winner_edges.edges_end[j].astype(np.uint8) * 255),
        ):
            path = folder / f"view{j + 1}_{label}.png"
            if not cv2.imwrite(str(path), picture):
                raise OSError(f"could not write {path}")
            written[f"edges_view{j + 1}_{label}"] = path
    return written


def _plot_seam(result: CycleResult, path: Path) -> None:
    plt = _pyplot()
    closing = result.closing
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6), dpi=100, gridspec_kw={"width_ratios": [2, 1]})
    frames = np.arange(result.cycle_frames)
    left.plot(frames, closing.penetrating_before, label="raw cycle", lw=1.5)
    left.plot(frames, closing.penetrating_closed, label=f"after '{closing.method}' closing", lw=1.2, ls="--")
    left.plot(frames, closing.penetrating_after, label=f"after push-out ({closing.push_out})", lw=1.2)
    left.set_xlabel("frame of the loop")
    left.set_ylabel("cloth vertices inside the body")
    left.set_title("Penetration per frame")
    left.legend(fontsize=8)
    names = ["position jump", "velocity jump", "max step"]
    before = [closing.seam_before.position_jump_ratio, closing.seam_before.velocity_jump_ratio, closing.seam_before.max_step_ratio]
    after = [closing.seam_after.position_jump_ratio, closing.seam_after.velocity_jump_ratio, closing.seam_after.max_step_ratio]
    x = np.arange(len(names))
    right.bar(x - 0.2, np.nan_to_num(before, posinf=0), 0.4, label="raw")
    right.bar(x + 0.2, np.nan_to_num(after, posinf=0), 0.4, label=closing.method)
    right.set_xticks(x, names, fontsize=8)
    right.set_ylabel("ratio to the median frame step")
    right.set_title("Seam")
    right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plot_candidates(result: CycleResult, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4), dpi=100)
    has_edges = all(c.edge_distance is not None for c in result.candidates)
    xs = [c.vertex_distance for c in result.candidates]
    ys = [c.edge_distance if has_edges else 0.0 for c in result.candidates]
    ax.scatter(xs, ys, c=["tab:red" if i == result.chosen else "tab:blue" for i in range(len(xs))])
    for i, c in enumerate(result.candidates):
        ax.annotate(f"Fs={c.start_frame}", (xs[i], ys[i]), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("pass 1: vertex distance (cache units)")
    ax.set_ylabel("pass 2: edge distance (px)" if has_edges else "pass 2 not run")
    ax.set_title("Candidates (winner in red)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# --- html ----------------------------------------------------------------------------------------------

def _number(value, digits: int = 4) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return html.escape(str(value))


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_number(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


_QUALITY_ROWS = (
    ("stretch_ratio", "stretch ratio", "mean edge strain of the loop ÷ that of the simulator's frames"),
    ("deviation_ratio", "deviation ratio", "largest per-frame RMS distance from the simulator's frame ÷ the raw seam jump"),
    ("seam_acceleration_ratio", "seam acceleration ratio",
     "acceleration at the wrap ÷ the larger of the loop's median and the simulator's own there"),
)


def _quality_html(quality: dict | None, method: str, heading: str = "h2") -> str:
    """The loop-quality section under a `heading` element: a table of the bounded ratios, and a loud
    banner when a bound is broken."""
    if quality is None:
        return ""
    rows = [
        [label, quality[name], quality["bounds"][name], "OVER" if name in quality["exceeded"] else "ok", meaning]
        for name, label, meaning in _QUALITY_ROWS
    ]
    table = _table(["figure", "value", "bound", "", "what it measures"], rows)
    if quality["exceeded"]:
        broken = ", ".join(html.escape(name.replace("_", " ")) for name in quality["exceeded"])
        banner = (
            f'<p class="warning"><b>WARNING: the {html.escape(method)} closing breaks its quality bounds ({broken}).</b> '
            "The loop strays from the simulation: look at it before shipping, or close it another way.</p>"
        )
    else:
        banner = f'<p class="ok">The {html.escape(method)} closing keeps within every quality bound.</p>'
    return f"<{heading}>Loop quality against the simulation</{heading}>{banner}{table}<p>{html.escape(quality.get('seam_acceleration_note', ''))}</p>"


def report_html(result: CycleResult, document: dict) -> str:
    """report.html of one clip: the chosen cycle, the closing and its quality bounds, the plots and the
    candidates (a timeline's clips: crowdbake.stages.clips_report)."""
    closing = result.closing
    candidates = _table(
        ["rank", "Fs", "Fe", "cycles", "vertex distance", "edge distance (px)", "chosen"],
        [
            [i + 1, c.start_frame, c.end_frame, c.cycle_count, c.vertex_distance, c.edge_distance, "✔" if i == result.chosen else ""]
            for i, c in enumerate(result.candidates)
        ],
    )
    seam = _table(
        ["", "position jump ratio", "velocity jump ratio", "max step ratio", "median step", "penetrating vertex-frames"],
        [
            ["raw cycle", closing.seam_before.position_jump_ratio, closing.seam_before.velocity_jump_ratio,
             closing.seam_before.max_step_ratio, closing.seam_before.median_step, int(closing.penetrating_before.sum())],
            [f"after {closing.method}", closing.seam_after.position_jump_ratio, closing.seam_after.velocity_jump_ratio,
             closing.seam_after.max_step_ratio, closing.seam_after.median_step, int(closing.penetrating_after.sum())],
        ],
    )
    quality = _quality_html(document["closing"].get("quality"), closing.method)
    params = _table(["parameter", "value"], [[k, v] for k, v in document["parameters"].items()])
    files = document.get("files", {})
    figures = "".join(
        f'<figure><img src="{html.escape(files[name])}" alt="{html.escape(caption)}"><figcaption>{html.escape(caption)}</figcaption></figure>'
        for name, caption in (
            ("pass1_plot", "Pass 1: vertex distance per start frame; candidates numbered, the winner starred."),
            ("edges_plot", "Pass 2: the winner at Fs and Fe from every view, with their Canny edges."),
            ("candidates_plot", "Every candidate's pass-1 and pass-2 scores."),
            ("seam_plot", "Penetration per frame before and after closing, and the seam ratios."),
        )
        if name in files
    )
    root = ""
    if document.get("root_motion"):
        root = f"<p>The character travels: the search and the loop are in the root's frame (root offset per loop {document['root_motion']['offset_per_loop']}).</p>"
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Cycle search: frames {result.start_frame}–{result.end_frame}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; max-width: 1100px; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1.5em; }}
td, th {{ border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }}
.warning {{ background: #fdd; border: 3px solid #c00; padding: 0.6em 1em; font-size: 1.2em; }}
.ok {{ background: #dfd; border: 1px solid #393; padding: 0.4em 1em; }}
figure {{ margin: 1em 0; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
</style></head><body>
<h1>Cyclical cloth: frames {result.start_frame} to {result.end_frame}</h1>
<p>The loop is {result.cycle_frames} frames ({result.cycle_count} walk cycle{'s' if result.cycle_count > 1 else ''} of
{result.walk_cycle_frames}) out of a cache of {result.frame_count} frames × {result.vertex_count} cloth vertices.
It was chosen by {document['selected_by'].replace('_', ' ')} among {len(result.candidates)} candidates and closed with
<b>{html.escape(closing.method)}</b>{f' over {closing.blend_frames} frames' if closing.blend_frames else ''}.
The push-out moved {closing.pushed_vertices} vertex-frames.</p>
{root}
<h2>Candidates</h2>{candidates}
{quality}
<h2>Seam</h2>
<p>Ratios are relative to the cycle's median frame-to-frame step: a position jump ratio of 1 means the seam jumps as far as a typical frame moves.</p>
{seam}
<h2>Figures</h2>{figures}
<h2>Parameters</h2>{params}
</body></html>
"""


def clips_report_html(document: dict) -> str:
    """The report's section on every clip loop and transition, with their quality figures (empty for one clip)."""
    if not document.get("clips"):
        return ""

    def figures(quality: dict | None) -> str:
        if quality is None:
            return "<td>–</td><td>–</td><td>–</td><td>–</td>"
        cells = "".join(f"<td>{_shown(quality.get(name))}</td>" for name in ("stretch_ratio", "deviation_ratio", "seam_acceleration_ratio"))
        verdict = "ok" if quality["within_bounds"] else "OVER: " + ", ".join(quality["exceeded"])
        return cells + f"<td>{html.escape(verdict)}</td>"

    head = "<th>stretch</th><th>deviation</th><th>seam acc.</th><th>bounds</th>"

    def pose_frames(entry: dict) -> str:  # the bundle's pose frames [first, end) of a range (several clips only)
        span = entry.get("pose_frames")
        return "<td>–</td>" if span is None else f"<td>{span[0]}–{span[1] - 1}</td>"

    loops = "".join(
        f"<tr><td>{html.escape(c['clip'])}</td><td>{c['period']}</td><td>{c['start_frame']}–{c['end_frame']}</td>"
        f"{pose_frames(c)}<td>{c['segment']}</td>{figures(c['closing'].get('quality'))}</tr>"
        for c in document["clips"]
    )
    moves = "".join(
        f"<tr><td>{html.escape(t['from_clip'])} → {html.escape(t['to_clip'])}</td><td>{t['leave_loop_frame']}</td>"
        f"<td>{t['arrive_loop_frame']}</td><td>{t['frames']}</td><td>{t['source_frames'][0]}–{t['source_frames'][1]}</td>"
        f"{pose_frames(t)}<td>leave</td>{figures(t['leave']['quality'])}</tr>"
        f"<tr><td></td><td></td><td></td><td></td><td></td><td></td><td>arrive</td>{figures(t['arrive']['quality'])}</tr>"
        for t in document["transitions"]
    )
    bounds = document["clips"][0]["closing"].get("quality") or {}
    if "bundle_ranges" in document:
        carried = (f"The bundle carries every loop and transition: {document['bundle_ranges']['pose_frames']} pose frames, "
                   "each range's shown below (format v2).")
    else:
        carried = f"The bundle carries {html.escape(document.get('primary_clip', ''))}."
    if not document["transitions"] and any(s.get("new_simulation") for s in document.get("timeline", {}).get("segments", [])):
        carried += " The clips were simulated apart (one cache per clip): no transitions, as no simulation joined them."
    limits = ", ".join(f"{name.replace('_', ' ')} ≤ {value:g}" for name, value in (bounds.get("bounds") or {}).items())
    return (
        f"<h2>Clips: a loop each</h2><p>{carried} Bounds: {html.escape(limits)}.</p>"
        f"<table><thead><tr><th>clip</th><th>period</th><th>cache frames</th><th>pose frames</th><th>segment</th>{head}</tr></thead><tbody>{loops}</tbody></table>"
        "<h2>Transitions taken from the simulation</h2><p>Playback leaves loop A before its frame <i>leave</i>, plays the "
        "transition's frames, and goes on with loop B's frame <i>arrive</i>; each join is crossfaded like a loop's seam.</p>"
        f"<table><thead><tr><th>change</th><th>leave</th><th>arrive</th><th>frames</th><th>cache frames</th><th>pose frames</th><th>join</th>{head}</tr></thead>"
        f"<tbody>{moves}</tbody></table>"
    )


def _shown(value) -> str:
    return "–" if value is None else f"{value:.3g}"
