"""Format v4 (a body as a skinned pose cache, CBSK) against shared_formats/vectors/v4, which crowdview's tests
read too; v1 to v3 bundles still read."""
from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from crowdbake.formats.bundle import verify_bundle
from crowdbake.formats.skinned_cache import SkinnedPoseCache, weight_codes
from vector_checks import assert_every_prefix_truncated, assert_refused_as_expected
from repo_paths import REPO_ROOT, VECTORS

V4 = VECTORS / "v4"
GOOD = V4 / "good" / "bundle"
BAD_CASES = sorted(p.name for p in (V4 / "bad").iterdir())


def test_good_v4_vector_reads_its_stored_arrays_and_skinned_frames():
    expected = json.loads((V4 / "good" / "expected.json").read_text())
    bundle = verify_bundle(GOOD)
    assert bundle.manifest["format_version"] == expected["format_version"] == 4
    skinned = {path: cache for path, cache in bundle.pose_caches.items() if isinstance(cache, SkinnedPoseCache)}
    assert set(skinned) == set(expected["skinned"]) == {"poses/body_lod0.cbsk", "poses/body_lod1.cbsk"}
    assert all(cache.version == 2 for path, cache in bundle.pose_caches.items() if path not in skinned)  # the garment stays quantized
    for path, values in expected["skinned"].items():
        cache = skinned[path]
        assert (cache.vertex_count, 3 * cache.triangle_count, cache.frame_count, cache.joint_count) == (
            values["vertex_count"], values["index_count"], values["frame_count"], values["joint_count"])
        assert np.array_equal(cache.joints, values["joints"]) and np.array_equal(cache.weight_codes, values["weight_codes"])
        assert np.array_equal(cache.matrices.reshape(cache.frame_count, cache.joint_count, 12), np.float32(values["matrices"]))
        assert np.array_equal(cache.positions, np.float32(values["positions"])), path
        assert np.array_equal(cache.normals, np.float32(values["normals"])), path
        assert (cache.positions >= np.float32(values["bounds_min"]) - 1e-6).all() and (cache.positions <= np.float32(values["bounds_max"]) + 1e-6).all()


def test_v4_frames_are_the_spec_maths_on_the_stored_arrays():
    """SPEC.md's skinning, written out here per vertex in float64: p = sum w A (p0, 1), n = normalize(sum w L^-T n0)."""
    expected = json.loads((V4 / "good" / "expected.json").read_text())
    bundle = verify_bundle(GOOD)
    for path, values in expected["skinned"].items():
        cache = bundle.pose_caches[path]
        matrices = np.float64(values["matrices"]).reshape(values["frame_count"], values["joint_count"], 3, 4)
        weights = np.float64(values["weight_codes"]) / 65535.0
        for frame in range(values["frame_count"]):
            for vertex in range(values["vertex_count"]):
                rest = np.append(cache.rest_positions[vertex].astype(np.float64), 1.0)
                position = sum(w * matrices[frame, j] @ rest for j, w in zip(values["joints"][vertex], weights[vertex]))
                normal = sum(w * np.linalg.inv(matrices[frame, j, :, :3]).T @ cache.rest_normals[vertex] for j, w in zip(values["joints"][vertex], weights[vertex]))
                assert np.allclose(position, values["positions"][frame][vertex], atol=1e-5), (path, frame, vertex)
                assert np.allclose(normal / np.linalg.norm(normal), values["normals"][frame][vertex], atol=1e-5), (path, frame, vertex)


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_v4_vector_is_refused_with_its_code_and_file(case):
    assert_refused_as_expected(V4 / "bad" / case)


def test_every_strict_prefix_of_a_v4_binary_is_truncated():
    assert_every_prefix_truncated(GOOD)


@pytest.mark.parametrize("older", ["v1", "v2", "v3"])
def test_older_bundles_still_read(older):
    bundle = verify_bundle(VECTORS / older / "good" / "bundle")
    assert not any(isinstance(cache, SkinnedPoseCache) for cache in bundle.pose_caches.values())


def test_weight_codes_are_an_exact_partition_of_unity():
    weights = np.random.default_rng(3).random((500, 4)) ** 3
    weights[:50, 1:] = 0.0  # one influence
    codes = weight_codes(weights)
    assert (codes.astype(np.int64).sum(axis=1) == 65535).all()
    assert np.abs(codes / 65535.0 - weights / weights.sum(axis=1, keepdims=True)).max() <= 2.5 / 65535
    with pytest.raises(ValueError, match="non-negative"):
        weight_codes(np.zeros((2, 4)))


def test_writer_still_produces_the_committed_v4_vectors(tmp_path):
    """Old vectors are never edited, so the writer must keep producing their exact bytes."""
    spec = importlib.util.spec_from_file_location("gen_v4", REPO_ROOT / "shared_formats" / "generate_vectors_v4.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v4")
    committed = sorted(p.relative_to(V4) for p in V4.rglob("*") if p.is_file())
    assert committed == sorted(p.relative_to(tmp_path / "v4") for p in (tmp_path / "v4").rglob("*") if p.is_file())
    for relative in committed:
        assert (tmp_path / "v4" / relative).read_bytes() == (V4 / relative).read_bytes(), relative
