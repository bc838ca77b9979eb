"""Checks every bundle format's vectors share: a bad vector is refused with the code and file its expect.json
(or a superseded expectation, repo_paths) names, and no strict prefix of a good binary parses."""
from __future__ import annotations

from pathlib import Path

import pytest

from crowdbake.formats.binary import decode_pose_cache, decode_texture_array
from crowdbake.formats.bundle import verify_bundle
from crowdbake.formats.errors import FormatError
from crowdbake.formats.skinned_cache import decode_skinned_pose_cache
from repo_paths import vector_expectation


def assert_refused_as_expected(case: Path) -> None:
    """`case`: a bad vector folder (bundle/ and expect.json)."""
    expect = vector_expectation(case)
    if expect["error"] is None:  # a newer reader reads it whole (repo_paths.SUPERSEDED_EXPECTATIONS)
        verify_bundle(case / "bundle")
        return
    with pytest.raises(FormatError) as raised:
        verify_bundle(case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"]), raised.value


def assert_every_prefix_truncated(good_bundle: Path) -> None:
    """Every CBPC/CBSK/CBTX binary under `good_bundle` decodes whole, and each strict prefix is `truncated`."""
    for path in sorted(good_bundle.rglob("*.cb*")):
        data = path.read_bytes()
        decode = {".cbpc": decode_pose_cache, ".cbsk": decode_skinned_pose_cache}.get(path.suffix, decode_texture_array)
        decode(data, path.name)
        for length in range(len(data)):
            with pytest.raises(FormatError) as raised:
                decode(data[:length], path.name)
            assert raised.value.code == "truncated", (path.name, length, raised.value)
