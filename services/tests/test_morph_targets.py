"""glTF morph targets are applied when a character is posed: bind pose + sum_i w_i(t) * delta_i, then skinned.

Regression: the reader dropped every primitive's `targets` with a warning, so a face animated by its
weights (RobotExpressive's head has Angry, Surprised and Sad) baked frozen. The targets, the mesh's
default weights and the animation's "weights" channels (LINEAR, STEP, CUBICSPLINE) are now kept; what
cannot be applied is refused naming the mesh and the target.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from crowdbake.bake.skinning import joint_matrices, pose_character, skin
from crowdbake.formats.gltf import AnimationChannel, Character, encode_character, load_character
from repo_paths import SHARED_ASSETS

ROBOT = SHARED_ASSETS / "robot_clips" / "robot.glb"
needs_robot = pytest.mark.skipif(not ROBOT.exists(), reason=f"the shared robot (robot_clips/robot.glb) is not in {SHARED_ASSETS}")

# A quad: vertices 0, 1 on the root joint (never moves), 2, 3 on the tip joint, lifted by (0, t, 0) at t s.
QUAD = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
# Two targets: "Lift" raises every vertex in z; "Spread" moves x apart and tilts the normals of 2 and 3.
LIFT = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1]], np.float32)
SPREAD = np.array([[-0.5, 0, 0], [0.5, 0, 0], [-0.5, 0, 0], [0.5, 0, 0]], np.float32)
SPREAD_NORMALS = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [1, 0, 0]], np.float32)
KEY_TIMES = np.array([0.0, 1.0, 2.0], np.float32)
KEY_WEIGHTS = np.array([[0.0, 1.0], [1.0, 0.0], [0.5, 0.5]], np.float32)  # (keys, targets)


def _quad_character() -> Character:
    return Character(
        positions=QUAD.copy(),
        normals=np.tile([0, 0, 1], (4, 1)).astype(np.float32),
        uvs=np.zeros((4, 2), np.float32),
        faces=np.array([[0, 1, 2], [1, 3, 2]], np.uint32),
        joints=np.array([[0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0]], np.uint16),
        weights=np.array([[1, 0, 0, 0]] * 4, np.float32),
        joint_names=["root", "tip"],
        joint_parents=np.array([-1, 0]),
        joint_parent_transforms=np.tile(np.eye(4), (2, 1, 1)),
        inverse_bind_matrices=np.stack([np.eye(4), np.linalg.inv(np.array([[1, 0, 0, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1.0]]))]).astype(np.float32),
        rest_translations=np.array([[0, 0, 0], [0, 1, 0]], float),
        rest_rotations=np.array([[0, 0, 0, 1], [0, 0, 0, 1]], float),
        rest_scales=np.ones((2, 3)),
        channels=[AnimationChannel(1, "translation", np.array([0, 2], np.float32), np.array([[0, 1, 0], [0, 3, 0]], np.float32))],
        animation_duration=2.0,
    )


def _view(gltf: pygltflib.GLTF2, data: bytes) -> int:
    """Append `data` to the GLB's BIN chunk (4-byte aligned) as a new bufferView; returns its index."""
    blob = gltf.binary_blob() or b""
    blob += b"\0" * (-len(blob) % 4)
    gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
    gltf.set_binary_blob(blob + data)
    gltf.buffers[0].byteLength = len(blob) + len(data)
    return len(gltf.bufferViews) - 1


def _accessor(gltf: pygltflib.GLTF2, array: np.ndarray, kind: str) -> int:
    """`array` (float32) as a new accessor of type `kind`; returns its index."""
    array = np.ascontiguousarray(array, np.float32)
    count = len(array) if kind != "SCALAR" else array.size
    rows = array.reshape(count, -1)
    gltf.accessors.append(pygltflib.Accessor(bufferView=_view(gltf, array.tobytes()), componentType=pygltflib.FLOAT, count=count, type=kind,
                                             min=rows.min(0).tolist(), max=rows.max(0).tolist()))
    return len(gltf.accessors) - 1


def _sparse_accessor(gltf: pygltflib.GLTF2, count: int, indices: np.ndarray, values: np.ndarray) -> int:
    """A VEC3 accessor of `count` zeros but `values` (k, 3) at `indices` (k,): a sparse block, no bufferView."""
    sparse = pygltflib.Sparse(
        count=len(indices),
        indices=pygltflib.AccessorSparseIndices(bufferView=_view(gltf, np.asarray(indices, "<u4").tobytes()), componentType=pygltflib.UNSIGNED_INT),
        values=pygltflib.AccessorSparseValues(bufferView=_view(gltf, np.asarray(values, "<f4").tobytes())))
    gltf.accessors.append(pygltflib.Accessor(componentType=pygltflib.FLOAT, count=count, type="VEC3", sparse=sparse,
                                             min=[0.0, 0.0, 0.0], max=np.asarray(values).max(0).tolist()))
    return len(gltf.accessors) - 1


def _write_quad(tmp_path: Path, interpolation: str | None = "LINEAR", default=(0.0, 0.0), weights_output=None,
                spread_count: int = 4, sparse_lift: bool = False) -> Path:
    """The quad as a .glb with the two targets (names in extras.targetNames), the mesh's default
    weights, and (unless interpolation is None) a weights channel keyed at KEY_TIMES."""
    gltf = pygltflib.GLTF2.load_from_bytes(encode_character(_quad_character()))
    mesh_node = next(k for k, node in enumerate(gltf.nodes) if node.mesh is not None)
    mesh = gltf.meshes[gltf.nodes[mesh_node].mesh]
    lift = _sparse_accessor(gltf, 4, np.array([2, 3]), LIFT[2:]) if sparse_lift else _accessor(gltf, LIFT, "VEC3")
    spread = _accessor(gltf, SPREAD[:spread_count], "VEC3")
    spread_normals = _accessor(gltf, SPREAD_NORMALS, "VEC3")
    mesh.primitives[0].targets = [{"POSITION": lift}, {"POSITION": spread, "NORMAL": spread_normals}]
    mesh.weights = list(default)
    mesh.extras = {"targetNames": ["Lift", "Spread"]}
    if interpolation is not None:
        output = KEY_WEIGHTS if weights_output is None else weights_output
        animation = gltf.animations[0]
        animation.samplers.append(pygltflib.AnimationSampler(input=_accessor(gltf, KEY_TIMES, "SCALAR"),
                                                             output=_accessor(gltf, output.reshape(-1), "SCALAR"), interpolation=interpolation))
        animation.channels.append(pygltflib.AnimationChannel(sampler=len(animation.samplers) - 1,
                                                             target=pygltflib.AnimationChannelTarget(node=mesh_node, path="weights")))
    path = tmp_path / f"quad_{interpolation}.glb"
    gltf.save_binary(str(path))
    return path


def _expected(times: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Known by construction: root vertices stay, tip vertices rise with the joint ((0, 1 + t, 0) from
    (0, 1, 0) at rest), each plus the weighted displacements. times (F,), weights (F, 2) -> (F, 4, 3)."""
    morphed = QUAD[None] + weights[:, 0, None, None] * LIFT[None] + weights[:, 1, None, None] * SPREAD[None]
    lift = np.zeros((len(times), 4, 3))
    lift[:, 2:, 1] = times[:, None]
    return morphed + lift


def test_linear_weights_move_the_bind_pose_before_skinning(tmp_path, caplog):
    with caplog.at_level(logging.INFO):
        character = load_character(_write_quad(tmp_path, "LINEAR"))
    assert [t.name for t in character.morph_targets] == ["Lift", "Spread"]
    assert any("Lift, Spread" in r.getMessage() for r in caplog.records)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    with pytest.raises(ValueError, match=r"2 morph targets \(Lift, Spread\), which encode_character does not write"):
        encode_character(character)
    times = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    posed, normals = pose_character(character, 2.0, 5)
    weights = np.array([[0, 1], [0.5, 0.5], [1, 0], [0.75, 0.25], [0.5, 0.5]])
    np.testing.assert_allclose(posed, _expected(times, weights), atol=1e-5)
    # The tilted normals of 2 and 3: (0, 0, 1) + w * (1, 0, 0), renormalised; 0 and 1 keep theirs.
    tilt = np.stack([weights[:, 1], np.zeros(5), np.ones(5)], axis=1)
    np.testing.assert_allclose(normals[:, 2], tilt / np.linalg.norm(tilt, axis=1, keepdims=True), atol=1e-5)
    np.testing.assert_allclose(normals[:, 0], np.tile([0, 0, 1.0], (5, 1)), atol=1e-6)


def test_step_weights_hold_until_the_next_key(tmp_path):
    character = load_character(_write_quad(tmp_path, "STEP"))
    posed, _ = pose_character(character, 4.0, 8)  # t = 0, 0.25, ..., 1.75
    times = np.arange(8) / 4.0
    weights = np.where(times[:, None] < 1.0, KEY_WEIGHTS[0], KEY_WEIGHTS[1])
    np.testing.assert_allclose(posed, _expected(times, weights), atol=1e-5)


def test_cubic_spline_weights_read_in_value_out_triples(tmp_path):
    # Zero tangents: the Hermite curve passes each key with zero slope, halfway at the middle of a span.
    triples = np.zeros((3, 3, 2), np.float32)
    triples[:, 1] = KEY_WEIGHTS
    character = load_character(_write_quad(tmp_path, "CUBICSPLINE", weights_output=triples))
    posed, _ = pose_character(character, 2.0, 3)  # t = 0, 0.5, 1
    weights = np.array([KEY_WEIGHTS[0], (KEY_WEIGHTS[0] + KEY_WEIGHTS[1]) / 2, KEY_WEIGHTS[1]])
    np.testing.assert_allclose(posed, _expected(np.array([0, 0.5, 1.0]), weights), atol=1e-5)


def test_default_weights_apply_without_a_channel(tmp_path):
    character = load_character(_write_quad(tmp_path, None, default=(0.25, 1.0)))
    np.testing.assert_allclose(character.morph_weights, [0.25, 1.0])
    posed, _ = pose_character(character, 1.0, 2)
    np.testing.assert_allclose(posed, _expected(np.array([0.0, 1.0]), np.array([[0.25, 1.0]] * 2)), atol=1e-5)


def test_a_sparse_target_moves_only_its_vertices(tmp_path):
    character = load_character(_write_quad(tmp_path, None, default=(1.0, 0.0), sparse_lift=True))
    np.testing.assert_array_equal(character.morph_targets[0].positions, np.where(np.arange(4)[:, None] >= 2, LIFT, 0))
    posed, _ = pose_character(character, 1.0, 1)
    np.testing.assert_allclose(posed[0], QUAD + np.where(np.arange(4)[:, None] >= 2, LIFT, 0), atol=1e-6)


def test_targets_that_cannot_be_applied_are_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match=r"morph target 'Spread' of meshes\[0\]: POSITION is \(3, 3\)"):
        load_character(_write_quad(tmp_path, "LINEAR", spread_count=3))
    with pytest.raises(ValueError, match=r"weights output has 3 values, expected 3 keys x 2 morph targets"):
        load_character(_write_quad(tmp_path, "LINEAR", weights_output=np.array([0.0, 1.0, 0.5], np.float32)))


def _robot_with_angry_ramp(tmp_path: Path) -> tuple[Path, np.ndarray]:
    """The robot with its Dance clip's weights channel rewritten so Angry ramps 0 -> 1 over the clip
    (the file's own clips hold every weight at 0). Returns the file and the key times."""
    gltf = pygltflib.GLTF2().load(str(ROBOT))
    dance = next(a for a in gltf.animations if a.name == "Dance")
    channel = next(c for c in dance.channels if c.target.path == "weights")
    sampler = dance.samplers[channel.sampler]
    blob = bytearray(gltf.binary_blob())

    def view(index: int) -> tuple[int, int]:
        accessor = gltf.accessors[index]
        return (gltf.bufferViews[accessor.bufferView].byteOffset or 0) + (accessor.byteOffset or 0), accessor.count

    start, count = view(sampler.input)
    times = np.frombuffer(bytes(blob[start : start + 4 * count]), "<f4")
    start, count = view(sampler.output)
    ramp = np.zeros((len(times), 3), np.float32)
    ramp[:, 0] = times / times[-1]
    assert count == ramp.size and sampler.interpolation == "LINEAR"
    blob[start : start + 4 * count] = ramp.tobytes()
    gltf.set_binary_blob(bytes(blob))
    path = tmp_path / "robot_angry.glb"
    gltf.save_binary(str(path))
    return path, times


@needs_robot
def test_the_robots_head_targets_are_kept_without_a_warning(caplog):
    with caplog.at_level(logging.WARNING):
        character = load_character(ROBOT, animation="Dance")
    assert not [r for r in caplog.records if "morph" in r.getMessage() or "target" in r.getMessage()]
    assert [t.name for t in character.morph_targets] == ["Angry", "Surprised", "Sad"]
    assert len(character.weight_channels) == 1 and character.weight_channels[0].count == 3
    # Each moves the face by a few percent of the bind-space mesh (the robot is bound at 1/65 scale).
    size = np.ptp(character.positions, axis=0).max()
    assert all(np.abs(t.positions).max() > 0.02 * size for t in character.morph_targets)


@needs_robot
def test_the_robots_head_moves_by_what_its_weights_say(tmp_path):
    path, key_times = _robot_with_angry_ramp(tmp_path)
    character = load_character(path, animation="Dance")
    angry = character.morph_targets[0]
    head = slice(angry.start, angry.start + len(angry.positions))
    times = np.array([0.0, float(key_times[-1]) / 2])
    posed, _ = pose_character(character, 1.0 / times[1], 2)
    # Expected: the bind pose plus w(t) * Angry, skinned by the same joints; w(0) = 0 and w(middle) = 1/2.
    matrices = joint_matrices(character, times)
    for frame, weight in enumerate((0.0, 0.5)):
        bind = character.positions.copy()
        bind[head] += weight * angry.positions
        expected, _ = skin(bind, character.normals, character.joints, character.weights, matrices[frame : frame + 1])
        np.testing.assert_allclose(posed[frame], expected[0], atol=1e-5)
    # The face moved: without the target the middle frame's head is where the file's own clip put it.
    unmorphed, _ = skin(character.positions, character.normals, character.joints, character.weights, matrices[1:])
    moved = np.linalg.norm(posed[1][head] - unmorphed[0][head], axis=1)
    assert moved.max() > 0.25 * np.linalg.norm(angry.positions, axis=1).max()
    assert np.allclose(posed[1][: angry.start], unmorphed[0][: angry.start], atol=1e-6)
