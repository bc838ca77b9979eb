"""The export's vertex-animation textures (crowdbake.export.vat) on small synthetic data whose answer is known:
the layout, the octahedral normal word, vertex frames, a skinned body's rest pose and joint matrices played
back as the shaders play them, and a coarser LOD found among a finer LOD's vertices."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from crowdbake.export.vat import (
    OCTAHEDRAL_MAX_ERROR_DEG,
    POSITION_BOUND_M,
    SKIN_BLOCKS,
    UNORM16_MAX,
    decode_joints,
    decode_octahedral_words,
    decode_skin,
    decode_vat,
    encode_joints,
    encode_skin,
    encode_vat,
    octahedral_words,
    play_skin,
    position_steps,
    shared_skin_vertices,
    shared_vertices,
    vat_layout,
    vat_texcoords,
)
from crowdbake.formats.skinned_cache import skin_frames, weight_codes


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1), -1, 1)))


def sphere(count: int) -> np.ndarray:
    """`count` unit vectors spread evenly over the sphere (a Fibonacci lattice), the poles and the octahedron's
    folds included."""
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    phi = np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z * z)
    axes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 0], [1, 0, -1], [0, -1, -1]], float)
    return np.concatenate([np.stack([r * np.cos(phi), r * np.sin(phi), z], 1), axes / np.linalg.norm(axes, axis=1, keepdims=True)])


def test_vat_layout_wraps_wide_meshes_into_rows_per_frame():
    layout = vat_layout(vertex_count=5000, frame_count=3, max_width=2048)
    assert (layout.width, layout.rows_per_frame, layout.height) == (2048, 3, 9)
    coords = vat_texcoords(layout)
    # Vertex 2048 starts the second row of frame 0; its texel centre is (0.5, 1.5) texels.
    np.testing.assert_allclose(coords[2048] * [layout.width, layout.height], [0.5, 1.5])
    # Another LOD's vertices reading these texels get the same coordinates for the same vertices.
    np.testing.assert_array_equal(vat_texcoords(layout, [2048, 7]), coords[[2048, 7]])
    with pytest.raises(ValueError):
        vat_layout(0, 3)


def test_octahedral_words_keep_every_direction_within_the_stated_angle():
    """8 bits a coordinate: over a dense sphere every normal comes back within OCTAHEDRAL_MAX_ERROR_DEG, and
    the bound is tight (some normal is more than half of it away)."""
    normals = sphere(200_000)
    words = octahedral_words(normals)
    assert words.dtype == np.uint16
    error = angles_deg(decode_octahedral_words(words), normals)
    assert error.max() <= OCTAHEDRAL_MAX_ERROR_DEG and error.max() > OCTAHEDRAL_MAX_ERROR_DEG / 2


def test_vat_positions_lie_on_a_power_of_two_grid_within_the_distance_bound():
    """Each axis's codes are multiples of a power of two (position_steps), the coarsest whose half step keeps
    a decoded position within POSITION_BOUND_M of its own as a distance (a 2 m cape: 8 codes, 0.125 mm per
    axis); the bound is reached in practice, and bound 0 keeps the plain 16 bits."""
    rng = np.random.default_rng(11)
    positions = rng.uniform([-1.0, 0.0, -0.7], [1.0, 2.2, 0.8], size=(6, 400, 3))
    normals = rng.normal(size=(6, 400, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    animation = encode_vat(positions, normals)
    extent = animation.bounds_max - animation.bounds_min
    assert animation.steps.tolist() == position_steps(extent).tolist() == [8, 8, 8]
    codes = animation.texels.reshape(6, -1, 4)[:, :400, :3].astype(np.int64)
    assert not ((codes % animation.steps) * (codes != UNORM16_MAX)).any()
    distance = np.linalg.norm(decode_vat(animation)[0] - positions, axis=-1)
    assert distance.max() <= POSITION_BOUND_M and distance.max() > POSITION_BOUND_M / 2
    assert (np.abs(decode_vat(animation)[0] - positions).max(axis=(0, 1)) <= animation.max_position_error + 1e-12).all()
    assert (animation.max_position_error * np.sqrt(3) <= POSITION_BOUND_M).all()
    # Each step is the coarsest: twice it would break the per-axis share of the bound.
    assert (2 * animation.steps * extent / (2 * UNORM16_MAX) > POSITION_BOUND_M / np.sqrt(3)).all()
    plain = encode_vat(positions, normals, bound_m=0)
    assert plain.steps.tolist() == [1, 1, 1] and (np.abs(decode_vat(plain)[0] - positions) <= plain.max_position_error + 1e-12).all()
    assert position_steps(np.array([0.0, 30.0, 0.01])).tolist() == [1, 1, 1024] and position_steps(np.full(3, 1e-6)).tolist() == [2 ** 15] * 3


def test_vat_frames_decode_within_half_a_step_and_the_octahedral_bound():
    rng = np.random.default_rng(7)
    positions = rng.uniform([-0.4, 0.0, -0.3], [0.4, 1.8, 0.3], size=(5, 300, 3))
    normals = rng.normal(size=(5, 300, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    animation = encode_vat(positions, normals, max_width=128)
    assert animation.texels.shape == (5 * 3, 128, 4) and animation.texels.dtype == np.uint16
    decoded_positions, decoded_normals = decode_vat(animation)
    error = np.abs(decoded_positions - positions).max(axis=(0, 1))
    assert (error <= animation.max_position_error + 1e-12).all()
    assert error.max() > 0.25 * animation.max_position_error.max()  # quantisation really happened
    assert angles_deg(decoded_normals, normals).max() <= OCTAHEDRAL_MAX_ERROR_DEG
    # Unused texels at the end of each frame's last row stay 0.
    assert (animation.texels[2, 300 - 256:] == 0).all()
    with pytest.raises(ValueError, match=r"\(F, V, 3\)"):
        encode_vat(positions[..., :2], normals[..., :2])


def test_vat_flat_axis_decodes_exactly():
    positions = np.zeros((2, 4, 3))
    positions[1, :, 0] = 1.0  # y and z never move
    normals = np.tile([0.0, 1.0, 0.0], (2, 4, 1))
    decoded, _ = decode_vat(encode_vat(positions, normals))
    np.testing.assert_array_equal(decoded, positions)


def two_bone_body(frames: int = 6):
    """A bent bar on two joints (a CBSK's data): 40 vertices along y, weights blending from joint 0 to joint 1;
    joint 1 turns and scales a little per frame, a third joint no vertex weighs; frame 3's matrices sheared
    (a blend of two poses). Returns rest positions, rest normals, joints, weight codes, matrices (F, 3, 3, 4)."""
    rng = np.random.default_rng(11)
    y = np.linspace(0.0, 1.6, 40)
    rest = np.stack([0.1 * np.cos(7 * y), y, 0.1 * np.sin(7 * y)], 1)
    normals = np.stack([np.cos(7 * y), np.zeros_like(y), np.sin(7 * y)], 1)
    blend = np.clip((y - 0.4) / 0.8, 0, 1)
    weights = np.stack([1 - blend, blend, np.zeros_like(y), np.zeros_like(y)], 1)
    joints = np.tile([0, 1, 2, 0], (40, 1))
    matrices = np.zeros((frames, 3, 3, 4))
    for f in range(frames):
        turn = Rotation.from_euler("xz", [0.3 * f, -0.2 * f]).as_matrix() * (1 + 0.05 * f)
        matrices[f, 0] = np.concatenate([np.eye(3), [[0.1 * f], [0.0], [0.0]]], 1)
        matrices[f, 1] = np.concatenate([turn, (np.array([0, 0.8, 0]) - turn @ [0, 0.8, 0])[:, None]], 1)
        matrices[f, 2] = np.concatenate([rng.normal(size=(3, 3)) * 50, rng.normal(size=(3, 1)) * 50], 1)  # never read
    matrices[3, 1, :, :3] = 0.5 * (matrices[2, 1, :, :3] + matrices[4, 1, :, :3])  # a crossfade: sheared
    return rest, normals, joints, weight_codes(weights), matrices


def test_a_skin_texture_and_its_joint_matrices_play_the_skinned_frames():
    """The skin texture holds joints and weights exactly; the joint texture rows decode within half a 16-bit
    step of their channel's range; skinning the decoded texels (the shaders' maths, play_skin) gives the CBSK's
    frames (crowdbake.formats.skinned_cache.skin_frames), a sheared frame included, within what those
    roundings allow. A joint no vertex weighs is written as the identity, so its wild matrices do not widen
    the ranges."""
    rest, normals, joints, codes, matrices = two_bone_body()
    used = np.array([True, True, False])
    skin = encode_skin(rest, normals, joints, codes, max_width=16)
    assert skin.layout == vat_layout(40, SKIN_BLOCKS, 16) and skin.texels.dtype == np.uint16
    texture = encode_joints(matrices, used, max_width=5)  # 9 rows a frame over 5 texels: 2 rows a frame
    assert (texture.layout.width, texture.layout.rows_per_frame, texture.layout.height) == (5, 2, 12)
    decoded_rest, decoded_normals, decoded_joints, decoded_weights = decode_skin(skin)
    np.testing.assert_array_equal(decoded_joints, np.where(codes > 0, joints, 0))
    np.testing.assert_array_equal(decoded_weights * 65535, codes)
    assert np.abs(decoded_rest - rest).max() <= (rest.max(0) - rest.min(0)).max() / 131070 + 1e-12
    assert angles_deg(decoded_normals, normals).max() <= OCTAHEDRAL_MAX_ERROR_DEG
    decoded = decode_joints(texture)
    step = (texture.maximum - texture.minimum) / 65535
    assert (np.abs(decoded[:, :2] - matrices[:, :2]) <= step / 2 + 1e-12).all()
    assert (np.abs(decoded[:, 2] - np.eye(3, 4)) <= step / 2 + 1e-12).all()
    assert texture.maximum.max() < 3 and texture.minimum.min() > -3  # joint 2's +-50 left out
    expected, expected_normals = skin_frames(rest.astype(np.float32), normals.astype(np.float32), joints.astype(np.uint16), codes,
                                             matrices.astype(np.float32))
    played, played_normals = play_skin(skin, texture)
    # Bound: the rest position's rounding, plus each matrix entry's half step times the rest coordinate.
    bound = (rest.max(0) - rest.min(0)).max() / 131070 * 1.1 + (step[:3].max() * np.abs(rest).max() * 3 + step[3]) / 2
    error = np.abs(played - expected).max()
    assert error <= bound and error > 0, (error, bound)
    assert angles_deg(played_normals, expected_normals).max() < 1.2
    np.testing.assert_array_equal(play_skin(skin, texture, [4])[0], played[[4]])


def test_a_skin_texture_refuses_what_it_cannot_hold():
    rest, normals, joints, codes, _ = two_bone_body()
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        encode_skin(rest[:, :2], normals, joints, codes)
    broken = codes.copy()
    broken[0, 0] -= 1
    with pytest.raises(ValueError, match="sum to 65535"):
        encode_skin(rest, normals, joints, broken)
    with pytest.raises(ValueError, match=r"\(F, J, 3, 4\)"):
        encode_joints(np.zeros((2, 3, 4, 4)))


def test_a_coarser_lod_reads_the_finer_lods_texels_only_where_its_vertices_are_the_same():
    """shared_vertices: a coarse mesh made of some fine vertices (in another order, each 0.05 mm off, as two
    LODs' 16-bit pose caches round apart) finds them; one vertex moved a millimetre, or turned, and it finds
    none (the coarse LOD then writes its own texels)."""
    rng = np.random.default_rng(5)
    fine = rng.uniform(-1, 1, size=(4, 30, 3))
    normals = rng.normal(size=(4, 30, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    picked = np.array([17, 3, 29, 3, 8])
    coarse = fine[:, picked] + 5e-5 / np.sqrt(3)
    found = shared_vertices(fine, normals, coarse, normals[:, picked])
    np.testing.assert_array_equal(found, picked)
    moved = coarse.copy()
    moved[2, 1] += 1e-3
    assert shared_vertices(fine, normals, moved, normals[:, picked]) is None
    turned = normals[:, picked].copy()
    turned[1, 4] = -turned[1, 4]
    assert shared_vertices(fine, normals, coarse, turned) is None


def test_a_coarser_skin_reads_the_finer_skins_texels_where_its_vertices_are_the_same():
    rest, normals, joints, codes, _ = two_bone_body()
    picked = np.array([39, 0, 20, 21])
    found = shared_skin_vertices(rest, normals, joints, codes, rest[picked], normals[picked], joints[picked], codes[picked])
    np.testing.assert_array_equal(found, picked)
    other = codes[picked].copy()
    other[2] = [65535, 0, 0, 0]  # the same place, other weights: not the same vertex
    assert shared_skin_vertices(rest, normals, joints, codes, rest[picked], normals[picked], joints[picked], other) is None
