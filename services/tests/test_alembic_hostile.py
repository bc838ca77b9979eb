"""Hostile Alembic caches, made here from the shared long_skirt.abc by rewriting its time sampling: the
counts and rates the archive claims are checked before Blender starts, the child is bounded and leaves
no process or temp file behind."""
from __future__ import annotations

import os
import struct
import tempfile
import threading
import time
from pathlib import Path

import pytest

from crowdbake.formats import alembic
from crowdbake.formats.alembic import MAX_POINT_SAMPLES, ReadCancelled, read_alembic


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
    """tempfile's folder for this test alone, and TMPDIR for the Blender child (which makes its own
    blender_XXXXXX folder there), to see that nothing stays behind."""
    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    monkeypatch.setenv("TMPDIR", str(folder))
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


def _descendants(pid: int) -> list[int]:
    """Every process below `pid` (children, their children, ...), from /proc."""
    parents = {int(entry): _parent(entry) for entry in os.listdir("/proc") if entry.isdigit()}
    found, frontier = [], [pid]
    while frontier:
        below = [child for child, parent in parents.items() if parent in frontier]
        found += below
        frontier = below
    return found


def _wait_for(condition, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


def slow_alembic(source: Path, target: Path) -> Path:
    """long_skirt.abc (4,032 points) claiming as many samples as the budget allows: Blender reads for
    about 10 s (2 cores), long enough to cancel it midway."""
    return _rewrite_animated_sampling(source, target, max_samples=MAX_POINT_SAMPLES // 4032)


def test_a_cancelled_read_kills_the_blender_child_and_removes_its_folder(shared_asset, tmp_path, private_tmp):
    """Regression: the Blender child of an upload whose client had left ran on for up to its 300 s
    deadline. The reader now watches a cancellation event (the API sets it on the client's disconnect,
    crowdbake.api.disconnects): set from another thread while Blender works, the read raises
    ReadCancelled within a second, with no child process and no temp folder left."""
    if not alembic.alembic_available():
        pytest.skip("the crowdbake[alembic] extra (Blender's bpy) is not installed: pip install -r services/requirements-alembic.txt")
    hostile = slow_alembic(shared_asset("long_skirt/long_skirt.abc"), tmp_path / "slow.abc")
    cancel = threading.Event()
    outcome: dict[str, object] = {}

    def read() -> None:
        try:
            outcome["cache"] = read_alembic(hostile, cancel=cancel)
        except BaseException as error:  # noqa: BLE001 (reported to the test thread)
            outcome["error"] = error

    reader = threading.Thread(target=read)
    reader.start()
    try:
        assert _wait_for(lambda: _descendants(os.getpid()), 20), "Blender never started"
        time.sleep(1.0)  # Blender is importing and reading, seconds from done
        assert _descendants(os.getpid()) and "cache" not in outcome
        cancel.set()
        cancelled_at = time.monotonic()
        reader.join(timeout=10)
        seconds = time.monotonic() - cancelled_at
    finally:
        cancel.set()
        reader.join()
    assert isinstance(outcome.get("error"), ReadCancelled), outcome
    assert seconds < 1.5, seconds
    assert _descendants(os.getpid()) == []
    assert list(private_tmp.iterdir()) == []


def test_a_cancel_set_before_the_read_starts_no_blender(shared_asset, private_tmp):
    if not alembic.alembic_available():
        pytest.skip("the crowdbake[alembic] extra (Blender's bpy) is not installed")
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(ReadCancelled, match="cancelled before Blender started"):
        read_alembic(shared_asset("long_skirt/long_skirt.abc"), cancel=cancel)
    assert list(private_tmp.iterdir()) == []
