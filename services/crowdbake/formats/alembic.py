"""Alembic (.abc) cloth caches, read through Blender's `bpy` module (the `crowdbake[alembic]` extra).

    read_alembic(path, object_name=None) -> crowdbake.formats.cloth_cache.ClothCache

What comes from the .abc alone:
  * the frame rate and the first sample's time, from the archive's time samplings (parsed here from the
    Ogawa container: bpy has no API for them, and the scene rate Blender shows after an import is only
    its default);
  * the mesh, its UVs and every sample's points, from Blender's Alembic importer evaluated at each
    sample time, with the world transform of the mesh's parents applied, turned back from Blender's
    Z-up world into Alembic's (and glTF's) Y-up: (x, y, z) -> (x, z, -y).

bpy is large and keeps global state, so it runs in a child process (crowdbake/formats/bpy_alembic_dump.py)
with the interpreter in $CROWDBAKE_BPY_PYTHON, else this one. Without bpy the reader says in one line
which extra to install.

Ogawa, the container of every Alembic file written since 2013: a 16-byte header ("Ogawa", a frozen
flag, a version, the root group's offset as uint64 little-endian); a group is uint64 count then that
many uint64 child offsets whose top bit marks data (else a group); data is uint64 size then bytes.
The archive's root group holds, in order: the Alembic version, the library version, the top object,
the archive metadata, the time samplings, the indexed metadata. The time samplings data repeats:
uint32 maxSample, float64 timePerCycle, uint32 sampleCount, float64 sampleTimes[sampleCount].
"""
from __future__ import annotations

import importlib.util
import json
import os
import resource
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crowdbake.formats.cloth_frames import ClothCache, mesh_from_polygons
from crowdbake.params import fps_problem

OGAWA_MAGIC = b"Ogawa"
_DATA_BIT = 1 << 63
# Alembic's marker for an acyclic time sampling's time per cycle (AbcCoreAbstract TimeSamplingType).
ACYCLIC_TIME_PER_CYCLE = sys.float_info.max / 32.0
# Points x samples one cache may hold, checked before Blender starts (the samples the archive claims)
# and by the child as soon as it knows the points (before it writes a frame): 2^24 is 192 MiB of
# float32 frames, far more than a garment needs (long_skirt: 385 samples of a few thousand points) and
# within the API's +300 MB target. Unchecked, a 2.4 MB .abc of 10,201 points claiming 2,000 samples (20
# million) runs 123 s and takes 1.85 GB; one claiming 2^32 - 1 samples runs until the child's deadline.
MAX_POINT_SAMPLES = 1 << 24
# The Blender child's deadline and address space: a cache within MAX_POINT_SAMPLES reads in well under
# a minute; bpy itself maps about 2 GB of address space before reading anything.
BPY_TIMEOUT_SECONDS = 300
BPY_ADDRESS_SPACE_BYTES = 8 << 30
# How often the wait on the child looks at the caller's cancellation: a request whose client left ends
# its Blender within this (plus the kill).
CANCEL_POLL_SECONDS = 0.2
MISSING_BPY = (
    "reading Alembic (.abc) needs the crowdbake[alembic] extra (Blender's bpy module): "
    "pip install -r services/requirements-alembic.txt, or set CROWDBAKE_BPY_PYTHON to a Python that has bpy"
)
DUMP_SCRIPT = Path(__file__).with_name("bpy_alembic_dump.py")


class ReadCancelled(Exception):
    """The caller cancelled the read (its request's client left): the Blender child was killed and its
    temp folder removed. Not a ValueError: nothing is wrong with the file."""


@dataclass(frozen=True)
class TimeSampling:
    """One Alembic time sampling: max_samples taken; time_per_cycle seconds; times (the first cycle's)."""

    max_samples: int
    time_per_cycle: float
    times: tuple[float, ...]

    @property
    def fps(self) -> float | None:
        """Samples per second: uniform and cyclic samplings from their cycle, acyclic from the times."""
        if self.time_per_cycle >= ACYCLIC_TIME_PER_CYCLE * 0.999:
            steps = np.diff(self.times)
            return float(1.0 / np.median(steps)) if len(steps) and np.median(steps) > 0 else None
        if self.time_per_cycle <= 0:
            return None
        return len(self.times) / self.time_per_cycle


def _ogawa_children(data: bytes, offset: int, where: str) -> list[int]:
    if offset + 8 > len(data):
        raise ValueError(f"{where}: Ogawa group at byte {offset} lies past the end ({len(data)} bytes)")
    (count,) = struct.unpack_from("<Q", data, offset)
    if offset + 8 + 8 * count > len(data):
        raise ValueError(f"{where}: Ogawa group at byte {offset} claims {count} children past the end")
    return list(struct.unpack_from(f"<{count}Q", data, offset + 8))


def _ogawa_data(data: bytes, child: int, where: str) -> bytes:
    if not child & _DATA_BIT:
        raise ValueError(f"{where}: expected Ogawa data, found a group")
    offset = child & ~_DATA_BIT
    if offset == 0:
        return b""
    if offset + 8 > len(data):
        raise ValueError(f"{where}: Ogawa data at byte {offset} lies past the end")
    (size,) = struct.unpack_from("<Q", data, offset)
    if offset + 8 + size > len(data):
        raise ValueError(f"{where}: Ogawa data at byte {offset} claims {size} bytes past the end")
    return data[offset + 8 : offset + 8 + size]


def read_time_samplings(path: str | os.PathLike) -> list[TimeSampling]:
    """The time samplings of an Ogawa Alembic archive (the first is always the static identity one).

    Reads the header, the root group and one data block: a few hundred bytes whatever the file's size."""
    path = Path(path)
    where = str(path)
    with open(path, "rb") as handle:
        header = handle.read(16)
        if len(header) < 16 or not header.startswith(OGAWA_MAGIC):
            kind = "an HDF5 Alembic (only Ogawa, the format of every exporter since 2013, is read)" if header[1:4] == b"HDF" else "not an Alembic (Ogawa) file"
            raise ValueError(f"{where}: {kind}")
        data = header + handle.read()
    try:
        return _time_samplings(data, where)
    except (struct.error, OverflowError, MemoryError) as error:  # a corrupt (e.g. byte-flipped) archive
        raise ValueError(f"{where}: a corrupt Alembic archive: {error}") from None


def _time_samplings(data: bytes, where: str) -> list[TimeSampling]:
    (root,) = struct.unpack_from("<Q", data, 8)
    children = _ogawa_children(data, root, where)
    if len(children) < 5:
        raise ValueError(f"{where}: the Alembic archive's root has {len(children)} entries, expected 6")
    block = _ogawa_data(data, children[4], where)
    samplings, offset = [], 0
    while offset < len(block):
        if offset + 16 > len(block):
            raise ValueError(f"{where}: truncated time sampling at byte {offset} of its block")
        max_samples, time_per_cycle, count = struct.unpack_from("<IdI", block, offset)
        offset += 16
        if offset + 8 * count > len(block):
            raise ValueError(f"{where}: time sampling claims {count} times past the end of its block")
        times = struct.unpack_from(f"<{count}d", block, offset)
        offset += 8 * count
        samplings.append(TimeSampling(int(max_samples), float(time_per_cycle), tuple(times)))
    return samplings


def animated_sampling(samplings: list[TimeSampling], where: str) -> TimeSampling:
    """The sampling the animation uses: the one with the most samples (index 0 is the static one)."""
    animated = [s for s in samplings[1:] if s.max_samples > 1] or samplings[1:] or samplings
    if not animated:
        raise ValueError(f"{where}: the Alembic archive has no time sampling")
    return max(animated, key=lambda s: s.max_samples)


def bpy_python() -> str:
    """The interpreter that runs bpy, or ValueError(MISSING_BPY) when there is none."""
    configured = os.environ.get("CROWDBAKE_BPY_PYTHON")
    if configured:
        if not shutil.which(configured) and not Path(configured).is_file():
            raise ValueError(f"CROWDBAKE_BPY_PYTHON={configured} is not an interpreter; {MISSING_BPY}")
        return configured
    if importlib.util.find_spec("bpy") is None:
        raise ValueError(MISSING_BPY)
    return sys.executable


def alembic_available() -> bool:
    try:
        bpy_python()
    except ValueError:
        return False
    return True


def blender_to_y_up(points: np.ndarray) -> np.ndarray:
    """(..., 3) Blender Z-up world -> Y-up: (x, y, z) -> (x, z, -y), the inverse of the importer's turn."""
    points = np.asarray(points)
    return np.stack([points[..., 0], points[..., 2], -points[..., 1]], axis=-1)


def read_alembic(path: str | os.PathLike, object_name: str | None = None, cancel: threading.Event | None = None) -> ClothCache:
    """An Alembic cloth cache -> ClothCache (frames (F, P, 3) float32, Y-up, the file's units; fps from the
    archive). `object_name` picks the mesh when the file holds several (Blender's object name).
    `cancel`, set from another thread, ends the Blender child (its process group) and raises ReadCancelled
    once its temp folder is removed.

    Raises ValueError with one line: no bpy (naming the extra), not Ogawa, no mesh, several meshes
    without a name, a topology that changes, or Blender's own failure."""
    path = Path(path)
    where = str(path)
    sampling = animated_sampling(read_time_samplings(path), where)
    fps = sampling.fps
    if fps is None or not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"{where}: the Alembic time sampling gives no frame rate")
    if (problem := fps_problem(fps)) is not None:
        raise ValueError(f"{where}: the Alembic time sampling's frame rate: {problem}")
    start = sampling.times[0] if sampling.times else 0.0
    samples = max(1, sampling.max_samples)
    if samples > MAX_POINT_SAMPLES:  # even one point a sample is too many: refused before Blender starts
        raise ValueError(f"{where}: the Alembic time sampling claims {samples} samples, more than the {MAX_POINT_SAMPLES} point samples a cache may hold")
    python = bpy_python()
    with tempfile.TemporaryDirectory(prefix="crowdbake-abc-") as out:
        command = [python, str(DUMP_SCRIPT), str(path.resolve()), out, repr(fps), repr(start), str(samples)]
        if object_name is not None:
            command.append(object_name)
        done = _run_bpy(command, where, Path(out), cancel)
        if done.returncode != 0:
            lines = [line for line in done.stderr.splitlines() if line.startswith("crowdbake-alembic:")]
            reason = lines[-1].split(":", 1)[1].strip() if lines else (done.stderr.strip().splitlines() or ["no message"])[-1]
            raise ValueError(f"{where}: {reason}")
        meta = json.loads((Path(out) / "meta.json").read_text())
        points, polygons, corners = meta["points"], meta["polygons"], meta["corners"]
        topology = np.fromfile(Path(out) / "topology.bin", dtype="<i4")
        sizes = topology[:polygons]
        corner_points = topology[polygons : polygons + corners]
        corner_uvs = None
        if meta["has_uvs"]:
            corner_uvs = topology[polygons + corners :].view("<f4").reshape(corners, 2)
        frames = _world_frames(Path(out) / "frames.bin", samples, points, where)
    if not np.isfinite(frames).all():
        raise ValueError(f"{where}: the cache holds NaN or infinite points")
    mesh = mesh_from_polygons(frames[0], sizes, corner_points, corner_uvs)
    return ClothCache(mesh=mesh, frames=frames, fps=float(fps), frame_step=1.0, source="alembic")


def _run_bpy(command: list[str], where: str, out: Path, cancel: threading.Event | None = None) -> subprocess.CompletedProcess:
    """Run the Blender child in its own process group under BPY_TIMEOUT_SECONDS and an address-space
    limit, telling it MAX_POINT_SAMPLES; the whole group is killed on a timeout, on `cancel` being set
    (ReadCancelled, within CANCEL_POLL_SECONDS) or on any error, so no Blender outlives its request.
    Blender's own session folder (blender_XXXXXX, left behind when it is killed) goes under `out`, which
    the caller removes: TMPDIR points there."""

    def limit_memory() -> None:  # runs in the child, before exec
        resource.setrlimit(resource.RLIMIT_AS, (BPY_ADDRESS_SPACE_BYTES, BPY_ADDRESS_SPACE_BYTES))

    if cancel is not None and cancel.is_set():
        raise ReadCancelled(f"{where}: cancelled before Blender started")
    blender_tmp = out / "blender-tmp"
    blender_tmp.mkdir()
    env = {**os.environ, "CROWDBAKE_ABC_MAX_POINT_SAMPLES": str(MAX_POINT_SAMPLES), "TMPDIR": str(blender_tmp)}
    deadline = time.monotonic() + BPY_TIMEOUT_SECONDS
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                             start_new_session=True, preexec_fn=limit_memory)
    try:
        while True:
            try:  # communicate may be called again after a timeout without losing output
                _, stderr = child.communicate(timeout=min(CANCEL_POLL_SECONDS, max(deadline - time.monotonic(), 0.0)))
                break
            except subprocess.TimeoutExpired:
                if cancel is not None and cancel.is_set():
                    raise ReadCancelled(f"{where}: cancelled while Blender read the cache") from None
                if time.monotonic() >= deadline:
                    raise ValueError(f"{where}: Blender took more than {BPY_TIMEOUT_SECONDS} s to read the cache") from None
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
    return subprocess.CompletedProcess(command, child.returncode, "", stderr)


def _world_frames(frames_file: Path, samples: int, points: int, where: str) -> np.ndarray:
    """frames.bin (per sample: float32 world matrix, then (points, 3) float32 local points) -> (samples,
    points, 3) float32 Y-up world points, one sample at a time: the file is mapped, never copied whole,
    and nothing is widened to float64 (which held several float64 copies of every frame)."""
    row = 16 + 3 * points
    if frames_file.stat().st_size != 4 * row * samples:
        raise ValueError(f"{where}: Blender wrote {frames_file.stat().st_size} bytes of frames, {samples} samples of {points} points need {4 * row * samples}")
    raw = np.memmap(frames_file, dtype="<f4", mode="r", shape=(samples, row))
    frames = np.empty((samples, points, 3), np.float32)
    for sample in range(samples):
        matrix = raw[sample, :16].reshape(4, 4)
        world = raw[sample, 16:].reshape(points, 3) @ matrix[:3, :3].T + matrix[:3, 3]
        frames[sample] = blender_to_y_up(world)
    del raw
    return frames
