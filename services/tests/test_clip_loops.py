"""Several clips in one cloth simulation: the timeline's checks, a loop per clip, transitions between loops.

The synthetic cache (clip_caches.py) plays Walk (12 frames) -> Run (8) -> Walk with 4-frame blends; its
settled frames depend on the clip frame alone, so loops and joins are known by construction. The real
check is robot_clips (Blender's cloth across Idle -> Walking -> Running -> Walking), cycle side only.
"""
from __future__ import annotations

import copy
import json
from dataclasses import replace

import numpy as np
import pytest

from clip_caches import PERIODS, multi_clip_cache, timeline_document
from crowdbake.bake.clips import find_clip_loop, find_clip_loops
from crowdbake.bake.transitions import find_transitions
from crowdbake.cli import main
from crowdbake.formats.obj import write_obj
from crowdbake.formats.pc2 import read_pc2, write_pc2
from crowdbake.ingest.timeline import TimelineFieldError, check_timeline_fits, timeline_fields


def rms(delta: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(delta), axis=-1))))


@pytest.fixture(scope="module")
def baked():
    cloth, faces = multi_clip_cache()
    timeline = timeline_fields(timeline_document(with_rows=True))
    loops = find_clip_loops(cloth, faces, timeline)
    transitions = find_transitions(cloth, faces, timeline, loops)
    return cloth, faces, timeline, loops, transitions


class TestTimelineChecks:
    def test_rows_and_segments_give_the_same_clip_frames(self):
        """Rows at a blend's first frame name the new clip at weight 0: the pure frame's clip frame is the old one's."""
        with_rows = timeline_fields(timeline_document(with_rows=True))
        derived = timeline_fields(timeline_document())
        np.testing.assert_array_equal(with_rows.clip_frame, derived.clip_frame)
        assert [(s.clip, s.pure_first_frame, s.pure_last_frame) for s in derived.segments] == [
            ("Walk", 0, 60), ("Run", 64, 124), ("Walk", 128, 171)]

    @pytest.mark.parametrize("change, pointer, words", [
        (lambda d: d.update(fps=0), "/fps", "outside the sane range"),
        (lambda d: d["segments"][1].update(clip_frames=1), "/segments/1/clip_frames", "at least 2"),
        (lambda d: d["segments"].reverse(), "/segments/1/first_frame", "playing order"),
        (lambda d: d["segments"][1].update(first_frame=56, pure_first_frame=58), "/segments/1/pure_first_frame", "overlaps segment 0"),
        (lambda d: d["segments"][2].update(clip_frames=13), "/segments/2/clip_frames", "'Walk' has 12 frames"),
        (lambda d: d["segments"][0].update(last_frame=500), "/segments/0/last_frame", "must be an integer in 0..171"),
        (lambda d: d["segments"][0].pop("clip"), "/segments/0/clip", "must be a clip name"),
        (lambda d: d["frames"][10].update(clip="Run", clip_frame=2), "/frames/10/clip", "pure frame of segment 0"),
        (lambda d: d["frames"].pop(), "/frames", "one row per frame"),
    ])
    def test_a_bad_field_is_named_by_its_pointer(self, change, pointer, words):
        document = copy.deepcopy(timeline_document(with_rows=True))
        change(document)
        with pytest.raises(TimelineFieldError) as caught:
            timeline_fields(document)
        assert caught.value.pointer == pointer and words in caught.value.message, caught.value.message
        assert caught.value.field == "timeline"

    def test_against_the_cache_and_the_character(self):
        timeline = timeline_fields(timeline_document())
        clips = {"Walk": 0.5, "Run": 8 / 24, "Jump": 1.0}
        check_timeline_fits(timeline, 172, 24.0, clips)  # fits
        for args, pointer, words in [
            ((171, 24.0, clips), "/total_frames", "the cloth cache has 171 frames"),
            ((172, 30.0, clips), "/fps", "plays at 30 frames per second"),
            ((172, 24.0, {"Walk": 0.5, "Jump": 1.0}), "/segments/1/clip", "which the character lacks (it has 'Walk', 'Jump')"),
            ((172, 24.0, {"Walk": 0.5, "Run": 0.5}), "/segments/1/clip_frames", "'Run' lasts 0.5 s = 12 frames"),
        ]:
            with pytest.raises(TimelineFieldError) as caught:
                check_timeline_fits(timeline, *args)
            assert caught.value.pointer == pointer and words in caught.value.message, caught.value.message


class TestClipLoops:
    def test_each_clip_loops_over_its_own_period_within_the_bounds(self, baked):
        cloth, _, timeline, loops, _ = baked
        assert [(loop.clip, len(loop.looped)) for loop in loops] == [("Walk", 12), ("Run", 8)]
        for loop in loops:
            assert loop.result.closing.quality.within_bounds, loop.result.closing.quality
            segment = timeline.segments[loop.segment]
            assert segment.clip == loop.clip
            assert segment.pure_first_frame <= loop.start_frame and loop.end_frame <= segment.pure_last_frame
            # The loop is the clip's motion: frame k shows clip frame (clip_phase + k), as the cache did there.
            assert timeline.clip_frame[loop.start_frame] == loop.clip_phase
            assert rms(loop.looped - cloth[loop.start_frame : loop.end_frame]) < 1e-3

    def test_a_clip_met_twice_is_searched_over_both_stretches(self, baked):
        """Walk's first stretch cut too short for two periods: its loop comes from its second segment."""
        cloth, faces, timeline, _, _ = baked
        short = replace(timeline.segments[0], pure_last_frame=20)
        clipped = replace(timeline, segments=(short, *timeline.segments[1:]))
        loop = find_clip_loop(cloth, faces, clipped, "Walk")
        assert loop.segment == 2 and loop.start_frame >= timeline.segments[2].pure_first_frame
        assert loop.to_dict(len(cloth))["searched_frames"] == [128, 171]

    def test_a_clip_without_two_periods_anywhere_is_refused_by_name(self, baked):
        cloth, faces, timeline, _, _ = baked
        short = replace(timeline.segments[1], pure_last_frame=timeline.segments[1].pure_first_frame + 10)
        clipped = replace(timeline, segments=(timeline.segments[0], short, timeline.segments[2]))
        with pytest.raises(ValueError, match="clip 'Run' \\(8 frames\\): no pure stretch holds a loop"):
            find_clip_loop(cloth, faces, clipped, "Run")


class TestMessagesNameCacheFrames:
    """Users look for the cache frames of a loop or transition, not its frames counted from a stretch's start."""

    def test_an_out_of_bounds_loop_is_named_by_clip_and_cache_frames(self, baked):
        from crowdbake.bake.bounds import bounds_message, out_of_bounds

        _, _, timeline, loops, transitions = baked
        run = loops[1]
        broken = replace(run.result.closing.quality, seam_acceleration_ratio=4.17, exceeded=("seam_acceleration_ratio",))
        loop = replace(run, result=replace(run.result, closing=replace(run.result.closing, quality=broken)))
        assert loop.offset > 0  # the loop's own frames count from its stretch: the message must not
        message = bounds_message(out_of_bounds([loop], transitions))
        assert "\n" not in message
        assert message.startswith(f"the loop of clip 'Run' (cache frames [{loop.start_frame}, {loop.end_frame})): "
                                  "seam_acceleration_ratio 4.17 > 1.5")

    def test_the_search_logs_its_loops_in_cache_frames(self, caplog):
        cloth, faces = multi_clip_cache()
        timeline = timeline_fields(timeline_document(with_rows=True))
        with caplog.at_level("DEBUG", logger="crowdbake.bake.cycle"):
            loop = find_clip_loop(cloth, faces, timeline, "Run")
        run = timeline.segments[1]
        assert loop.offset == run.pure_first_frame > 0
        lines = [record.getMessage() for record in caplog.records]
        assert f"clip 'Run', loop at cache frames [{loop.start_frame}, {loop.end_frame}): seam position jump" in " ".join(lines)
        for text in lines:
            if "cache frames [" in text:
                first = int(text.split("cache frames [")[1].split(",")[0])
                assert run.pure_first_frame <= first <= run.pure_last_frame, text


class TestTransitions:
    def test_one_per_change_of_clip_within_the_bounds(self, baked):
        _, _, _, _, transitions = baked
        assert [(t.from_clip, t.to_clip, t.from_segment) for t in transitions] == [("Walk", "Run", 0), ("Run", "Walk", 1)]
        for transition in transitions:
            assert transition.within_bounds, (transition.leave.quality, transition.arrive.quality)

    def test_frames_come_from_the_simulation_between_the_joins(self, baked):
        cloth, _, timeline, loops, transitions = baked
        by_clip = {loop.clip: loop for loop in loops}
        for t in transitions:
            a, b, h_a, h_b = t.leave.cache_frame, t.arrive.cache_frame, t.leave.half_width, t.arrive.half_width
            assert len(t.frames) == b - a + h_a + h_b and t.source_frames == (a - h_a, b + h_b)
            np.testing.assert_array_equal(t.frames[2 * h_a : -2 * h_b], cloth[a + h_a : b - h_b])
            # Each join matches the body's pose: the loop frame shows the cache frame's clip frame.
            loop_a, loop_b = by_clip[t.from_clip], by_clip[t.to_clip]
            assert (loop_a.clip_phase + t.leave.loop_frame) % loop_a.period == timeline.clip_frame[a] % loop_a.period
            assert (loop_b.clip_phase + t.arrive.loop_frame) % loop_b.period == timeline.clip_frame[b] % loop_b.period
            assert t.leave_loop_frame == (t.leave.loop_frame - h_a) % loop_a.period
            assert t.arrive_loop_frame == (t.arrive.loop_frame + h_b) % loop_b.period

    def test_playback_never_jumps_further_than_the_loops_move(self, baked):
        """loop A up to the frame before leave_loop_frame, the transition, loop B from arrive_loop_frame."""
        _, _, _, loops, transitions = baked
        by_clip = {loop.clip: loop for loop in loops}
        for t in transitions:
            loop_a, loop_b = by_clip[t.from_clip].looped, by_clip[t.to_clip].looped
            largest = max(rms(np.diff(np.concatenate([loop, loop[:1]]), axis=0)[k]) for loop in (loop_a, loop_b) for k in range(len(loop)))
            assert rms(t.frames[0] - loop_a[t.leave_loop_frame - 1]) <= 1.5 * largest
            assert rms(loop_b[t.arrive_loop_frame] - t.frames[-1]) <= 1.5 * largest


@pytest.fixture(scope="module")
def clip_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("clip_inputs")
    cloth, faces = multi_clip_cache()
    t = np.linspace(0, 1, 6)[:, None] * np.ones((1, 16))
    angle = np.linspace(0, 2 * np.pi, 16, endpoint=False)[None, :] * np.ones((6, 1))
    body = np.stack([0.1 * np.sin(angle), 1.2 * (1 - t), 0.1 * np.cos(angle)], -1).reshape(-1, 3).astype(np.float32)
    from clip_caches import grid_faces

    write_pc2(folder / "cloth.pc2", cloth)
    write_obj(folder / "cloth.obj", cloth[0], faces)
    write_pc2(folder / "body.pc2", np.repeat(body[None], len(cloth), axis=0))
    write_obj(folder / "body.obj", body, grid_faces(6, 16))
    (folder / "timeline.json").write_text(json.dumps(timeline_document(with_rows=True)))
    return folder


def cycle_args(folder, out, timeline) -> list[str]:
    return ["cycle", str(folder / "cloth.pc2"), "--mesh", str(folder / "cloth.obj"), "--body", str(folder / "body.pc2"),
            "--body-mesh", str(folder / "body.obj"), "--timeline", str(timeline), "--no-edge-pass", "--out", str(out)]


class TestCycleCommand:
    def test_writes_every_loop_and_transition(self, clip_files, tmp_path):
        assert main(cycle_args(clip_files, tmp_path, clip_files / "timeline.json")) == 0
        document = json.loads((tmp_path / "cycle.json").read_text())
        assert document["primary_clip"] == "Walk" and document["cycle_frames"] == PERIODS["Walk"]
        assert [c["clip"] for c in document["clips"]] == ["Walk", "Run"]
        assert [(t["from_clip"], t["to_clip"]) for t in document["transitions"]] == [("Walk", "Run"), ("Run", "Walk")]
        for entry in document["transitions"]:
            assert entry["within_bounds"] and entry["leave"]["quality"]["within_bounds"]
            assert read_pc2(tmp_path / entry["file"]).sample_count == entry["frames"]
        for entry in document["clips"]:
            assert read_pc2(tmp_path / entry["file"]).sample_count == entry["period"]
        # The top level is the primary clip's loop, as a one-clip cycle.json (start_frame in cache frames).
        assert document["start_frame"] == document["clips"][0]["start_frame"]
        np.testing.assert_array_equal(read_pc2(tmp_path / "looped.pc2").points, read_pc2(tmp_path / "clips/walk.pc2").points)
        assert "Transitions taken from the simulation" in (tmp_path / "report.html").read_text()

    def test_a_timeline_that_does_not_fit_the_cache_is_one_line(self, clip_files, tmp_path, capsys):
        document = timeline_document()
        document["total_frames"] = 200
        document["segments"][-1].update(last_frame=199, pure_last_frame=199)
        (tmp_path / "long.json").write_text(json.dumps(document))
        assert main(cycle_args(clip_files, tmp_path / "out", tmp_path / "long.json")) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert lines == ["crowdbake cycle: error: long.json: /total_frames is 200, but the cloth cache has 172 frames"]
        assert not (tmp_path / "out" / "cycle.json").exists()

    @pytest.mark.parametrize("field, value, pointer", [("clip", ["Walk"], "/frames/5/clip"), ("clip", {"Walk": 1}, "/frames/5/clip"),
                                                       ("blend_from", ["Walk"], "/frames/5/blend_from")])
    def test_a_row_of_the_wrong_type_is_one_line(self, clip_files, tmp_path, capsys, field, value, pointer):
        """A list or object where a clip name belongs was a TypeError (unhashable) and a traceback."""
        document = timeline_document(with_rows=True)
        document["frames"][5].update({field: value, "weight": 0.5, "blend_from_frame": 0} if field == "blend_from" else {field: value})
        (tmp_path / "typed.json").write_text(json.dumps(document))
        assert main(cycle_args(clip_files, tmp_path / "out", tmp_path / "typed.json")) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith(f"crowdbake cycle: error: typed.json: {pointer} must be a clip of the segments"), lines


def test_robot_clips_loops_and_transitions_keep_the_bounds(shared_asset):
    """Real cloth (Blender, 717 frames): a loop per clip and a transition per change, all within the bounds."""
    from crowdbake.formats.obj import read_obj
    from crowdbake.ingest.clip_choice import character_clips
    from crowdbake.ingest.timeline import read_timeline

    timeline_path = shared_asset("robot_clips/timeline.json")
    cache = read_pc2(shared_asset("robot_clips/garment.pc2"))
    mesh = read_obj(shared_asset("robot_clips/garment.obj"))
    faces = mesh.source_index[mesh.faces.astype(np.int64)]
    timeline = read_timeline(timeline_path)
    clips = {clip.name: clip.seconds for clip in character_clips(shared_asset("robot_clips/robot.glb"))}
    check_timeline_fits(timeline, cache.sample_count, 24.0, clips)
    loops = find_clip_loops(cache.points, faces, timeline)
    transitions = find_transitions(cache.points, faces, timeline, loops)
    assert [(loop.clip, loop.period) for loop in loops] == [("Idle", 80), ("Walking", 23), ("Running", 23)]
    assert all(loop.result.closing.quality.within_bounds for loop in loops)
    assert [(t.from_clip, t.to_clip) for t in transitions] == [("Idle", "Walking"), ("Walking", "Running"), ("Running", "Walking")]
    assert all(t.within_bounds for t in transitions)
    # A clip the robot lacks is named with the clips it has.
    renamed = replace(timeline, segments=(replace(timeline.segments[0], clip="Sleeping"), *timeline.segments[1:]))
    with pytest.raises(TimelineFieldError, match="'Sleeping', which the character lacks \\(it has .*'Idle'.*'Running'"):
        check_timeline_fits(renamed, cache.sample_count, 24.0, clips)


def test_bake_refuses_a_timeline_that_does_not_fit_in_one_line(shared_asset, tmp_path, capsys):
    """`crowdbake bake --timeline` checks the timeline against the character before any stage runs."""
    robot, cache, mesh = (shared_asset(f"robot_clips/{name}") for name in ("robot.glb", "garment.pc2", "garment.obj"))
    document = json.loads(shared_asset("robot_clips/timeline.json").read_text())
    document.pop("frames")
    document["segments"][2]["clip"] = "Sleeping"
    (tmp_path / "sleepy.json").write_text(json.dumps(document))
    base = ["bake", str(robot), "--cloth", str(cache), "--cloth-mesh", str(mesh), "--name", "robot", "--version", "1", "--out", str(tmp_path / "out")]
    assert main([*base, "--timeline", str(tmp_path / "sleepy.json")]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(
        "crowdbake bake: error: --timeline: sleepy.json: /segments/2/clip names 'Sleeping', which the character lacks (it has "), lines
    assert "'Running'" in lines[0]
    document["segments"][2]["clip"] = "Running"
    document["total_frames"] = 800
    document["segments"][-1].update(last_frame=799, pure_last_frame=799)
    (tmp_path / "short.json").write_text(json.dumps(document))
    assert main([*base, "--timeline", str(tmp_path / "short.json")]) == 2
    assert "--timeline: short.json: /total_frames is 800, but the cloth cache has 717 frames" in capsys.readouterr().err


def test_the_bundles_cycle_json_keeps_the_figures_but_not_the_work_files(clip_files, tmp_path):
    from crowdbake.stages.cycle import bundle_cycle_document

    assert main(cycle_args(clip_files, tmp_path, clip_files / "timeline.json")) == 0
    published = bundle_cycle_document(json.loads((tmp_path / "cycle.json").read_text()))
    assert [entry["clip"] for entry in published["clips"]] == ["Walk", "Run"]
    assert all("file" not in entry and "timings_s" not in entry for entry in [*published["clips"], *published["transitions"]])
    assert published["transitions"][0]["leave"]["quality"]["bounds"] == {"stretch_ratio": 1.1, "deviation_ratio": 1.5, "seam_acceleration_ratio": 1.5}


def test_bake_takes_the_periods_from_the_timeline(shared_asset, tmp_path, capsys):
    robot, cache, mesh, timeline = (shared_asset(f"robot_clips/{name}") for name in ("robot.glb", "garment.pc2", "garment.obj", "timeline.json"))
    args = ["bake", str(robot), "--cloth", str(cache), "--cloth-mesh", str(mesh), "--timeline", str(timeline), "--cycle-frames", "23",
            "--name", "robot", "--version", "1", "--out", str(tmp_path / "out")]
    assert main(args) == 2
    assert capsys.readouterr().err.strip() == "crowdbake bake: error: --cycle-frames: the timeline gives each clip's period: drop cycle_frames"
    assert main([*args[:-8], "--animation", "Dance", *args[-6:]]) == 2
    assert "--animation: animation 'Dance' is not a clip of the timeline (it plays Idle, Walking, Running)" in capsys.readouterr().err
