"""A skinned body (CBSK) exported as a glTF skin (crowdbake.export.body_skin): checked on synthetic skins whose
answer is known, then written to a .glb that the Khronos glTF-Validator reads and that our own glTF skinning
plays back. The real bakes' skinned bodies are checked in test_export.py (the sample) and
test_export_clips.py (the robot)."""
from __future__ import annotations

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from test_export import MORPH_TOLERANCE_M, node_tool, skin_played
from crowdbake.export.animations import animation_plans
from crowdbake.export.body_skin import CORRECTIVE_BOUND_M, corrective_step, decompose, gltf_skin, play, trs_matrices, why_not_a_skin
from crowdbake.export.glb import GlbMaterial, GlbPart, GlbVariant, build_glb
from crowdbake.formats.ranges import Clip, Ranges, Transition
from crowdbake.formats.skinned_cache import SkinnedPoseCache, weight_codes


def two_bone_strip(matrices: np.ndarray) -> SkinnedPoseCache:
    """A strip of 8 vertices along +Y weighed from joint 0 (bottom) to joint 1 (top), posed by (F, 2, 3, 4) matrices."""
    y = np.linspace(0.0, 1.0, 8)
    rest = np.stack([np.where(np.arange(8) % 2, 0.1, -0.1), y, np.zeros(8)], axis=1).astype(np.float32)
    normals = np.tile(np.float32([0.0, 0.0, 1.0]), (8, 1))
    joints = np.tile(np.uint16([0, 1, 0, 0]), (8, 1))
    weights = np.stack([1.0 - y, y, np.zeros(8), np.zeros(8)], axis=1)
    weights[0, 1] = 0.0
    weights[0, 0] = 1.0
    indices = np.array([[k, k + 1, k + 2] for k in range(6)], dtype=np.uint32)
    return SkinnedPoseCache(indices, np.zeros((8, 2), np.float32), rest, normals, joints, weight_codes(weights), np.asarray(matrices, np.float32), 24.0)


def pose(angle_deg: float, axis: str, translation, scale: float = 1.0) -> np.ndarray:
    """(3, 4) a rotation about `axis` times a uniform scale, then a translation."""
    matrix = np.zeros((3, 4))
    matrix[:, :3] = Rotation.from_euler(axis, angle_deg, degrees=True).as_matrix() * scale
    matrix[:, 3] = translation
    return matrix


def test_trs_takes_a_rotation_and_scale_apart_exactly_and_measures_shear():
    matrix = pose(40.0, "z", [0.1, 0.2, 0.3])
    matrix[:, :3] = matrix[:, :3] * [1.0, 2.0, 0.5]  # non-uniform scale in the joint's own axes
    t, r, s, error = decompose(matrix[None])
    np.testing.assert_allclose(trs_matrices(t, r, s)[0], matrix, atol=1e-12)
    assert error[0] < 1e-12 and r[0, 3] >= 0
    blend = (pose(90.0, "z", [0, 0, 0]) + pose(90.0, "x", [0, 0, 0])) / 2  # two poses about two axes mixed: sheared
    assert decompose(blend[None])[3][0] > 0.1


def test_a_blended_frame_gets_a_corrective_target_and_every_frame_plays_exactly():
    """Frames 0 and 1 are rigid poses (joint 1 at scale 100, as the robot's), frame 2 their matrices' mean (a
    crossfade): it alone carries a corrective target, and the rest plus that target skinned by the joints'
    TRS gives every frame of the cache, the target's deltas on a power-of-two grid (float32 with zero low bits)
    within CORRECTIVE_BOUND_M once skinned, at scale 100 too."""
    rigid = [np.stack([pose(0.0, "z", [0, 0, 0]), pose(10.0, "x", [0, 0.5, 0], 100.0)]),
             np.stack([pose(30.0, "y", [0.2, 0, 0]), pose(-70.0, "y", [0, 0.6, 0.1], 100.0)])]
    cache = two_bone_strip(np.stack([*rigid, (rigid[0] + rigid[1]) / 2]))
    assert why_not_a_skin(cache) is None
    skin = gltf_skin(cache)
    assert skin.corrected.tolist() == [2] and skin.animated.tolist() == [0, 1]
    played = play(skin, np.arange(3))
    np.testing.assert_allclose(played[:2], cache.positions[:2], atol=1e-5)
    error = np.linalg.norm(played[2] - cache.positions[2], axis=-1).max()
    assert error <= CORRECTIVE_BOUND_M and error > CORRECTIVE_BOUND_M / 100  # rounded, within the bound
    deltas = skin.position_deltas[0].astype(np.float64)
    grid = max(e for e in range(-40, 0) if not np.any(deltas / 2.0 ** e % 1))  # the coarsest power of two every delta is a multiple of
    assert 2.0 ** grid >= corrective_step(100.0 * np.sqrt(3))  # joint 1's block at scale 100 (Frobenius norm 173)
    assert np.abs(skin.position_deltas[0]).max() > 1e-3  # the blend really needed it
    assert corrective_step(100.0, 1e-4) <= 2e-4 / (np.sqrt(3) * 100) < 2 * corrective_step(100.0, 1e-4)


def test_a_joint_that_mirrors_space_keeps_morph_targets():
    mirrored = pose(0.0, "z", [0, 0, 0])
    mirrored[:, 0] *= -1
    cache = two_bone_strip(np.stack([np.stack([pose(0.0, "z", [0, 0, 0]), mirrored])]))
    assert "mirrors" in why_not_a_skin(cache)


def test_a_skinned_glb_validates_and_plays_every_clip_and_transition(tmp_path):
    """The strip in a .glb of two clips and a transition: the validator finds nothing, the body has no morph
    target but its blended frame's, and each animation played at its keys gives the cache's frames."""
    frames = [np.stack([pose(10.0 * k, "xyz"[k % 3], [0.01 * k, 0, 0]), pose(-15.0 * k, "yzx"[k % 3], [0, 0.5, 0])]) for k in range(6)]
    frames[4] = (frames[3] + frames[5]) / 2  # the transition's frame: a crossfade
    cache = two_bone_strip(np.stack(frames))
    # Clip a = frames 0..1, b = 2..3, a -> b = frame 4 (leaving a at its frame 1, arriving at b's 0); 5 unused.
    ranges = Ranges(6, (Clip("a", 0, 2, 0, 2, "none", 0.0, 0.0), Clip("b", 2, 2, 0, 2, "none", 0.0, 0.0)),
                    (Transition(0, 1, 1, 0, 4, 1, 0, 1, 0.0, 0.0),))
    plans = animation_plans(ranges)
    skin = gltf_skin(cache)
    assert skin.corrected.tolist() == [4]
    part = GlbPart("body", "body", 0, cache.positions, cache.normals, cache.uvs, np.zeros((8, 2), np.float32), cache.indices, skin=skin)
    png = bytes.fromhex("89504e470d0a1a0a0000000d4948445200000001000000010802000000907753de0000000c4944415408d763f8cfc000000301010018dd8db00000000049454e44ae426082")
    data = build_glb([part], [GlbMaterial("body", [("image/png", png)])], [GlbVariant("look_0", 0, 0)], 24.0, {}, plans)
    gltf = pygltflib.GLTF2.load_from_bytes(data)
    blob = gltf.binary_blob()
    mesh = gltf.meshes[0]
    assert len(mesh.primitives[0].targets) == 1 and mesh.extras["targetNames"] == ["frame_4"] and len(gltf.skins) == 1
    for plan, animation in zip(plans, gltf.animations, strict=True):
        played = skin_played(gltf, blob, 0, animation, range(plan.key_count))
        assert np.abs(played - cache.positions[plan.keys]).max() < MORPH_TOLERANCE_M, plan.name
    out = tmp_path / "skin.glb"
    out.write_bytes(data)
    (report,) = node_tool("validate-gltf.mjs", out)
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"][:5]


def test_a_skin_no_smaller_than_its_morph_targets_keeps_them():
    """The export's rule (writer.body_skin): 8 vertices cost 12 bytes a frame as morph targets, 40 once as a
    skin, but 2 joints keyed at 30 keys cost 2,400 more: the strip keeps its morph targets, and says why."""
    from crowdbake.export.writer import body_skin

    cache = two_bone_strip(np.stack([np.stack([pose(5.0 * k, "z", [0, 0, 0]), pose(0.0, "x", [0, 0.5, 0])]) for k in range(3)]))
    skin, refused = body_skin(cache, key_count=30)
    assert skin is None and "bytes" in refused
    many_frames = two_bone_strip(np.stack([np.stack([pose(5.0 * k, "z", [0, 0, 0]), pose(0.0, "x", [0, 0.5, 0])]) for k in range(60)]))
    skin, refused = body_skin(many_frames, key_count=2)  # 528 + 2 * 80 bytes against 12 * 8 * 61 = 5,856
    assert skin is not None and refused is None
