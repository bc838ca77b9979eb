"""Hostile Alembic caches, made here from the shared long_skirt.abc by rewriting its time sampling: the
counts and rates the archive claims are checked before Blender starts, the child is bounded and leaves
no process or temp file behind."""
from __future__ import annotations

import os
import struct
import tempfile
import time
from pathlib import Path

import pytest

from crowdbake.formats import alembic
from crowdbake.formats.alembic import MAX_POINT_SAMPLES, read_alembic


def _samplings_block(data: bytes) -> int:
    """The byte offset of the time samplings' data block (the root group's fifth child)."""
    (root,) = struct.unpack_from("<Q", data, 8)
    child = struct.unpack_from("<Q", data, root + 8 + 8 * 4)[0] & ~(1 << 63)
    return child + 8


def _rewrite_animated_sampling(source: Path, target: Path, max_samples: int | None = None, time_per_cycle: float | None = None) -> Path:
    """long_skirt.abc with its animated time sampling (the second) claiming other counts or rates."""
    data = bytearray(source.read_bytes())
    block = _samplings_block(bytes(data))
    _, _, count = struct.unpack_from("<IdI", data, block)
    animated = block + 16 + 8 * count
    old_samples, old_cycle, _ = struct.unpack_from("<IdI", data, animated)
    struct.pack_into("<Id", data, animated, old_samples if max_samples is None else max_samples,
                     old_cycle if time_per_cycle is None else time_per_cycle)
    target.write_bytes(bytes(data))
    return target


@pytest.fixture
def private_tmp(tmp_path, monkeypatch):
    """tempfile's folder for this test alone, to see that nothing stays behind."""
    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


def test_a_sampling_claiming_2_to_the_32_samples_is_refused_before_blender(shared_asset, tmp_path, private_tmp):
    """Regression: an .abc whose time sampling claims 2^32 - 1 samples ran the Blender child (one core)
    up to its 1,800 s limit and grew a frames file without bound. The claim is now refused from the
    archive's header, before any child starts."""
    hostile = _rewrite_animated_sampling(shared_asset("long_skirt/long_skirt.abc"), tmp_path / "forever.abc", max_samples=2**32 - 1)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=rf"claims 4294967295 samples, more than the {MAX_POINT_SAMPLES} point samples"):
        read_alembic(hostile)
    assert time.perf_counter() - start < 2.0
    assert list(private_tmp.iterdir()) == []


def test_an_alembic_rate_outside_the_sane_range_is_refused(shared_asset, tmp_path):
    """Regression: an Alembic at 1e-300 fps (a time per cycle of 1e300 s) was accepted."""
    hostile = _rewrite_animated_sampling(shared_asset("long_skirt/long_skirt.abc"), tmp_path / "slow.abc", time_per_cycle=1e300)
    with pytest.raises(ValueError, match=r"frame rate: 1e-300 frames per second is outside the sane range 1\.\.1000"):
        read_alembic(hostile)


@pytest.mark.parametrize("offset", [8, 16, 24])
def test_a_byte_flipped_alembic_is_refused_clearly(shared_asset, tmp_path, offset):
    """Regression: a flipped-bytes .abc was accepted. Bytes of the root offset and the first group flipped
    give a ValueError naming the file, never struct.error or an accepted cache."""
    data = bytearray(shared_asset("long_skirt/long_skirt.abc").read_bytes())
    for index in range(offset, offset + 8):
        data[index] ^= 0xFF
    path = tmp_path / "flipped.abc"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=str(path)):
        read_alembic(path)


def test_the_blender_child_checks_points_times_samples_before_writing_frames(shared_asset, tmp_path, private_tmp, monkeypatch):
    """Regression: a 2.4 MB .abc of 10,201 points claiming 2,000 samples was read whole (123 s, +1.85 GB
    in the API). The child now stops as soon as it knows the points, with a budget made small here, and
    no Blender process or temp file outlives the call."""
    if not alembic.alembic_available():
        pytest.skip("the crowdbake[alembic] extra (Blender's bpy) is not installed: pip install -r services/requirements-alembic.txt")
    monkeypatch.setattr(alembic, "MAX_POINT_SAMPLES", 1000)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"samples of \d+ points are \d+ point samples, more than the 1000 a cache may hold"):
        read_alembic(shared_asset("long_skirt/long_skirt.abc"))
    seconds = time.perf_counter() - start
    assert list(private_tmp.iterdir()) == []
    children = [pid for pid in os.listdir("/proc") if pid.isdigit() and _parent(pid) == os.getpid()]
    assert children == [], children
    assert seconds < 60


def _parent(pid: str) -> int | None:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None
