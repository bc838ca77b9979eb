"""Which animation a bake uses when it was not told (crowdbake.ingest.clip_choice): the one the cloth
cache repeats after, among the clips the cache holds twice.

Regression: a character with an Idle (first) and a Walk, the cloth simulated on the Walk, and no
`animation` given: the bake took the first clip, Idle, and nothing said so."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from crowdbake.errors import InputError
from crowdbake.ingest.clip_choice import Clip, character_clips, choose_clip, repeat_gap
from crowdbake.ingest.bake_request import check_two_cycles
from crowdbake.params import BakeParams
from crowdbake.stages.validate import BakeInputs, stage_validate

SAMPLE_CYCLE_FRAMES = 24  # sample_fixtures.SMALL_SAMPLE


def _with_clips(sample: Path, out: Path, *speeds: tuple[str, float]) -> Path:
    """The sample character with its walk replaced by copies played `speed` times as fast, in order."""
    gltf = pygltflib.GLTF2().load(str(sample / "character.glb"))
    data = gltf.binary_blob()
    walk = gltf.animations[0]
    clips = []
    for name, speed in speeds:
        clip = copy.deepcopy(walk)
        clip.name = name
        inputs = {}
        for sampler in clip.samplers:
            if sampler.input not in inputs:
                accessor = gltf.accessors[sampler.input]
                view = gltf.bufferViews[accessor.bufferView]
                start = (view.byteOffset or 0) + (accessor.byteOffset or 0)
                times = np.frombuffer(data, "<f4", accessor.count, start) / speed
                offset = len(data)
                data += times.astype("<f4").tobytes()
                gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=4 * accessor.count))
                gltf.accessors.append(pygltflib.Accessor(bufferView=len(gltf.bufferViews) - 1, componentType=5126,
                                                         count=accessor.count, type="SCALAR",
                                                         min=[float(times.min())], max=[float(times.max())]))
                inputs[sampler.input] = len(gltf.accessors) - 1
            sampler.input = inputs[sampler.input]
        clips.append(clip)
    gltf.animations = clips
    gltf.buffers[0].byteLength = len(data)
    gltf.set_binary_blob(data)
    path = out / "character.glb"
    gltf.save_binary(str(path))
    return path


def _inputs(sample: Path, character: Path, params: BakeParams = BakeParams()) -> BakeInputs:
    return BakeInputs(character=character, cloth=sample / "cloth.pc2", cloth_mesh=sample / "cloth.obj", textures=None,
                      cycle=None, name="clips", version="1.0", params=params)


def test_repeat_gap_is_zero_one_period_later():
    """A cloth that moves with period 10 frames comes back after 10 and 20 frames, not after 5."""
    t = np.arange(60)[:, None]
    rest = np.random.default_rng(0).normal(size=(1, 30, 3))
    cloth = rest + np.stack([np.sin(2 * np.pi * t / 10) * np.linspace(0, 1, 30)] * 3, axis=2)
    assert repeat_gap(cloth, 10) < 1e-9 and repeat_gap(cloth, 20) < 1e-9
    assert repeat_gap(cloth, 5) > 0.5
    # Walking forward (the same offset on every vertex) changes nothing.
    assert repeat_gap(cloth + np.arange(60)[:, None, None] * 0.1, 10) < 1e-9


def test_unnamed_animation_is_the_clip_the_cloth_repeats_after(small_sample, tmp_path):
    """A half-length clip first, the walk the cloth was simulated on second: the walk is baked, and the
    job says which clip was picked and why."""
    character = _with_clips(small_sample, tmp_path, ("quick", 2.0), ("walk", 1.0))
    assert [(clip.name, clip.frames(24.0)) for clip in character_clips(character)] == [("quick", 12), ("walk", 24)]
    job = stage_validate(_inputs(small_sample, character), tmp_path / "work").record
    assert job.params["animation"] == 1 and job.cycle_frames == SAMPLE_CYCLE_FRAMES
    assert job.animation_choice["name"] == "walk" and job.animation_choice["frames"] == SAMPLE_CYCLE_FRAMES
    assert "repeats best" in job.animation_choice["reason"] and "'quick' 12 frames" in job.animation_choice["reason"]

    # A named animation is kept as it is, without a choice.
    named = stage_validate(_inputs(small_sample, character, BakeParams(animation="quick")), tmp_path / "named").record
    assert named.params["animation"] == "quick" and named.cycle_frames == 12 and named.animation_choice is None


def test_no_clip_the_cache_holds_twice_is_refused_listing_the_clips(small_sample, tmp_path):
    character = _with_clips(small_sample, tmp_path, ("idle", 0.5), ("stroll", 1 / 3))
    with pytest.raises(InputError, match=r"'idle' \(48 frames\), 'stroll' \(72 frames\)") as caught:
        stage_validate(_inputs(small_sample, character), tmp_path / "work")
    assert caught.value.field == "animation"


def test_request_check_with_several_clips_and_none_named():
    """The REST preflight passes when some clip fits (the validate stage picks) and lists them when none does."""
    character = {"animations": [{"name": "Idle", "seconds": 47 / 24}, {"name": "Walk", "seconds": 1.0}]}
    assert check_two_cycles(character, {"frame_count": 72, "fps": 24.0}, None, animation=None) == 24
    with pytest.raises(InputError, match=r"'Idle' \(47 frames\), 'Walk' \(24 frames\)") as caught:
        check_two_cycles(character, {"frame_count": 40, "fps": 24.0}, None, animation=None)
    assert caught.value.field == "params.animation"


def test_robot_clips_cape_picks_a_looping_23_frame_clip(shared_asset):
    """The CC0 robot (14 clips) and its cape, simulated across Idle, Walking, Running, Walking: the cape
    repeats best after 23 frames; of the 23-frame clips Death does not loop, Walking and Running tie."""
    from crowdbake.ingest.garment import read_cloth

    glb = shared_asset("robot_clips/robot.glb")
    clips = character_clips(glb)
    assert len(clips) == 14 and not clips[[c.name for c in clips].index("Death")].loops
    cache = read_cloth(shared_asset("robot_clips/garment.pc2"), shared_asset("robot_clips/garment.obj"))
    choice = choose_clip(clips, cache.frames, 24.0)
    assert choice.name in ("Walking", "Running") and choice.frames == 23
    assert "tie with it" in choice.reason


def test_one_clip_is_that_clip():
    cloth = np.zeros((10, 3, 3))
    assert choose_clip([Clip("only", 100.0)], cloth, 24.0).reason == "the character's only animation"


def _sampled_walk(keys: int, last_key_step_short: bool) -> np.ndarray:
    """(keys, 4) quaternions of a hip swinging +-20 degrees once over the clip: the last key equals the
    first, or (as many exports end) stops one key's step before the first pose comes round again."""
    period = keys if last_key_step_short else keys - 1
    angles = np.radians(20.0) * np.sin(2 * np.pi * np.arange(keys) / period)
    return np.stack([np.sin(angles / 2), np.zeros(keys), np.zeros(keys), np.cos(angles / 2)], axis=1)


def test_a_walk_that_ends_one_key_short_of_its_first_pose_loops():
    """Regression: a Mixamo-like Walk (24 keys) whose last key is one step from the first was judged
    "does not loop" by the absolute 1 cm rule, so an Idle that loops was baked under a walking cape."""
    from crowdbake.ingest.clip_choice import LOOP_TOLERANCE, _channel_loops

    short = _sampled_walk(24, last_key_step_short=True)
    assert np.abs(short[0] - short[-1]).max() > LOOP_TOLERANCE  # the old rule's "does not loop"
    assert _channel_loops(short, 24, "LINEAR")
    assert _channel_loops(_sampled_walk(24, last_key_step_short=False), 24, "LINEAR")
    # A fall: the hip turns 90 degrees in even steps and stays turned; its end is many steps from its start.
    fall = np.radians(np.linspace(0.0, 90.0, 24))
    falling = np.stack([np.sin(fall / 2), np.zeros(24), np.zeros(24), np.cos(fall / 2)], axis=1)
    assert not _channel_loops(falling, 24, "LINEAR")
    # A still channel with a jump at the end is not a loop either (its median step is zero).
    still = np.zeros((24, 3))
    still[-1] = 0.5
    assert not _channel_loops(still, 24, "LINEAR")


def test_the_walk_the_cloth_repeats_after_wins_over_a_looping_idle():
    """Both loop now (the walk by its own motion), so the smaller repeat gap decides: the cloth was
    driven by a 24-frame walk and comes back after 24 frames, not after the 47-frame idle."""
    t = np.arange(140)[:, None]
    rest = np.random.default_rng(1).normal(size=(1, 40, 3))
    swing = np.stack([np.sin(2 * np.pi * t / 24) * np.linspace(0, 0.3, 40)] * 3, axis=2)
    choice = choose_clip([Clip("Idle", 47 / 24, loops=True), Clip("Walk", 1.0, loops=True)], rest + swing, 24.0)
    assert choice.name == "Walk" and "(does not loop)" not in choice.reason
