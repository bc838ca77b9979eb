"""Quantized pose caches (crowdbake.formats.pose_codec, CBPC version 2): the error bounds SPEC.md states hold,
by construction on synthetic garments whose answer is known."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.formats import pose_codec
from crowdbake.formats.binary import (
    POSE_CACHE_HEADER_SIZE,
    decode_pose_cache,
    encode_pose_cache,
    encode_quantized_pose_cache,
)


def unit_vectors(count: int, seed: int = 0) -> np.ndarray:
    """Random unit vectors plus the axes and the octahedron's edges, where the fold is exact or nearly."""
    rng = np.random.default_rng(seed)
    vectors = rng.normal(size=(count, 3))
    corners = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                        [1, 1, 0], [1, -1, 0], [-1, 1, 0], [-1, -1, 0], [1, 0, -1], [0, -1, -1], [1e-9, 1e-9, -1]], float)
    vectors = np.concatenate([vectors, corners])
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between unit vectors, from the cross product so that tiny angles are not lost in arccos."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(axis=-1)))


def garment_frames(frames: int = 6, vertices: int = 400, size_m: float = 2.0, drift_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A `size_m` garment swaying over `frames`, moving `drift_m` along x per frame; positions and unit normals."""
    rng = np.random.default_rng(3)
    rest = rng.random((vertices, 3)) * size_m - size_m / 2
    positions = np.stack([rest + [drift_m * f + 0.05 * np.sin(f), 0.0, 0.0] for f in range(frames)]).astype(np.float32)
    normals = np.stack([unit_vectors(vertices, seed=f)[:vertices] for f in range(frames)]).astype(np.float32)
    return positions, normals


def test_octahedral_normals_stay_within_the_stated_angle():
    normals = unit_vectors(200_000)
    decoded = pose_codec.decode_octahedral(pose_codec.encode_octahedral(normals))
    worst = angles_deg(normals, decoded).max()
    assert worst <= pose_codec.OCTAHEDRAL_MAX_ERROR_DEG
    # The bound is tight enough to mean something: half of it would not hold.
    assert worst > pose_codec.OCTAHEDRAL_MAX_ERROR_DEG / 2


def test_a_2m_garment_decodes_within_half_a_millimetre_and_within_half_a_step():
    positions, _ = garment_frames(size_m=2.0)
    bounds = pose_codec.frame_bounds(positions)
    decoded = pose_codec.dequantize_positions(pose_codec.quantize_positions(positions, bounds), bounds)
    error = np.abs(decoded.astype(float) - positions).max(axis=(1, 2))
    assert (error <= pose_codec.position_error_bound(bounds)).all()
    assert error.max() <= 2.0 / 65535  # 0.03 mm: the step, of which rounding leaves half
    assert error.max() <= pose_codec.MAX_POSITION_ERROR_M


def test_bounds_follow_each_frame_so_a_walk_keeps_the_step_small():
    """A character walking 10 m over the cycle: the cache's bounds would span 10 m, each frame's only 2 m."""
    positions, _ = garment_frames(frames=11, size_m=2.0, drift_m=1.0)
    bounds = pose_codec.frame_bounds(positions)
    assert (bounds[:, 1] - bounds[:, 0]).max() < 2.0 + 1e-3
    decoded = pose_codec.dequantize_positions(pose_codec.quantize_positions(positions, bounds), bounds)
    assert np.abs(decoded.astype(float) - positions).max() <= 2.0 / 65535


def test_an_axis_a_frame_does_not_span_decodes_exactly():
    positions = np.zeros((2, 3, 3), np.float32)
    positions[:, :, 0] = [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]
    positions[:, :, 1] = 1.25  # a flat garment: y the same everywhere
    bounds = pose_codec.frame_bounds(positions)
    decoded = pose_codec.dequantize_positions(pose_codec.quantize_positions(positions, bounds), bounds)
    assert np.array_equal(decoded[:, :, 1], positions[:, :, 1]) and np.array_equal(decoded[:, :, 2], positions[:, :, 2])


def test_a_version_2_file_is_ten_bytes_a_vertex_a_frame_and_decodes_to_its_codes():
    positions, normals = garment_frames(frames=5, vertices=300)
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    uvs = np.zeros((300, 2), np.float32)
    data = encode_quantized_pose_cache(faces, uvs, positions, normals, 24.0)
    float_data = encode_pose_cache(faces, uvs, positions, normals, 24.0)
    payload = len(data) - POSE_CACHE_HEADER_SIZE - 4 * 6 - 8 * 300
    assert payload == 24 * 5 + 10 * 300 * 5
    assert len(float_data) - POSE_CACHE_HEADER_SIZE - 4 * 6 - 8 * 300 == 24 * 300 * 5
    cache = decode_pose_cache(data)
    assert cache.version == 2 and cache.positions.dtype == np.float32
    assert np.abs(cache.positions - positions).max() <= 2.0 / 65535
    assert angles_deg(normals, cache.normals).max() <= pose_codec.OCTAHEDRAL_MAX_ERROR_DEG


def test_a_frame_too_wide_for_16_bits_is_refused():
    """200 m across, a 16-bit step is 3 mm: the bake stops rather than ship the error (from 65 m on, half a
    step may pass 0.5 mm)."""
    positions, normals = garment_frames(frames=2, vertices=100, size_m=200.0)
    with pytest.raises(ValueError, match="16-bit positions"):
        encode_quantized_pose_cache(np.array([[0, 1, 2]]), np.zeros((100, 2)), positions, normals, 24.0)
