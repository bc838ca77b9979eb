"""The cycle report of several clips: a section for every clip's loop and every transition, with their
figures and pictures (crowdbake.stages.cycle_report keeps the one-clip report).

    clip_figures(sections, loops, transitions, cloth) -> ClipFigures   # names each entry's pictures
    ClipFigures.draw(out_dir)                                           # draws them
    clips_report(document) -> report.html's text

Each loop gets the one-clip report's plots (pass 1, pass 2's edges when it ran, the candidates, the seam),
each transition a picture of each join: the cloth's step per frame across it, as playback shows it (loop,
then transition, or back), beside the loop going on alone and the simulation's own frames, with the
crossfade and the switch between the two files marked. A join reads well when the played curve stays
within the other two. Files sit beside report.html with flat names (clip_<clip>_pass1.png,
transition_<k>_<from>_<to>_leave.png), as the service serves the report's pictures.
"""
from __future__ import annotations

import html
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.bake.clips import ClipLoop
from crowdbake.bake.cycle import CycleResult
from crowdbake.bake.transitions import Transition, loop_steps, reference_step
from crowdbake.stages.cycle_report import _number, _pyplot, _quality_html, _table, clips_report_html, write_cycle_plots

# The one-clip report's plots, drawn for each loop: the file each is written to, and its caption.
CLIP_PLOTS = (
    ("pass1", "Pass 1: vertex distance per start frame (cache frames); candidates numbered, the winner starred."),
    ("edges", "Pass 2: the winner at Fs and Fe from every view, with their Canny edges."),
    ("candidates", "Every candidate's pass-1 and pass-2 scores."),
    ("seam", "Penetration per frame before and after closing, and the seam ratios."),
)
# A join's picture shows this many crossfade half-widths either side of the join, at least MIN_JOIN_MARGIN
# frames: the blend and as much unblended motion on each side.
JOIN_MARGIN_WIDTHS = 2
MIN_JOIN_MARGIN = 8


@dataclass(frozen=True)
class JoinSteps:
    """The cloth's step per frame across one join of a transition, for its picture.

    offsets: (n,) int, frames from the join's centre t = 0 (cache frame a or b, loop frame i or j); each
    curve (n,) float64 is the RMS step from t to t + 1 over every cloth vertex, cache units: played (what
    playback shows), loop (the loop going on alone), simulation (the cache's own frames, NaN outside it).
    half_width: h, the crossfade covers t = -h .. h - 1; switch: the t whose step is playback's switch
    between the loop's file and the transition's; reference: the larger of the two loops' median steps."""

    offsets: np.ndarray
    played: np.ndarray
    loop: np.ndarray
    simulation: np.ndarray
    half_width: int
    switch: int
    reference: float


def _steps(frames: np.ndarray) -> np.ndarray:
    """(n - 1,) RMS step between consecutive frames of (n, V, 3)."""
    return np.sqrt(np.mean(np.sum(np.square(np.diff(np.asarray(frames, np.float64), axis=0)), axis=-1), axis=-1))


def _cache_steps(cloth: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """The steps of cloth over the cache frames `frames` (consecutive), NaN where a step leaves the cache."""
    inside = (frames >= 0) & (frames < len(cloth))
    positions = np.full((len(frames), *cloth.shape[1:]), np.nan)
    positions[inside] = cloth[frames[inside]]
    return _steps(positions)


def join_steps(transition: Transition, loop_a: np.ndarray, loop_b: np.ndarray, cloth: np.ndarray) -> tuple[JoinSteps, JoinSteps]:
    """(leave, arrive) step curves of a transition's two joins. loop_a, loop_b: (L, V, 3) the loops it
    joins; cloth: (F, V, 3) the cache it was taken from. Playback: loop A up to its frame i - h - 1, the
    transition's frames (its frame k at t = k - h of the leave join; its last at t = h - 1 of the arrive
    join), loop B from its frame j + h."""
    frames = np.asarray(transition.frames, np.float64)
    n = len(frames)
    reference = reference_step(loop_steps(loop_a), loop_steps(loop_b))

    join = transition.leave
    h, i, a = join.half_width, join.loop_frame, join.cache_frame
    margin = max(JOIN_MARGIN_WIDTHS * h, MIN_JOIN_MARGIN)
    t = np.arange(-h - margin, min(h + margin, n - h - 1) + 1)
    looping = np.asarray(loop_a[(i + t) % len(loop_a)], np.float64)
    played = np.where((t < -h)[:, None, None], looping, frames[np.clip(t + h, 0, n - 1)])
    leave = JoinSteps(t[:-1], _steps(played), _steps(looping), _cache_steps(cloth, a + t), h, -h - 1, reference)

    join = transition.arrive
    h, j, b = join.half_width, join.loop_frame, join.cache_frame
    margin = max(JOIN_MARGIN_WIDTHS * h, MIN_JOIN_MARGIN)
    t = np.arange(max(-h - margin, h - n), h + margin + 1)
    looping = np.asarray(loop_b[(j + t) % len(loop_b)], np.float64)
    played = np.where((t >= h)[:, None, None], looping, frames[np.clip(n - h + t, 0, n - 1)])
    arrive = JoinSteps(t[:-1], _steps(played), _steps(looping), _cache_steps(cloth, b + t), h, h - 1, reference)
    return leave, arrive


def _plot_join(steps: JoinSteps, title: str, loop_label: str, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.0, 3.0), dpi=100)
    h = steps.half_width
    ax.axvspan(-h - 0.5, h - 0.5, color="0.92", label=f"crossfade ({2 * h} frames)")
    ax.plot(steps.offsets, steps.simulation, color="0.55", lw=1.2, label="simulation")
    ax.plot(steps.offsets, steps.loop, color="tab:blue", lw=1.0, ls="--", label=loop_label)
    ax.plot(steps.offsets, steps.played, color="tab:red", lw=1.6, label="played")
    ax.plot([steps.switch], [steps.played[list(steps.offsets).index(steps.switch)]], "o", color="tab:red", ms=6)
    if steps.reference > 0:
        ax.axhline(steps.reference, color="0.3", lw=0.8, ls=":", label="loops' median step")
    ax.set_xlabel("frames from the join (dot: the switch between files)")
    ax.set_ylabel("step per frame (cache units)")
    ax.set_ylim(bottom=0)  # from zero, so that a jump reads against the motion itself
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))  # beside the curves, never over them
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


@dataclass
class ClipFigures:
    """The pictures of a several-clip report, ready to draw: (file prefix, loop result in cache frames, the
    cache frames [first, end) searched) per clip, (file, title, loop label, steps) per join."""

    clips: list[tuple[str, CycleResult, tuple[int, int]]]
    joins: list[tuple[str, str, str, JoinSteps]]

    def draw(self, out_dir: str | os.PathLike) -> None:
        out = Path(out_dir)
        for prefix, result, searched in self.clips:
            write_cycle_plots(result, out, prefix=f"{prefix}_", searched=searched)
        for file, title, loop_label, steps in self.joins:
            _plot_join(steps, title, loop_label, out / file)


def clip_figures(sections: dict, loops: list[ClipLoop], transitions: list[Transition], cloth: np.ndarray) -> ClipFigures:
    """The pictures of every loop and transition of cycle.json's sections (crowdbake.stages.cycle_job.
    write_clip_files), named in place: each clip and transition entry gets `figures` (file names beside
    report.html). cloth: (F, V, 3) the cache the transitions were taken from."""
    total = sections["timeline"]["total_frames"]
    clip_plans = []
    for entry, loop in zip(sections["clips"], loops):
        prefix = f"clip_{Path(entry['file']).stem}"
        result = loop.cache_result(total)
        shown = [name for name, _ in CLIP_PLOTS if name != "edges" or result.winner_images is not None]
        entry["figures"] = {name: f"{prefix}_{name}.png" for name in shown}
        clip_plans.append((prefix, result, (loop.offset, loop.offset + loop.result.frame_count)))
    by_clip = {loop.clip: loop for loop in loops}
    join_plans = []
    for entry, transition in zip(sections["transitions"], transitions):
        loop_a, loop_b = by_clip[transition.from_clip].looped, by_clip[transition.to_clip].looped
        leave, arrive = join_steps(transition, loop_a, loop_b, cloth)
        stem = f"transition_{Path(entry['file']).stem}"
        entry["figures"] = {"leave": f"{stem}_leave.png", "arrive": f"{stem}_arrive.png"}
        change = f"{transition.from_clip} → {transition.to_clip}"
        join_plans.append((entry["figures"]["leave"], f"{change}: leaving at cache frame {transition.leave.cache_frame}",
                           f"loop {transition.from_clip} going on", leave))
        join_plans.append((entry["figures"]["arrive"], f"{change}: arriving at cache frame {transition.arrive.cache_frame}",
                           f"loop {transition.to_clip} going on", arrive))
    return ClipFigures(clip_plans, join_plans)


# --- html ----------------------------------------------------------------------------------------------

def _figure(file: str, caption: str) -> str:
    return (f'<figure><img src="{html.escape(file)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _anchor(kind: str, index: int) -> str:
    return f"{kind}-{index}"


def _clip_section(index: int, entry: dict, carried: bool) -> str:
    """One loop: what was chosen, its candidates, its quality against the bounds, its seam, its plots."""
    closing, seam = entry["closing"], entry["seam"]
    candidates = _table(
        ["rank", "Fs", "Fe", "cycles", "vertex distance", "edge distance (px)", "chosen"],
        [[k + 1, c["start_frame"], c["end_frame"], c["cycle_count"], c["vertex_distance"], c["edge_distance"],
          "✔" if k == entry["chosen_candidate"] else ""] for k, c in enumerate(entry["candidates"])],
    )
    seam_rows = []
    for label, figures, penetrating in (("raw cycle", seam["before"], entry["penetration"]["total_before"]),
                                        (f"after {closing['method']}", seam["after"], entry["penetration"]["total_after"])):
        seam_rows.append([label, figures["position_jump_ratio"], figures["velocity_jump_ratio"], figures["max_step_ratio"],
                          figures["median_step"], penetrating])
    seam_table = _table(["", "position jump ratio", "velocity jump ratio", "max step ratio", "median step", "penetrating vertex-frames"],
                        seam_rows)
    captions = dict(CLIP_PLOTS)
    figures = "".join(_figure(file, captions[name]) for name, file in entry.get("figures", {}).items())
    searched = entry["searched_frames"]
    blend = f" over {closing['blend_frames']} frames" if closing.get("blend_frames") else ""
    bundle = " The bundle carries this loop." if carried else ""
    quality = _quality_html(closing.get("quality"), closing["method"], heading="h3")
    return (
        f'<section class="clip" id="{_anchor("clip", index)}" data-clip="{html.escape(entry["clip"])}">'
        f"<h2>Loop of {html.escape(entry['clip'])}: cache frames {entry['start_frame']} to {entry['end_frame']}</h2>"
        f"<p>{entry['cycle_frames']} frames ({entry['cycle_count']} cycle{'s' if entry['cycle_count'] > 1 else ''} of the clip's "
        f"{entry['period']}), cut from timeline segment {entry['segment']} (cache frames {searched[0]} to {searched[1]} searched); "
        f"loop frame 0 shows clip frame {entry['clip_phase']}. Chosen by {entry['selected_by'].replace('_', ' ')} among "
        f"{len(entry['candidates'])} candidates, closed with <b>{html.escape(closing['method'])}</b>{blend}; the push-out moved "
        f"{closing['pushed_vertices']} vertex-frames.{bundle}</p>"
        f"<h3>Candidates</h3>{candidates}{quality}<h3>Seam</h3>{seam_table}<h3>Figures</h3>{figures}</section>"
    )


def _join_cells(name: str, join: dict) -> list:
    quality = join.get("quality") or {}
    verdict = "–" if not quality else ("ok" if quality["within_bounds"] else "OVER: " + ", ".join(quality["exceeded"]))
    return [name, join["cache_frame"], join["loop_frame"], join["distance"], join["crossfade_frames"], join["switch_step_ratio"],
            quality.get("stretch_ratio"), quality.get("deviation_ratio"), quality.get("seam_acceleration_ratio"), verdict]


def _transition_section(index: int, entry: dict) -> str:
    """One transition: how playback goes through it, each join's figures against the bounds, a picture of each join."""
    start, end = entry["source_frames"]
    change = f"{html.escape(entry['from_clip'])} → {html.escape(entry['to_clip'])}"
    if entry["within_bounds"]:
        banner = '<p class="ok">Both joins keep within every quality bound.</p>'
    else:
        banner = ('<p class="warning"><b>WARNING: a join of this transition breaks its quality bounds.</b> '
                  "Playback strays from the simulation there: look at it before shipping.</p>")
    joins = _table(["join", "cache frame", "loop frame", "distance", "crossfade frames", "switch step ratio", "stretch",
                    "deviation", "seam acc.", "bounds"],
                   [_join_cells("leave", entry["leave"]), _join_cells("arrive", entry["arrive"])])
    files = entry.get("figures", {})
    figures = "".join(
        _figure(files[side], f"{side.capitalize()} at cache frame {entry[side]['cache_frame']}: the cloth's step per frame as "
                             "played, the loop going on alone, and the simulation; the crossfade shaded, the switch dotted.")
        for side in ("leave", "arrive") if side in files
    )
    return (
        f'<section class="transition" id="{_anchor("transition", index)}">'
        f"<h2>Transition {change}</h2>"
        f"<p>Playback leaves the loop of {html.escape(entry['from_clip'])} before its frame {entry['leave_loop_frame']}, plays the "
        f"transition's {entry['frames']} frames (cache frames {start} to {end - 1}: segment {entry['from_segment']} into "
        f"{entry['to_segment']}), and goes on with the loop of {html.escape(entry['to_clip'])} from its frame "
        f"{entry['arrive_loop_frame']}. Each join is crossfaded like a loop's seam.</p>"
        f"{banner}{joins}{figures}</section>"
    )


def clips_report(document: dict) -> str:
    """report.html of a cycle search over a timeline: the summary tables, then a section per loop and per
    transition (cycle.json's `clips` and `transitions`, with their `figures`), then the parameters."""
    clips, moves = document["clips"], document["transitions"]
    names = ", ".join(html.escape(c["clip"]) for c in clips)
    carried_one = "bundle_ranges" not in document
    contents = "".join(f'<li><a href="#{_anchor("clip", k)}">Loop of {html.escape(c["clip"])}</a></li>' for k, c in enumerate(clips))
    contents += "".join(f'<li><a href="#{_anchor("transition", k)}">Transition {html.escape(t["from_clip"])} → '
                        f'{html.escape(t["to_clip"])}</a></li>' for k, t in enumerate(moves))
    sections = "".join(_clip_section(k, c, carried_one and c["clip"] == document.get("primary_clip")) for k, c in enumerate(clips))
    sections += "".join(_transition_section(k, t) for k, t in enumerate(moves))
    params = _table(["parameter", "value"], [[k, v] for k, v in document["parameters"].items()])
    title = f"{len(clips)} clip{'s' if len(clips) > 1 else ''} and {len(moves)} transition{'s' if len(moves) != 1 else ''}"
    cache = document["input"]
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Cycle search: {title}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; max-width: 1100px; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1.5em; }}
td, th {{ border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }}
.warning {{ background: #fdd; border: 3px solid #c00; padding: 0.6em 1em; font-size: 1.2em; }}
.ok {{ background: #dfd; border: 1px solid #393; padding: 0.4em 1em; }}
section {{ border-top: 2px solid #888; margin-top: 2em; }}
figure {{ margin: 1em 0; display: inline-block; vertical-align: top; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
</style></head><body>
<h1>Cyclical cloth: {title}</h1>
<p>A cache of {_number(cache['frame_count'])} frames × {_number(cache['vertex_count'])} cloth vertices plays {names} (its
timeline): each clip is looped on its own frames, and each change of clip the simulation made is kept as a transition.</p>
<ul>{contents}</ul>
{clips_report_html(document)}
{sections}
<h2>Parameters</h2>{params}
</body></html>
"""
