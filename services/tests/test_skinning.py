"""Keyframe sampling and linear blend skinning: small cases with known answers, then CesiumMan."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake.skinning import (
    joint_matrices,
    joint_world_matrices,
    pose_character,
    sample_channel,
    skin,
    slerp,
)
from crowdbake.geometry import quaternion_matrices
from crowdbake.formats.gltf import AnimationChannel, Character, load_character


def _about_z(degrees: float) -> np.ndarray:
    half = np.radians(degrees) / 2
    return np.array([0.0, 0.0, np.sin(half), np.cos(half)])


def test_slerp_endpoints_midpoint_and_short_way_round():
    q0, q1 = _about_z(0)[None], _about_z(90)[None]
    np.testing.assert_allclose(slerp(q0, q1, np.array([0.0])), q0, atol=1e-12)
    np.testing.assert_allclose(slerp(q0, q1, np.array([1.0])), q1, atol=1e-12)
    np.testing.assert_allclose(slerp(q0, q1, np.array([0.5])), _about_z(45)[None], atol=1e-12)
    # -q1 is the same rotation; slerp must not take the 270-degree path.
    np.testing.assert_allclose(np.abs(slerp(q0, -q1, np.array([0.5]))), _about_z(45)[None], atol=1e-12)
    # Nearly equal keys fall back to a normalised lerp without dividing by ~0.
    almost = _about_z(1e-6)[None]
    assert np.isfinite(slerp(q0, almost, np.array([0.3]))).all()


def test_sample_channel_interpolations():
    times = np.array([0.0, 1.0, 2.0], dtype=np.float32)
    values = np.array([[0, 0, 0], [2, 0, 0], [2, 4, 0]], dtype=np.float32)
    linear = AnimationChannel(0, "translation", times, values, "LINEAR")
    np.testing.assert_allclose(sample_channel(linear, [-1.0, 0.5, 1.5, 3.0]), [[0, 0, 0], [1, 0, 0], [2, 2, 0], [2, 4, 0]])
    step = AnimationChannel(0, "translation", times, values, "STEP")
    np.testing.assert_allclose(sample_channel(step, [0.5, 1.0, 1.99, 2.5]), [[0, 0, 0], [2, 0, 0], [2, 0, 0], [2, 4, 0]])
    # Cubic spline with zero tangents: value(s) = v0 + (3s^2 - 2s^3)(v1 - v0).
    cubic_values = np.zeros((3, 3, 3), dtype=np.float32)
    cubic_values[:, 1] = values
    cubic = AnimationChannel(0, "translation", times, cubic_values, "CUBICSPLINE")
    np.testing.assert_allclose(sample_channel(cubic, [0.25]), [[2 * (3 * 0.0625 - 2 * 0.015625), 0, 0]], atol=1e-6)
    # Rotations are slerped.
    rotation = AnimationChannel(0, "rotation", times[:2], np.stack([_about_z(0), _about_z(120)]).astype(np.float32))
    np.testing.assert_allclose(sample_channel(rotation, [0.25]), _about_z(30)[None], atol=1e-6)


def _chain() -> Character:
    """Two joints on the x axis, 1 m apart; the root turns 90 degrees about z over 1 s."""
    identity = np.tile(np.eye(4), (2, 1, 1))
    inverse_bind = identity.copy()
    inverse_bind[1, 0, 3] = -1.0
    positions = np.array([[0.0, 0.1, 0], [1.0, 0.1, 0], [2.0, 0.0, 0]], dtype=np.float32)
    return Character(
        positions=positions,
        normals=np.tile([0.0, 1.0, 0.0], (3, 1)).astype(np.float32),
        uvs=np.zeros((3, 2), np.float32),
        faces=np.array([[0, 1, 2]], np.uint32),
        joints=np.array([[0, 0, 0, 0], [0, 1, 0, 0], [1, 0, 0, 0]], np.uint16),
        weights=np.array([[1, 0, 0, 0], [0.5, 0.5, 0, 0], [1, 0, 0, 0]], np.float32),
        joint_names=["root", "child"],
        joint_parents=np.array([-1, 0]),
        joint_parent_transforms=identity,
        inverse_bind_matrices=inverse_bind.astype(np.float32),
        rest_translations=np.array([[0.0, 0, 0], [1.0, 0, 0]]),
        rest_rotations=np.array([[0.0, 0, 0, 1], [0.0, 0, 0, 1]]),
        rest_scales=np.ones((2, 3)),
        channels=[AnimationChannel(0, "rotation", np.array([0, 1], np.float32), np.stack([_about_z(0), _about_z(90)]).astype(np.float32))],
        animation_duration=1.0,
    )


def test_joint_world_matrices_follow_the_hierarchy():
    world = joint_world_matrices(_chain(), np.array([0.0, 1.0]))
    np.testing.assert_allclose(world[0, 1, :3, 3], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(world[1, 1, :3, 3], [0, 1, 0], atol=1e-12)  # child swung round with its parent
    np.testing.assert_allclose(world[1, 0, :3, :3], quaternion_matrices(_about_z(90)), atol=1e-12)


def test_skinning_blends_and_keeps_the_bind_pose():
    character = _chain()
    posed, normals = pose_character(character, fps=1.0, frame_count=2)
    np.testing.assert_allclose(posed[0], character.positions, atol=1e-6)  # at rest, skinning is the identity
    # After 90 degrees about z at the root, everything bound to either joint turns rigidly: (x, y) -> (-y, x).
    np.testing.assert_allclose(posed[1], [[-0.1, 0, 0], [-0.1, 1, 0], [0, 2, 0]], atol=1e-6)
    np.testing.assert_allclose(normals[1], np.tile([-1, 0, 0], (3, 1)), atol=1e-6)


def test_skin_blends_matrices_linearly():
    positions = np.array([[0.0, 0.0, 0.0]], np.float32)
    normals = np.array([[0.0, 1.0, 0.0]], np.float32)
    matrices = np.tile(np.eye(4, dtype=np.float32), (1, 2, 1, 1))
    matrices[0, 1, :3, 3] = [2.0, 0.0, 0.0]
    out, _ = skin(positions, normals, np.array([[0, 1, 0, 0]]), np.array([[0.25, 0.75, 0, 0]], np.float32), matrices)
    np.testing.assert_allclose(out[0, 0], [1.5, 0, 0], atol=1e-6)


def test_normals_use_the_inverse_transpose():
    """Under a non-uniform scale, a normal must stay perpendicular to the scaled surface."""
    tangent = np.array([1.0, 1.0, 0.0])
    normal = np.array([[1.0, -1.0, 0.0]], np.float32) / np.sqrt(2)
    matrices = np.tile(np.eye(4, dtype=np.float32), (1, 1, 1, 1))
    matrices[0, 0, 0, 0] = 3.0  # stretch x
    _, out = skin(np.zeros((1, 3), np.float32), normal, np.zeros((1, 4), int), np.array([[1, 0, 0, 0]], np.float32), matrices)
    scaled_tangent = np.array([3.0, 1.0, 0.0])
    assert abs(out[0, 0] @ scaled_tangent) < 1e-6
    assert abs(out[0, 0] @ tangent) > 0.1  # and it did change
    np.testing.assert_allclose(np.linalg.norm(out[0, 0]), 1.0, atol=1e-6)


def test_skin_validates_shapes():
    with pytest.raises(ValueError, match="joints and weights"):
        skin(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((3, 4), int), np.zeros((2, 4)), np.zeros((1, 1, 4, 4)))
    with pytest.raises(ValueError, match="joint indices"):
        skin(np.zeros((1, 3)), np.zeros((1, 3)), np.full((1, 4), 5), np.ones((1, 4)) / 4, np.zeros((1, 2, 4, 4)))
    with pytest.raises(ValueError, match="fps"):
        pose_character(_chain(), fps=0.0, frame_count=3)


def test_cesium_man_walk_is_plausible(shared_asset):
    """CesiumMan's 2 s walk at 24 fps: a ~1.5 m tall person, Y up, feet that move, a loop that closes."""
    character = load_character(shared_asset("CesiumMan.glb"))
    positions, normals = pose_character(character, fps=24.0, frame_count=49)
    assert positions.shape == (49, 3273, 3)
    heights = positions[..., 1].max(axis=1) - positions[..., 1].min(axis=1)
    assert np.all((heights > 1.35) & (heights < 1.65)), heights
    assert positions[..., 1].min() > -0.1  # standing on y = 0, not upside down or Z-up
    # The animation loops: frame 48 (t = 2 s) is frame 0.
    np.testing.assert_allclose(positions[48], positions[0], atol=1e-4)
    # Feet move: the lowest vertices travel back and forth by several centimetres.
    feet = positions[0, :, 1] < 0.1
    travel = np.ptp(positions[:, feet, 2].mean(axis=1))
    assert travel > 0.03
    # Skinning keeps the surface together: edge lengths stay within a plausible band.
    faces = character.faces.astype(int)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    rest = np.linalg.norm(np.diff(character.positions[edges], axis=1)[:, 0], axis=1)
    posed = np.linalg.norm(np.diff(positions[24][edges], axis=1)[:, 0], axis=1)
    ratio = posed[rest > 1e-6] / rest[rest > 1e-6]
    assert 0.6 < np.percentile(ratio, 1) and np.percentile(ratio, 99) < 1.5
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-4)
    matrices = joint_matrices(character, np.array([0.0]))
    assert matrices.dtype == np.float32 and matrices.shape == (1, 19, 4, 4)
