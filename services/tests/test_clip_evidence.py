"""The physical evidence of the clip that drove a cloth (crowdbake.bake.clip_evidence) and its part in the
choice of animation (crowdbake.ingest.clip_choice): under the right clip the cloth stays outside the body
and moves with it. Where clips repeat alike (same length), the evidence decides; a clip whose body the
cloth does not follow, or sits inside, loses."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from crowdbake.bake.clip_evidence import (ClipEvidence, conclusive, evidence_pairs, measure_clip_evidence,
                                          rejections)
from crowdbake.ingest.clip_choice import character_clip_evidence, character_clips, choose_clip, repeat_gap
from crowdbake.params import BakeParams
from crowdbake.stages.validate import BakeInputs, stage_validate

FPS = 24.0


def _sphere(count: int = 400, radius: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(count, 3) points on a sphere and its (T, 3) convex-hull triangles, wound outwards."""
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(3)
    points = rng.normal(size=(count, 3))
    points *= radius / np.linalg.norm(points, axis=1, keepdims=True)
    hull = ConvexHull(points)
    faces = hull.simplices.copy()
    centres = points[faces].mean(axis=1)
    normals = np.cross(points[faces[:, 1]] - points[faces[:, 0]], points[faces[:, 2]] - points[faces[:, 0]])
    flip = np.einsum("ij,ij->i", normals, centres) < 0
    faces[flip] = faces[flip][:, ::-1]
    return points, faces


def _bobbing(points: np.ndarray, frames: int, phase: float, axis: int = 1) -> np.ndarray:
    """(frames, N, 3): the points moving 5 cm up and down along `axis`, a 24-frame cycle starting at `phase`."""
    offset = 0.05 * np.sin(2 * np.pi * (np.arange(frames) / 24 + phase))
    moved = np.repeat(points[None], frames, axis=0)
    moved[:, :, axis] += offset[:, None]
    return moved


def test_the_cloth_follows_the_body_that_drove_it_and_stays_outside():
    """A shell of cloth 10 cm outside a bobbing ball: under the ball's own motion it follows (about 1) and
    none of it is inside; under the same bob a quarter cycle on, or sideways, it does not follow; under a
    ball grown past the shell, the cloth is inside."""
    ball, faces = _sphere()
    shell = _sphere(600, 0.4)[0]
    cloth = _bobbing(shell, 48, 0.0)
    pairs = evidence_pairs(48)
    assert pairs.shape == (16, 2) and (pairs[:, 1] - pairs[:, 0] == 1).all() and pairs.max() == 47
    own = measure_clip_evidence(cloth, _bobbing(ball, 48, 0.0), faces)
    late = measure_clip_evidence(cloth, _bobbing(ball, 48, 0.25), faces)
    sideways = measure_clip_evidence(cloth, _bobbing(ball, 48, 0.0, axis=0), faces)
    grown = measure_clip_evidence(cloth, _bobbing(ball * 1.5, 48, 0.0), faces)
    assert own.penetration == 0 and own.follow > 0.99
    assert abs(late.follow) < 0.2 and abs(sideways.follow) < 0.05
    assert grown.penetration > 0.9 and grown.follow > 0.99
    judged = {0: own, 1: late, 2: sideways, 3: grown}
    assert conclusive(judged)
    assert rejections(judged) == {1: "does not follow", 2: "does not follow", 3: "inside the body"}
    # The measure on the sampled pairs is the measure on every frame's pairs, near enough.
    frames = np.unique(pairs)
    sampled = measure_clip_evidence(cloth[frames], _bobbing(ball, 48, 0.0)[frames], faces,
                                    pairs=np.searchsorted(frames, pairs))
    assert sampled.penetration == 0 and sampled.follow > 0.99


def test_evidence_that_follows_no_clip_rules_nothing_out():
    weak = {0: ClipEvidence(0.0, 0.1, 16), 1: ClipEvidence(0.3, -0.2, 16)}
    assert not conclusive(weak) and rejections(weak) == {}
    assert not conclusive({})


def test_a_clip_the_cloth_is_inside_loses_even_where_it_repeats_as_well():
    """Two clips of one length: the cloth follows both (the same motion), but one body is grown past it."""
    from crowdbake.ingest.clip_choice import Clip

    ball, faces = _sphere()
    shell = _sphere(600, 0.4)[0]
    cloth = _bobbing(shell, 72, 0.0)
    bodies = {0: _bobbing(ball * 1.5, 72, 0.0), 1: _bobbing(ball, 72, 0.0)}

    def evidence(indices):
        pairs = evidence_pairs(len(cloth))
        return {k: measure_clip_evidence(cloth, bodies[k], faces, pairs=pairs) for k in indices}

    clips = [Clip("grown", 1.0), Clip("own", 1.0)]
    assert choose_clip(clips, cloth, FPS).name == "grown"  # the gap alone: a tie, the first taken
    choice = choose_clip(clips, cloth, FPS, evidence)
    assert choice.name == "own"
    assert "'grown' 24 frames" in choice.reason and "rejected: inside the body" in choice.reason
    assert "tie with it" not in choice.reason


def _with_animation_variants(glb: Path, out: Path, variants: list[tuple[str, float, float]]) -> Path:
    """A copy of the character whose animations are its first one, once per (name, phase, grow) in order:
    keyed `phase` of a cycle later (its keys rolled: they must be evenly spaced, the last one repeating the
    first), and with the skeleton's root joint scaled by `grow` (1: as it is)."""
    gltf = pygltflib.GLTF2().load(str(glb))
    data = gltf.binary_blob()
    source = gltf.animations[0]
    root = gltf.skins[0].joints[0]

    def add(values: np.ndarray, kind: str) -> int:
        nonlocal data
        values = np.ascontiguousarray(values, "<f4")
        offset = len(data) + (-len(data)) % 4
        data += b"\0" * (offset - len(data)) + values.tobytes()
        gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=values.nbytes))
        gltf.accessors.append(pygltflib.Accessor(bufferView=len(gltf.bufferViews) - 1, componentType=5126,
                                                 count=len(values), type=kind))
        return len(gltf.accessors) - 1

    def read(index: int) -> np.ndarray:
        accessor = gltf.accessors[index]
        view = gltf.bufferViews[accessor.bufferView]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[accessor.type]
        start = (view.byteOffset or 0) + (accessor.byteOffset or 0)
        return np.frombuffer(data, "<f4", accessor.count * width, start).reshape(accessor.count, width)

    animations = []
    for name, phase, grow in variants:
        clip = copy.deepcopy(source)
        clip.name = name
        for sampler in clip.samplers:
            values = read(sampler.output)
            keys = len(values) - 1  # the last key repeats the first
            rolled = np.roll(values[:keys], -int(round(phase * keys)), axis=0)
            sampler.output = add(np.vstack([rolled, rolled[:1]]), gltf.accessors[sampler.output].type)
        if grow != 1:
            times = clip.samplers[0].input
            scale = add(np.full((gltf.accessors[times].count, 3), grow), "VEC3")
            clip.samplers.append(pygltflib.AnimationSampler(input=times, output=scale, interpolation="LINEAR"))
            clip.channels = [c for c in clip.channels if not (c.target.node == root and c.target.path == "scale")]
            clip.channels.append(pygltflib.AnimationChannel(sampler=len(clip.samplers) - 1,
                                                            target=pygltflib.AnimationChannelTarget(node=root, path="scale")))
        animations.append(clip)
    gltf.animations = animations
    gltf.buffers[0].byteLength = len(data)
    gltf.set_binary_blob(data)
    path = out / "character.glb"
    gltf.save_binary(str(path))
    return path


def _validate(sample: Path, character: Path, work: Path):
    inputs = BakeInputs(character=character, cloth=sample / "cloth.pc2", cloth_mesh=sample / "cloth.obj", textures=None,
                        cycle=None, name="clips", version="1.0", params=BakeParams())
    return stage_validate(inputs, work).record


def test_the_walk_the_cloth_followed_beats_the_same_walk_half_a_step_on(small_sample, tmp_path):
    """The sample's cloth was simulated on its walk. A character with that walk half a cycle on first and
    the walk second: both are 24 frames and loop, so the repeat gap ties (the first in the file was taken);
    the cloth follows the walk, and the bake takes it, saying why."""
    character = _with_animation_variants(small_sample / "character.glb", tmp_path, [("walk, half on", 0.5, 1.0), ("walk", 0.0, 1.0)])
    clips = character_clips(character)
    assert [(clip.name, clip.frames(FPS), clip.loops) for clip in clips] == [("walk, half on", 24, True), ("walk", 24, True)]
    from crowdbake.ingest.garment import read_cloth

    cloth = read_cloth(small_sample / "cloth.pc2", small_sample / "cloth.obj").frames
    assert choose_clip(clips, cloth, FPS).name == "walk, half on"  # the gap alone
    evidence = character_clip_evidence(character, [0, 1], cloth, FPS)
    assert evidence[1].follow > evidence[0].follow + 0.2

    job = _validate(small_sample, character, tmp_path / "work")
    assert job.params["animation"] == 1 and job.animation_choice["name"] == "walk"
    reason = job.animation_choice["reason"]
    assert "repeats best" in reason and "does not follow)" in reason
    assert f"follow {evidence[1].follow:.2f}" in reason and "% inside" in reason

    # `crowdbake cycle` chooses alike: the body it searches against is the walk's.
    from crowdbake.bake.skinning import pose_character
    from crowdbake.formats.gltf import load_character
    from crowdbake.stages.cycle_inputs import load_cycle_inputs

    inputs = load_cycle_inputs(small_sample / "cloth.pc2", small_sample / "cloth.obj", character=character)
    walk, _ = pose_character(load_character(character, animation="walk"), FPS, 24)
    assert inputs.cycle_frames == 24 and np.allclose(inputs.body[:24], walk, atol=1e-5)


def test_a_body_the_cloth_sits_inside_loses(small_sample, tmp_path):
    """The walk with the body grown by a third, first in the file: the cloth moves with it (the same
    motion) but sits inside it; the walk as simulated is taken."""
    character = _with_animation_variants(small_sample / "character.glb", tmp_path, [("walk, grown", 0.0, 1.35), ("walk", 0.0, 1.0)])
    from crowdbake.ingest.garment import read_cloth

    cloth = read_cloth(small_sample / "cloth.pc2", small_sample / "cloth.obj").frames
    evidence = character_clip_evidence(character, [0, 1], cloth, FPS)
    assert evidence[0].penetration > 2 * evidence[1].penetration + 0.05
    choice = choose_clip(character_clips(character), cloth, FPS, lambda indices: character_clip_evidence(character, indices, cloth, FPS))
    assert choice.name == "walk" and "rejected: inside the body" in choice.reason


@pytest.mark.parametrize("clip, first, last, gap_alone, rival", [
    ("Walking", 337, 492, "Wave", "Running"), ("Running", 515, 624, "Running", "Walking"), ("Idle", 0, 314, "Dance", "Dance")])
def test_robot_cape_frames_of_one_clip_pick_that_clip(shared_asset, clip, first, last, gap_alone, rival):
    """robot_clips' cape over the blend-free frames of one clip (from a frame where the clip starts over).
    The gap alone takes Wave (44 frames) for the Walking frames, and Dance, first in the file and as long
    as Idle (80 frames), for the Idle ones; Walking and Running (23 frames, both loop) tie. The cloth
    follows the clip that drove it, and `rival` (of the same length, or the gap's pick) is ruled out."""
    import re

    from crowdbake.ingest.garment import read_cloth

    glb = shared_asset("robot_clips/robot.glb")
    cloth = read_cloth(shared_asset("robot_clips/garment.pc2"), shared_asset("robot_clips/garment.obj")).frames[first:last + 1]
    clips = character_clips(glb)
    assert choose_clip(clips, cloth, FPS).name == gap_alone
    choice = choose_clip(clips, cloth, FPS, lambda indices: character_clip_evidence(glb, indices, cloth, FPS))
    assert choice.name == clip and "tie with it" not in choice.reason
    assert re.search(rf"'{rival}' \d+ frames [^()]*\([^)]*does not follow\)", choice.reason), choice.reason


def test_robot_cape_across_several_clips_follows_none_and_the_gap_decides(shared_asset):
    """The whole cache plays Idle, Walking, Running, Walking: the cloth follows no one clip over it, the
    evidence is set aside, and Walking and Running tie as before."""
    from crowdbake.ingest.garment import read_cloth

    glb = shared_asset("robot_clips/robot.glb")
    cloth = read_cloth(shared_asset("robot_clips/garment.pc2"), shared_asset("robot_clips/garment.obj")).frames
    choice = choose_clip(character_clips(glb), cloth, FPS, lambda indices: character_clip_evidence(glb, indices, cloth, FPS))
    assert choice.name in ("Walking", "Running") and "tie with it" in choice.reason
    assert "follows none of them" in choice.reason


def test_long_skirt_picks_cesium_mans_walk_over_it_half_a_cycle_on(shared_asset, tmp_path):
    """CesiumMan's walk and the same walk half a cycle on (48 frames each): the skirt simulated on the
    walk follows it (0.3) and not the other (below 0)."""
    from crowdbake.ingest.garment import read_cloth

    character = _with_animation_variants(shared_asset("CesiumMan.glb"), tmp_path, [("Walk, half on", 0.5, 1.0), ("Walk", 0.0, 1.0)])
    cloth = read_cloth(shared_asset("long_skirt/long_skirt.pc2"), shared_asset("long_skirt/long_skirt.obj")).frames
    choice = choose_clip(character_clips(character), cloth, FPS, lambda indices: character_clip_evidence(character, indices, cloth, FPS))
    assert choice.name == "Walk" and "does not follow)" in choice.reason


def test_a_tie_on_the_gap_goes_to_the_clip_the_cloth_follows_best():
    """Two 24-frame clips the cloth repeats after alike and neither ruled out (follows 0.40 and 0.50, less
    than FOLLOW_MARGIN apart): the better followed wins, and the reason says why; evidence alike leaves a
    tie, named as before."""
    from crowdbake.ingest.clip_choice import Clip

    t = np.arange(72)[:, None]
    cloth = np.random.default_rng(2).normal(size=(1, 30, 3)) + np.stack([np.sin(2 * np.pi * t / 24) * np.linspace(0, 0.3, 30)] * 3, axis=2)
    clips = [Clip("run", 1.0), Clip("walk", 1.0)]
    choice = choose_clip(clips, cloth, FPS, lambda indices: {0: ClipEvidence(0.01, 0.40, 16), 1: ClipEvidence(0.01, 0.50, 16)})
    assert choice.name == "walk" and "'run' repeats alike" in choice.reason and "follows 'walk' best" in choice.reason
    assert "rejected" not in choice.reason and "tie with it" not in choice.reason
    alike = choose_clip(clips, cloth, FPS, lambda indices: {k: ClipEvidence(0.01, 0.5, 16) for k in indices})
    assert alike.name == "run" and "'walk' tie with it" in alike.reason
