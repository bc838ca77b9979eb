"""Format v2 (clips and transitions) against shared_formats/vectors/v2, which crowdview's tests read too,
and v1 read as one clip."""
from __future__ import annotations

import importlib.util
import json

import pytest

from crowdbake.formats.bundle import verify_bundle
from vector_checks import assert_every_prefix_truncated, assert_refused_as_expected
from repo_paths import REPO_ROOT, VECTORS

V2 = VECTORS / "v2"
GOOD = V2 / "good" / "bundle"
BAD_CASES = sorted(p.name for p in (V2 / "bad").iterdir())


def test_good_v2_vector_reads_as_its_clips_and_transitions():
    expected = json.loads((V2 / "good" / "expected.json").read_text())
    bundle = verify_bundle(GOOD)
    assert bundle.manifest["format_version"] == expected["format_version"] == 2
    assert bundle.ranges.pose_frames == expected["pose_frames"]
    assert [clip.to_manifest() for clip in bundle.ranges.clips] == expected["clips"]
    assert [transition.to_manifest() for transition in bundle.ranges.transitions] == expected["transitions"]
    assert bundle.manifest["impostor"]["frame_indices"] == expected["frame_indices"]
    assert {path: cache.frame_count for path, cache in bundle.pose_caches.items()} == expected["pose_cache_frame_count"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_v2_vector_is_refused_with_its_code_and_file(case):
    assert_refused_as_expected(V2 / "bad" / case)


def test_every_strict_prefix_of_a_v2_binary_is_truncated():
    """The binaries stay CBPC/CBTX v1, so a prefix of any of them still reads as truncated, never a crash."""
    assert_every_prefix_truncated(GOOD)


def test_v1_reads_as_one_clip_named_cycle():
    bundle = verify_bundle(VECTORS / "v1" / "good" / "bundle")
    cycle = bundle.manifest["cycle"]
    (clip,) = bundle.ranges.clips
    assert (clip.name, clip.first_frame, clip.frames, bundle.ranges.pose_frames) == ("cycle", 0, cycle["frames"], cycle["frames"])
    assert (clip.source_start_frame, clip.closing, clip.position_jump_ratio) == (cycle["source_start_frame"], cycle["closing"], cycle["position_jump_ratio"])
    assert bundle.ranges.transitions == ()


def test_writer_still_produces_the_committed_v2_vectors(tmp_path):
    """Old vectors are never edited, so the writer must keep producing their exact bytes."""
    spec = importlib.util.spec_from_file_location("gen_v2", REPO_ROOT / "shared_formats" / "generate_vectors_v2.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v2")
    committed = sorted(p.relative_to(V2) for p in V2.rglob("*") if p.is_file())
    assert committed == sorted(p.relative_to(tmp_path / "v2") for p in (tmp_path / "v2").rglob("*") if p.is_file())
    for relative in committed:
        assert (tmp_path / "v2" / relative).read_bytes() == (V2 / relative).read_bytes(), relative
