"""The procedural sample's clips (Idle, Walking, Running simulated in one run, with its timeline) and its builds.

One small clips sample (clips_fixtures: tight skirt on the heavy build, a walk of 16 frames, a coarse 8 x 36
cloth) is simulated once and baked once with `--timeline`: that bake is both the check that a clips sample
bakes and that another build does; its cycle.json holds every loop's and transition's quality figures.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from clips_fixtures import WALK_FRAMES
from crowdbake.bake.skinning import joint_world_matrices
from crowdbake.cli import main
from crowdbake.formats.gltf import load_character
from crowdbake.formats.pc2 import read_pc2
from crowdbake.ingest.clip_choice import character_clips
from crowdbake.ingest.timeline import check_timeline_fits, read_timeline
from crowdbake.sample.clips import (
    CLIP_NAMES,
    DEFAULT_SEQUENCE,
    Strip,
    clip_animations,
    clip_periods,
    parse_sequence,
    sequence_layout,
    sequence_world_matrices,
)
from crowdbake.sample.colliders import WAIST_HEIGHT, fit_capsules, segment_distance
from crowdbake.sample.humanoid import BUILDS, JOINT_INDEX, STANDARD, build_body, build_character
from crowdbake.sample.walk import FPS

# ---------------------------------------------------------------------------------------------- clips


def test_the_glb_holds_three_named_loops_in_place(clips_sample):
    clips = {clip.name: clip.seconds for clip in character_clips(clips_sample / "character.glb")}
    periods = clip_periods(WALK_FRAMES)
    assert list(clips) == list(CLIP_NAMES)
    assert {name: round(seconds * FPS) for name, seconds in clips.items()} == periods
    assert periods["Running"] < periods["Walking"] < periods["Idle"]  # a faster cadence, a slow breath
    for name in CLIP_NAMES:
        character = load_character(clips_sample / "character.glb", animation=name)
        for channel in character.channels:  # a loop of whole frames: the last key is the first
            assert len(channel.times) == periods[name] + 1
            np.testing.assert_array_equal(channel.values[-1], channel.values[0])
        hips = next(c for c in character.channels if c.path == "translation").values
        assert np.ptp(hips[:, 2]) < 1e-6 and np.ptp(hips[:, 0]) < 0.06  # in place: no travel, a sway


def test_the_run_strides_further_and_swings_more_than_the_walk():
    """Per clip, seen from the hips: the knee's travel front to back, the knee's largest bend, the wrist's swing."""
    character = build_character(build_body(), [], 0.0, None)
    animations = clip_animations(40)
    figures = {}
    for name, channels in animations.items():
        character.channels = channels
        world = joint_world_matrices(character, np.arange(clip_periods(40)[name]) / FPS)
        relative = np.linalg.inv(world[:, JOINT_INDEX["hips"]])[:, None] @ world
        hip, knee, ankle = (relative[:, JOINT_INDEX[joint], :3, 3] for joint in ("thigh_l", "shin_l", "foot_l"))
        thigh, shin = knee - hip, ankle - knee
        bend = np.degrees(np.arccos(np.sum(thigh * shin, axis=1) / np.linalg.norm(thigh, axis=1) / np.linalg.norm(shin, axis=1)))
        figures[name] = (np.ptp(knee[:, 2]), bend.max(), np.ptp(relative[:, JOINT_INDEX["hand_l"], 2, 3]))
    idle, walk, run = figures["Idle"], figures["Walking"], figures["Running"]
    assert run[0] > 1.15 * walk[0] > 2 * idle[0]  # stride
    assert run[1] > walk[1] + 10 > idle[1] + 30  # knee bend, degrees
    assert run[2] > 1.25 * walk[2] > 2 * idle[2]  # arm swing


def test_the_timeline_is_robot_clips_format_and_fits(clips_sample):
    """The existing reader takes it unchanged; its segments and rows say what the simulation played."""
    document = json.loads((clips_sample / "timeline.json").read_text())
    timeline = read_timeline(clips_sample / "timeline.json")
    cache = read_pc2(clips_sample / "cloth.pc2")
    clips = {clip.name: clip.seconds for clip in character_clips(clips_sample / "character.glb")}
    check_timeline_fits(timeline, cache.sample_count, FPS, clips)
    assert [s.clip for s in timeline.segments] == [clip for clip, _ in DEFAULT_SEQUENCE]
    assert {"fps", "total_frames", "blend_frames", "segments", "frames"} <= set(document)
    blend = document["blend_frames"]
    for k, (s, entry) in enumerate(zip(timeline.segments, document["segments"])):
        assert entry["repeats"] == DEFAULT_SEQUENCE[k][1] and len(entry["cycle_gap_rms_m"]) >= 1
        if k:  # strip k fades in over the blend frames before its pure frames, as Blender's NLA did
            rows = document["frames"][s.first_frame : s.pure_first_frame]
            assert len(rows) == blend and all(row["blend_from"] == timeline.segments[k - 1].clip for row in rows)
            weights = [row["weight"] for row in rows]
            assert weights[0] == 0 and weights == sorted(weights) and weights[-1] < 1
    row = document["frames"][100]
    assert set(row) >= {"frame", "clip", "segment", "clip_frame", "clip_time", "weight"}
    assert row["clip_time"] == pytest.approx(row["clip_frame"] / FPS, abs=1e-6)


def test_the_body_blends_between_clips_without_a_jump():
    """A switch without a blend moves the joints several centimetres in one substep (the poses differ);
    blended, no substep moves a joint further than the clips themselves do."""
    character = build_character(build_body(), [], 0.0, None)
    animations = clip_animations(WALK_FRAMES)
    periods = clip_periods(WALK_FRAMES)
    substeps = 4

    def largest_step(blend: int) -> tuple[float, float]:
        strips, total = sequence_layout((("Idle", 2), ("Running", 2), ("Walking", 2)), periods, blend)
        joints = sequence_world_matrices(character, animations, strips, blend, FPS, substeps, total * substeps)[:, :, :3, 3]
        step = np.linalg.norm(np.diff(joints, axis=0), axis=-1).max(axis=1)
        switching = np.zeros(len(step), bool)
        for s in strips[1:]:
            switching[max(s.first_frame * substeps - 1, 0) : (s.first_frame + blend) * substeps] = True
        return float(step[switching].max()), float(step[~switching].max())

    blended, inside = largest_step(6)
    snapped, _ = largest_step(1)
    assert blended <= 1.05 * inside, (blended, inside)
    assert snapped > 2 * inside  # the check can fail: a one-frame switch is a jump


def test_the_loops_and_transitions_keep_the_bounds_in_the_bake(clips_bake):
    """`crowdbake bake --timeline` on the sample: a loop per clip and a transition per change, all within the
    bounds (stretch <= 1.10, deviation <= 1.5, seam acceleration <= 1.5), on the heavy build."""
    code, bundle = clips_bake
    assert code == 0
    cycle = json.loads((bundle / "cycle.json").read_text())
    assert [(c["clip"], c["period"]) for c in cycle["clips"]] == [(name, clip_periods(WALK_FRAMES)[name]) for name in CLIP_NAMES]
    for entry in cycle["clips"]:
        quality = entry["closing"]["quality"]
        assert quality["within_bounds"], (entry["clip"], quality)
        assert quality["bounds"] == {"stretch_ratio": 1.1, "deviation_ratio": 1.5, "seam_acceleration_ratio": 1.5}
    changes = [(a, b) for (a, _), (b, _) in zip(DEFAULT_SEQUENCE, DEFAULT_SEQUENCE[1:])]
    assert [(t["from_clip"], t["to_clip"]) for t in cycle["transitions"]] == changes
    assert all(t["within_bounds"] for t in cycle["transitions"]), [(t["from_clip"], t["to_clip"]) for t in cycle["transitions"]]
    # Its body is stored as skinning across every loop and blended join (format 4: crowdbake.stages.body_skin).
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["format_version"] == 4
    assert sorted(mesh["file"] for mesh in manifest["meshes"] if mesh["kind"] == "body") == ["meshes/body_lod0.cbsk", "meshes/body_lod1.cbsk"]


@pytest.mark.parametrize("given, words", [
    ("Idle:3,Jumping:2", "entry 2 ('Jumping:2'): the clip must be one of Idle, Walking, Running"),
    ("Idle:3,Walking", "entry 2 ('Walking'): write CLIP:REPEATS, e.g. Walking:3"),
    ("Idle:1,Walking:3", "Idle (entry 1) repeats 1 times; repeats must lie in 2..100"),
    ("Walking:3,Walking:2", "Walking follows itself (entries 1 and 2): give it more repeats instead"),
])
def test_a_bad_sequence_is_one_line(given, words, tmp_path, capsys):
    assert main(["sample", str(tmp_path / "s"), "--clips", given]) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert lines == [f"crowdbake sample: error: --clips {given}: {words}"]
    assert not (tmp_path / "s").exists()


def test_a_blend_as_long_as_a_clip_is_refused():
    with pytest.raises(ValueError, match="blend frames must lie in 1..10"):
        sequence_layout(parse_sequence("Idle:2,Running:2"), clip_periods(16), 11)
    strips, total = sequence_layout(parse_sequence("Idle:2,Running:3"), clip_periods(16), 4)
    assert strips == [Strip("Idle", 0, 2, 32), Strip("Running", 60, 3, 11)] and total == 60 + 33 + 1


def test_walk_cycles_and_blends_each_say_what_they_need(tmp_path, capsys):
    assert main(["sample", str(tmp_path / "s"), "--clips", "--cycles", "3"]) == 2
    assert "--cycles counts walk cycles; with --clips the sequence says how often" in capsys.readouterr().err
    assert main(["sample", str(tmp_path / "s"), "--blend-frames", "3"]) == 2
    assert "--blend-frames blends one clip into the next: it needs --clips" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


# ---------------------------------------------------------------------------------------------- builds


@pytest.fixture(scope="module")
def bodies():
    return {name: build_body(build) for name, build in BUILDS.items()}


def _extent(body, part: str, axis: int) -> float:
    first, stop = body.part_ranges[part]
    return float(np.ptp(body.positions[first:stop, axis]))


def test_builds_change_height_width_and_girth(bodies):
    standard, heavy, slim = bodies["standard"], bodies["heavy"], bodies["slim"]
    height = {name: float(body.positions[:, 1].max()) for name, body in bodies.items()}
    assert height["heavy"] < height["standard"] < height["slim"]
    for part, axis in (("torso", 0), ("torso", 2), ("leg_l", 2)):  # hips and shoulders across, trunk and thigh deep
        assert _extent(heavy, part, axis) > 1.05 * _extent(standard, part, axis) > 1.1 * _extent(slim, part, axis), (part, axis)
    shoulders = {name: b.positions[b.part_ranges["arm_l"][0], 0] - b.positions[b.part_ranges["arm_r"][0], 0] for name, b in bodies.items()}
    assert shoulders["heavy"] > shoulders["standard"] > shoulders["slim"]
    # Same topology and UVs, so textures and the bake's LODs treat every build alike.
    for body in (heavy, slim):
        np.testing.assert_array_equal(body.faces, standard.faces)
        np.testing.assert_array_equal(body.uvs, standard.uvs)
    assert heavy.build is BUILDS["heavy"] and standard.build is STANDARD


@pytest.mark.parametrize("name", ["heavy", "slim"])
def test_a_builds_capsules_enclose_its_legs_and_follow_its_waist(bodies, name):
    """As test_sample's checks for the standard build, at the build's own heights."""
    from crowdbake.sample.cloth_sim import surface_distance
    from crowdbake.sample.garments import outer_radius

    body, h = bodies[name], BUILDS[name].height
    capsules = fit_capsules(body)
    legs = [k for k, capsule in enumerate(capsules.names) if capsule.startswith(("thigh", "shin"))]
    first, stop = body.part_ranges["leg_l"]
    positions = body.positions[first:stop].astype(np.float64)
    covered = (positions[:, 1] > 0.06 * h) & (positions[:, 1] < 0.92 * h)
    distance = np.min([segment_distance(positions[covered], *capsules.endpoints[k]) - capsules.radii[k] for k in legs], axis=0)
    assert distance.max() <= 1e-9
    trunk = np.array([capsule.startswith(("pelvis", "waist")) for capsule in capsules.names])
    angles = 2 * np.pi * np.arange(72) / 72
    waist = WAIST_HEIGHT * h
    surface = outer_radius(np.array([waist]), angles, capsules.endpoints[trunk][None], capsules.radii[trunk])[0]
    points = surface[:, None] * np.stack([np.sin(angles), np.zeros(72), -np.cos(angles)], axis=1) + [0.0, waist, 0.0]
    first, stop = body.part_faces["torso"]
    assert surface_distance(points, body.positions, body.faces[first:stop]).max() < 0.004


def test_the_baked_build_is_the_heavy_body(clips_sample, clips_bake, bodies):
    """The sample written with --build heavy carries the heavy body, and bakes (the clips bake above)."""
    character = load_character(clips_sample / "character.glb", animation="Walking")
    np.testing.assert_allclose(character.positions, bodies["heavy"].positions, atol=1e-6)
    assert not np.allclose(character.positions, bodies["standard"].positions, atol=0.01)
    sample = json.loads((clips_sample / "sample.json").read_text())
    assert sample["build"]["name"] == "heavy" and sample["clips"]["timeline"] == "timeline.json"
    assert clips_bake[0] == 0
