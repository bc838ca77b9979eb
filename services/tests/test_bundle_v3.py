"""Format v3 (quantized pose caches, CBPC version 2) against shared_formats/vectors/v3, which crowdview's tests
read too; v1 and v2 bundles still read."""
from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from crowdbake.formats.bundle import verify_bundle
from vector_checks import assert_every_prefix_truncated, assert_refused_as_expected
from repo_paths import REPO_ROOT, VECTORS

V3 = VECTORS / "v3"
GOOD = V3 / "good" / "bundle"
BAD_CASES = sorted(p.name for p in (V3 / "bad").iterdir())


def test_good_v3_vector_decodes_to_its_expected_codes_and_values():
    expected = json.loads((V3 / "good" / "expected.json").read_text())
    bundle = verify_bundle(GOOD)
    assert bundle.manifest["format_version"] == expected["format_version"] == 3
    assert [clip.to_manifest() for clip in bundle.ranges.clips] == expected["clips"]
    assert [transition.to_manifest() for transition in bundle.ranges.transitions] == expected["transitions"]
    assert set(bundle.pose_caches) == set(expected["pose_caches"])
    for path, values in expected["pose_caches"].items():
        cache = bundle.pose_caches[path]
        assert (cache.version, cache.vertex_count, cache.frame_count) == (values["version"], values["vertex_count"], values["frame_count"])
        # float32 values written as JSON numbers: the nearest float32 is exact.
        assert np.array_equal(cache.positions.reshape(-1), np.float32(values["positions"])), path
        assert np.array_equal(cache.normals.reshape(-1), np.float32(values["normals"])), path
        bounds = np.float32(values["frame_bounds"]).reshape(-1, 2, 3)
        # Every code decodes inside its frame's bounds, up to the float32 rounding of min + q * step.
        positions = cache.positions
        assert (positions >= bounds[:, None, 0] - 1e-6).all() and (positions <= bounds[:, None, 1] + 1e-6).all(), path


def test_v3_codes_are_the_bytes_the_file_stores():
    """expected.json's codes were read straight from the bytes: decoding them by hand gives the reader's values."""
    expected = json.loads((V3 / "good" / "expected.json").read_text())
    for values in expected["pose_caches"].values():
        frames, vertices = values["frame_count"], values["vertex_count"]
        bounds = np.float32(values["frame_bounds"]).reshape(frames, 2, 3)
        codes = np.uint16(values["position_codes"]).reshape(frames, vertices, 3).astype(np.float32)
        by_hand = bounds[:, None, 0] + codes * ((bounds[:, None, 1] - bounds[:, None, 0]) / np.float32(65535))
        assert np.array_equal(by_hand.reshape(-1), np.float32(values["positions"]))


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_v3_vector_is_refused_with_its_code_and_file(case):
    assert_refused_as_expected(V3 / "bad" / case)


def test_every_strict_prefix_of_a_v3_binary_is_truncated():
    assert_every_prefix_truncated(GOOD)


@pytest.mark.parametrize("older", ["v1", "v2"])
def test_older_bundles_still_read(older):
    bundle = verify_bundle(VECTORS / older / "good" / "bundle")
    assert {cache.version for cache in bundle.pose_caches.values()} == {1}


def test_writer_still_produces_the_committed_v3_vectors(tmp_path):
    """Old vectors are never edited, so the writer must keep producing their exact bytes."""
    spec = importlib.util.spec_from_file_location("gen_v3", REPO_ROOT / "shared_formats" / "generate_vectors_v3.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v3")
    committed = sorted(p.relative_to(V3) for p in V3.rglob("*") if p.is_file())
    assert committed == sorted(p.relative_to(tmp_path / "v3") for p in (tmp_path / "v3").rglob("*") if p.is_file())
    for relative in committed:
        assert (tmp_path / "v3" / relative).read_bytes() == (V3 / relative).read_bytes(), relative
