"""The cycle search's file side: read the inputs, run crowdbake.bake.cycle.find_cycle, write the outputs.

    run_cycle_job(cloth_pc2, cloth_obj, out_dir, character=... | body_pc2=..., body_obj=...) -> CycleResult

writes into out_dir:
    cycle.json      the chosen cycle, every candidate's scores, the closing and seam figures, every parameter
    looped.pc2      the looped cloth cache: exactly cycle_frames frames, frame 0 = Fs
    report.html     a page a person can read, with PNG plots:
      pass1.png       the pass-1 distance curve with the candidates marked
      edges.png       the winner's pictures and Canny edges at Fs and Fe from every view
      seam.png        penetrating vertices per frame before/after closing, and the seam ratios
      candidates.png  every candidate's pass-1 and pass-2 scores
    edges/          the winner's pictures and edge images, one PNG per view and frame

Frame rate (crowdbake.params.cache_fps): `fps` when the caller passes it, else the cache's own (MDD frame
times, Alembic time sampling), else BASE_FPS / sample_rate with BASE_FPS = 24 (the film rate the sample
content and most DCC scenes use): a PC2 file stores the interval between samples in frames, not a rate. The cycle length, when not given, is the character's animation
duration times that rate.
"""
from __future__ import annotations

import html
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from crowdbake.bake.cycle import CycleParams, CycleResult, find_cycle
from crowdbake.params import BASE_FPS, min_cloth_frames

logger = logging.getLogger(__name__)

# The animation's duration times the frame rate must be this close to a whole number of frames for the
# body to be tiled from one posed cycle; otherwise each frame is posed at its own wrapped time.
_WHOLE_FRAME_TOLERANCE = 1e-3

Progress = Callable[[str, int, int], None]


@dataclass
class CycleInputs:
    """Arrays for find_cycle plus what the files said.

    cloth: (F, V, 3) float32 in PC2 point order; cloth_faces: (T, 3) int64 into those points.
    body: (F, Vb, 3) float32 or None; body_faces (Tb, 3) int64; body_normals (F, Vb, 3) or None.
    cycle_frames: l; fps: the cache's frame rate; sample_rate/start_frame: from the cloth PC2 header.
    """

    cloth: np.ndarray
    cloth_faces: np.ndarray
    body: np.ndarray | None
    body_faces: np.ndarray | None
    body_normals: np.ndarray | None
    cycle_frames: int
    fps: float
    sample_rate: float
    start_frame: float
    cycle_frames_source: str
    sources: dict


def _pose_body(character, fps: float, frame_count: int) -> tuple[np.ndarray, np.ndarray]:
    """The character's looping animation at the cache's frames: frame f at time (f / fps) mod duration."""
    from crowdbake.bake.skinning import pose_character

    duration = float(character.animation_duration)
    if duration <= 0:
        raise ValueError("the character has no animation to pose the body with")
    frames_per_loop = duration * fps
    whole = round(frames_per_loop)
    if whole >= 1 and abs(frames_per_loop - whole) < _WHOLE_FRAME_TOLERANCE:
        positions, normals = pose_character(character, fps, min(whole, frame_count))
        index = np.arange(frame_count) % whole
        return positions[index], normals[index]
    posed = [pose_character(character, fps, 1, start_time=(f / fps) % duration) for f in range(frame_count)]
    return np.concatenate([p for p, _ in posed]), np.concatenate([n for _, n in posed])


def _check_two_cycles(frame_count: int, cycle_frames: int, path) -> None:
    if cycle_frames < 2:
        raise ValueError(f"the cycle length must be at least 2 frames, got {cycle_frames}")
    if frame_count < min_cloth_frames(cycle_frames):
        raise ValueError(
            f"too few frames for two cycles: {path} has {frame_count} frames, two cycles of {cycle_frames} need {min_cloth_frames(cycle_frames)}"
        )


def _pc2_start_frame(path: str | os.PathLike) -> float:
    """A PC2 header's startFrame (recorded in cycle.json); 0 for the other caches, which start at their first sample."""
    import struct

    if Path(path).suffix.lower() != ".pc2":
        return 0.0
    with open(path, "rb") as handle:
        return float(struct.unpack("<f", handle.read(24)[20:24])[0])


def load_cycle_inputs(
    cloth_pc2: str | os.PathLike,
    cloth_obj: str | os.PathLike | None = None,
    character: str | os.PathLike | None = None,
    body_pc2: str | os.PathLike | None = None,
    body_obj: str | os.PathLike | None = None,
    cycle_frames: int | None = None,
    fps: float | None = None,
    up: str | None = None,
    units: str | None = None,
    animation: int | str = 0,
) -> CycleInputs:
    """Read and cross-check the cycle search's input files. Raises ValueError with a one-line reason.

    cloth_pc2: any cloth cache crowdbake reads (.pc2 or .mdd with `cloth_obj`, .abc or an OBJ-sequence
    .zip alone; crowdbake.ingest.garment.read_cloth). fps: None takes the cache's own rate
    (crowdbake.params.cache_fps). The cloth's first frame is checked against the body's
    (crowdbake.ingest.garment.place_cloth) and converted to Y-up metres when up/units say so."""
    from crowdbake.formats.obj import read_obj
    from crowdbake.formats.pc2 import read_pc2
    from crowdbake.ingest.garment import place_cloth, read_cloth
    from crowdbake.params import cache_fps

    if character is not None and (body_pc2 is not None or body_obj is not None):
        raise ValueError("give the body either as a character (.glb) or as a body cache and mesh, not both")
    if (body_pc2 is None) != (body_obj is None):
        raise ValueError("a body cache needs its mesh: give both --body and --body-mesh")
    cache = read_cloth(cloth_pc2, cloth_obj)
    cloth_faces = cache.mesh.source_index[cache.faces.astype(np.int64)]
    frame_rate = cache_fps(fps, cache.fps, cache.frame_step)
    if not frame_rate > 0:
        raise ValueError(f"fps must be positive, got {frame_rate}")
    frame_count = cache.frame_count
    sources = {"cloth_cache": str(cloth_pc2)}
    if cloth_obj is not None:
        sources["cloth_mesh"] = str(cloth_obj)
    if cycle_frames is not None:
        _check_two_cycles(frame_count, int(cycle_frames), cloth_pc2)

    body = body_faces = body_normals = None
    loaded_character = None
    if character is not None:
        from crowdbake.formats.gltf import load_character

        loaded_character = load_character(character, animation=animation)
        # The garment must sit on the character before a minute of search is spent on it.
        from crowdbake.ingest.garment import body_at_rest

        cache = place_cloth(cache, body_at_rest(loaded_character), up, units)
        body, body_normals = _pose_body(loaded_character, frame_rate, frame_count)
        body_faces = np.asarray(loaded_character.faces, dtype=np.int64)
        sources["character"] = str(character)
    elif body_pc2 is not None:
        body_cache = read_pc2(body_pc2)
        body_mesh = read_obj(body_obj)
        if body_mesh.position_count != body_cache.point_count:
            raise ValueError(
                f"vertex counts do not match: {body_obj} has {body_mesh.position_count} positions, {body_pc2} has {body_cache.point_count} points"
            )
        if body_cache.sample_count != frame_count:
            raise ValueError(f"frame counts do not match: {body_pc2} has {body_cache.sample_count} frames, {cloth_pc2} has {frame_count}")
        if len(body_mesh.faces) == 0:
            raise ValueError(f"{body_obj} has no faces")
        body = body_cache.points
        # The body cache is taken as Y-up metres, like a character; up/units convert the cloth only.
        cache = place_cloth(cache, body[0], up, units)
        body_faces = body_mesh.source_index[body_mesh.faces.astype(np.int64)]
        sources.update(body_cache=str(body_pc2), body_mesh=str(body_obj))

    if cycle_frames is not None:
        length, origin = int(cycle_frames), "given"
    elif loaded_character is not None:
        length, origin = int(round(loaded_character.animation_duration * frame_rate)), "character animation"
    else:
        raise ValueError("the cycle length is unknown: give --cycle-frames (a body cache carries no animation length)")
    _check_two_cycles(frame_count, length, cloth_pc2)
    return CycleInputs(
        cloth=cache.frames,
        cloth_faces=cloth_faces,
        body=body,
        body_faces=body_faces,
        body_normals=body_normals,
        cycle_frames=length,
        fps=frame_rate,
        sample_rate=cache.frame_step,
        start_frame=_pc2_start_frame(cloth_pc2),
        cycle_frames_source=origin,
        sources=sources,
    )


def run_cycle_job(
    cloth_pc2: str | os.PathLike,
    cloth_obj: str | os.PathLike,
    out_dir: str | os.PathLike,
    character: str | os.PathLike | None = None,
    body_pc2: str | os.PathLike | None = None,
    body_obj: str | os.PathLike | None = None,
    cycle_frames: int | None = None,
    fps: float | None = None,
    params: CycleParams = CycleParams(),
    up: str | None = None,
    units: str | None = None,
    animation: int | str = 0,
    progress: Progress | None = None,
    edge_pass: bool = True,
    plots: bool = True,
) -> CycleResult:
    """The whole `crowdbake cycle` job: files in, cycle.json + looped.pc2 + report.html out.

    edge_pass: run pass 2 (rendering under OSMesa/EGL); False picks the best pass-1 candidate.
    plots: draw the report's plots now; False leaves them to write_cycle_plots(result, out_dir).
    Raises ValueError on bad input (with a one-line reason).
    """
    report = progress or (lambda stage, done, total: None)
    report("load", 0, 1)
    inputs = load_cycle_inputs(cloth_pc2, cloth_obj, character, body_pc2, body_obj, cycle_frames, fps, up, units, animation)
    report("load", 1, 1)
    render_views = None
    if edge_pass:
        from crowdbake.render.cloth_views import ClothViewRenderer

        render_views = ClothViewRenderer(
            inputs.cloth_faces, inputs.body_faces, params.views, params.image_size, params.elevation_deg
        )
    result = find_cycle(
        inputs.cloth, inputs.cloth_faces, inputs.body, inputs.body_faces, inputs.cycle_frames,
        params, render_views, body_normals=inputs.body_normals, progress=progress,
    )
    report("report", 0, 1)
    write_cycle_outputs(result, out_dir, inputs, plots=plots)
    report("report", 1, 1)
    return result


def write_cycle_outputs(result: CycleResult, out_dir: str | os.PathLike, inputs: CycleInputs | None = None,
                        plots: bool = True) -> dict[str, Path]:
    """Write cycle.json, looped.pc2, the PNG plots, the edge images and report.html; returns the paths.

    plots: False skips the matplotlib plots (a second or more), for write_cycle_plots to draw later (the bake
    runner draws them beside the next stages); every other file, the report's links included, is written."""
    from crowdbake.formats.pc2 import write_pc2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "cycle_json": out / "cycle.json",
        "looped_cache": out / "looped.pc2",
        "report": out / "report.html",
        "pass1_plot": out / "pass1.png",
        "seam_plot": out / "seam.png",
        "candidates_plot": out / "candidates.png",
    }
    sample_rate = inputs.sample_rate if inputs is not None else 1.0
    write_pc2(paths["looped_cache"], result.looped, start_frame=0.0, sample_rate=sample_rate)

    if result.winner_images is not None and result.winner_edges is not None:
        paths["edges_plot"] = out / "edges.png"
        paths.update(_write_edge_images(result, out / "edges"))
    if plots:
        write_cycle_plots(result, out)

    document = result.to_dict()
    document["files"] = {name: path.relative_to(out).as_posix() for name, path in paths.items() if name != "cycle_json"}
    if inputs is not None:
        document["input"].update(
            fps=inputs.fps,
            sample_rate=inputs.sample_rate,
            pc2_start_frame=inputs.start_frame,
            cycle_frames_source=inputs.cycle_frames_source,
            sources=inputs.sources,
        )
    paths["cycle_json"].write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
    paths["report"].write_text(_report_html(result, document), encoding="utf-8")
    logger.info("cycle outputs written to %s", out)
    return paths


def write_cycle_plots(result: CycleResult, out_dir: str | os.PathLike) -> None:
    """The report's plots: pass1.png, seam.png, candidates.png and, after pass 2, edges.png."""
    out = Path(out_dir)
    _plot_pass1(result, out / "pass1.png")
    _plot_seam(result, out / "seam.png")
    _plot_candidates(result, out / "candidates.png")
    if result.winner_images is not None and result.winner_edges is not None:
        _plot_edges(result, out / "edges.png")


# --- plots -------------------------------------------------------------------------------------------

def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # no display on workers
    import matplotlib.pyplot as plt

    return plt


def _plot_pass1(result: CycleResult, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=100)
    for curve in result.curves:
        ax.plot(curve.start_frames, curve.distances, lw=1.2, label=f"gap {curve.gap} frames ({curve.cycle_count} cycle{'s' if curve.cycle_count > 1 else ''})")
    ax.axvspan(0, result.settle_frames, color="0.9", label="settle-in")
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
    ax.set_xlim(0, result.frame_count)
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


def _write_edge_images(result: CycleResult, folder: Path) -> dict[str, Path]:
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


def _quality_html(quality: dict | None, method: str) -> str:
    """The loop-quality section: a table of the bounded ratios, and a loud banner when a bound is broken."""
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
    return f"<h2>Loop quality against the simulation</h2>{banner}{table}<p>{html.escape(quality.get('seam_acceleration_note', ''))}</p>"


def _report_html(result: CycleResult, document: dict) -> str:
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
