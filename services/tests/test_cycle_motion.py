"""A cache of several clips searched as one is refused, naming where its motion changes.

robot_clips' cache (Idle -> Walking -> Running -> Walking) given to `crowdbake cycle` without its timeline
and with `--animation Running` was cut inside Idle, where the cape barely moves so any two frames match,
and played on the running body, with only a seam warning. The cycle job now compares the cloth's mean
speed over consecutive cycles (crowdbake.bake.motion_changes) and refuses a cache whose speed changes,
naming the frames; caches of one clip (the long skirt, the sample) go through.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from crowdbake.bake.motion_changes import CHANGE_FACTOR, cycle_speeds, motion_changes
from crowdbake.cli import main

CYCLE = 12


def swinging_cloth(amplitudes: list[float], cycle: int = CYCLE, points: int = 30) -> np.ndarray:
    """(cycles x cycle, points, 3): a row of points swinging sideways once a cycle, cycle k with amplitude
    amplitudes[k] (a hanging cloth, only its speed changing), plus a forward walk that the shape ignores."""
    frames = np.arange(len(amplitudes) * cycle)
    amplitude = np.repeat(np.asarray(amplitudes, np.float64), cycle)
    height = np.linspace(0.0, 1.0, points)
    swing = amplitude[:, None] * height[None] * np.sin(2 * np.pi * frames / cycle)[:, None]
    cloth = np.stack([swing, np.broadcast_to(-height, swing.shape), np.zeros_like(swing)], -1)
    cloth[..., 2] += 0.05 * frames[:, None]  # walking forward: the same for every point
    return cloth


def test_one_motion_repeated_has_a_flat_cycle_speed_and_no_change():
    cloth = swinging_cloth([0.2] * 8)
    speeds = cycle_speeds(cloth, CYCLE)
    np.testing.assert_allclose(speeds, speeds[0], rtol=1e-9)
    assert motion_changes(cloth, CYCLE, CYCLE) == []


def test_a_faster_motion_is_found_where_it_starts():
    """Four cycles at 0.1, then four at 0.3: the cycle after frame 4 x CYCLE is 3 times the one before."""
    cloth = swinging_cloth([0.1] * 4 + [0.3] * 4)
    changes = motion_changes(cloth, CYCLE, CYCLE)
    assert len(changes) == 1 and changes[0].frame == 4 * CYCLE and changes[0].factor == pytest.approx(3.0, rel=1e-6)
    # A change inside the settle-in is the search's to skip.
    assert motion_changes(cloth, CYCLE, 4 * CYCLE) == []
    # From stillness (up to the rounding of the walk taken out of the shape): beyond any factor.
    assert motion_changes(swinging_cloth([0.0] * 3 + [0.2] * 3), CYCLE)[0].factor > 1e6
    # Under the factor: the cloth's own cycle-to-cycle variation.
    assert motion_changes(swinging_cloth([0.2, 0.2, 0.2 * (CHANGE_FACTOR - 0.1), 0.2, 0.2]), CYCLE, CYCLE) == []


def test_the_robots_clips_without_their_timeline_are_refused_naming_the_changes(shared_asset, tmp_path, capsys):
    robot, cache, mesh, timeline = (shared_asset(f"robot_clips/{name}") for name in ("robot.glb", "garment.pc2", "garment.obj", "timeline.json"))
    args = ["cycle", str(cache), "--mesh", str(mesh), "--character", str(robot), "--animation", "Running", "--no-fit",
            "--no-edge-pass", "--out", str(tmp_path / "out")]
    assert main(args) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "the cloth's motion changes along the cache" in lines[0] and "--timeline" in lines[0], lines
    named = [int(part.split()[0].rstrip(",);")) for part in lines[0].split("at frame ")[1:]]
    # Every change of clip is named within a cycle (23 frames) of where the timeline's blend is.
    segments = json.loads(timeline.read_text())["segments"]
    for before, after in zip(segments, segments[1:]):
        change = (before["pure_last_frame"] + after["pure_first_frame"]) // 2
        assert any(abs(frame - change) <= 23 for frame in named), (change, named)
    assert not (tmp_path / "out" / "cycle.json").exists()


def test_the_long_skirt_of_one_walk_is_not_refused(shared_asset, tmp_path):
    skirt, mesh, walker = (shared_asset(name) for name in ("long_skirt/long_skirt.pc2", "long_skirt/long_skirt.obj", "CesiumMan.glb"))
    assert main(["cycle", str(skirt), "--mesh", str(mesh), "--character", str(walker), "--no-edge-pass", "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "cycle.json").read_text())["cycle_frames"] == 48
