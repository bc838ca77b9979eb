"""The cycle report of several clips shows every loop and every transition.

report.html of a `crowdbake cycle --timeline` run titled itself "frames 166 to 246" and showed the
candidates, seam and plots of the first clip's loop alone, without saying so; the transitions had a table
and no picture. It now has a section per loop (its candidates, quality figures against the bounds, seam
and plots) and per transition (each join's figures and a picture of the cloth's step across it).
"""
from __future__ import annotations

import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

from crowdbake.cli import main


class Sections(HTMLParser):
    """The <section> elements of a page: class, attributes, the text inside, and the src of each <img>."""

    def __init__(self):
        super().__init__()
        self.sections: list[dict] = []
        self.title = ""
        self._open = None
        self._in_title = False

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "section":
            self._open = {"attrs": attrs, "text": "", "images": []}
            self.sections.append(self._open)
        elif tag == "img" and self._open is not None:
            self._open["images"].append(attrs["src"])
        elif tag == "title":
            self._in_title = True

    def handle_endtag(self, tag):
        if tag == "section":
            self._open = None
        elif tag == "title":
            self._in_title = False

    def handle_data(self, data):
        if self._open is not None:
            self._open["text"] += data
        if self._in_title:
            self.title += data


def parse_report(path: Path) -> Sections:
    page = Sections()
    page.feed(path.read_text(encoding="utf-8"))
    return page


def shown(value: float) -> str:
    """A figure as the report's tables print it (cycle_report._number)."""
    return f"{value:.4g}"


def assert_every_loop_and_transition_is_shown(out: Path) -> None:
    document = json.loads((out / "cycle.json").read_text())
    page = parse_report(out / "report.html")
    assert "frames" not in page.title and f"{len(document['clips'])} clips" in page.title, page.title
    clips = [s for s in page.sections if s["attrs"].get("class") == "clip"]
    moves = [s for s in page.sections if s["attrs"].get("class") == "transition"]
    assert [s["attrs"]["data-clip"] for s in clips] == [c["clip"] for c in document["clips"]]
    assert len(moves) == len(document["transitions"]) > 0
    for section, entry in zip(clips, document["clips"]):
        quality = entry["closing"]["quality"]
        assert f"cache frames {entry['start_frame']} to {entry['end_frame']}" in section["text"]
        assert "Candidates" in section["text"] and "Seam" in section["text"]
        for name in ("stretch_ratio", "deviation_ratio", "seam_acceleration_ratio"):
            assert shown(quality[name]) in section["text"], (entry["clip"], name)
        assert shown(entry["seam"]["after"]["position_jump_ratio"]) in section["text"]
        # Pass 1, candidates and seam plots (and pass 2's edges when it ran), drawn.
        assert len(section["images"]) >= 3 and all((out / image).is_file() for image in section["images"]), section["images"]
    for section, entry in zip(moves, document["transitions"]):
        assert f"Transition {entry['from_clip']} → {entry['to_clip']}" in section["text"]
        for side in ("leave", "arrive"):
            assert shown(entry[side]["quality"]["stretch_ratio"]) in section["text"]
            assert shown(entry[side]["quality"]["seam_acceleration_ratio"]) in section["text"]
        assert ("keep within every quality bound" in section["text"]) == entry["within_bounds"]
        # A picture of each join.
        assert len(section["images"]) == 2 and all((out / image).is_file() for image in section["images"]), section["images"]


def test_a_cycle_run_over_the_clips_samples_timeline_reports_every_loop_and_transition(clips_sample, tmp_path):
    s = clips_sample
    out = tmp_path / "cycle"
    assert main(["cycle", str(s / "cloth.pc2"), "--mesh", str(s / "cloth.obj"), "--character", str(s / "character.glb"),
                 "--timeline", str(s / "timeline.json"), "--views", "3", "--candidates", "2", "--out", str(out)]) == 0
    assert_every_loop_and_transition_is_shown(out)
    # Pass 2 ran: every loop shows its edge pictures.
    page = parse_report(out / "report.html")
    assert all(any(image.endswith("_edges.png") for image in section["images"]) for section in page.sections if section["attrs"]["class"] == "clip")


def test_a_one_clip_report_keeps_its_layout(tmp_path):
    """The cache of one clip (a timeline of one segment would have sections): titled by its frames, no sections."""
    from crowdbake.sample.generate import generate_sample

    folder = tmp_path / "one"
    generate_sample(folder, garment="tight", seed=1, cycles=5, cycle_frames=16, texture_size=64, cloth_rows=8, cloth_columns=36, build="heavy")
    out = tmp_path / "cycle"
    assert main(["cycle", str(folder / "cloth.pc2"), "--mesh", str(folder / "cloth.obj"), "--character", str(folder / "character.glb"),
                 "--no-edge-pass", "--out", str(out)]) == 0
    document = json.loads((out / "cycle.json").read_text())
    page = parse_report(out / "report.html")
    assert page.title == f"Cycle search: frames {document['start_frame']}–{document['end_frame']}" and page.sections == []


def test_the_join_picture_follows_the_loop_then_the_simulation():
    """Known by construction: before the switch playback shows loop A, so the played steps are the loop's;
    past the crossfade the transition is the cache's frames, so they are the simulation's (and arriving,
    the other way round)."""
    from clip_caches import multi_clip_cache, timeline_document
    from crowdbake.bake.clips import find_clip_loops
    from crowdbake.bake.transitions import find_transitions
    from crowdbake.ingest.timeline import timeline_fields
    from crowdbake.stages.clips_report import join_steps

    cloth, faces = multi_clip_cache()
    timeline = timeline_fields(timeline_document(with_rows=True))
    loops = find_clip_loops(cloth, faces, timeline)
    by_clip = {loop.clip: loop.looped for loop in loops}
    for transition in find_transitions(cloth, faces, timeline, loops):
        leave, arrive = join_steps(transition, by_clip[transition.from_clip], by_clip[transition.to_clip], cloth)
        h = leave.half_width
        before, after = leave.offsets < -h - 1, leave.offsets >= h
        assert before.any() and after.any()
        np.testing.assert_allclose(leave.played[before], leave.loop[before], rtol=1e-6)
        np.testing.assert_allclose(leave.played[after], leave.simulation[after], rtol=1e-5)
        h = arrive.half_width
        before, after = arrive.offsets < -h - 1, arrive.offsets >= h
        np.testing.assert_allclose(arrive.played[before], arrive.simulation[before], rtol=1e-5)
        np.testing.assert_allclose(arrive.played[after], arrive.loop[after], rtol=1e-6)
        # The switch is a step of what is played, at the crossfade's edge.
        assert (leave.switch, arrive.switch) == (-leave.half_width - 1, arrive.half_width - 1)


def test_the_bundles_cycle_json_drops_the_report_pictures(clips_sample, tmp_path):
    from crowdbake.stages.cycle import bundle_cycle_document

    s = clips_sample
    assert main(["cycle", str(s / "cloth.pc2"), "--mesh", str(s / "cloth.obj"), "--character", str(s / "character.glb"),
                 "--timeline", str(s / "timeline.json"), "--no-edge-pass", "--candidates", "2", "--out", str(tmp_path)]) == 0
    document = json.loads((tmp_path / "cycle.json").read_text())
    assert all("figures" in entry for entry in [*document["clips"], *document["transitions"]])
    published = bundle_cycle_document(document)
    assert not any("figures" in entry for entry in [*published["clips"], *published["transitions"]])


def test_the_robots_bake_reports_every_loop_and_transition(robot_bake):
    """A bake draws the report's pictures after the stage, beside the next ones: they are there when it ends."""
    assert_every_loop_and_transition_is_shown(robot_bake[1] / "cycle")
