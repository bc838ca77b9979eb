"""MDD point caches (LightWave's format, written by Blender, Houdini, Maya and 3ds Max plug-ins).

Layout, big-endian throughout:

    int32    frameCount
    int32    pointCount
    float32  times[frameCount]                  seconds of each frame
    float32  points[frameCount][pointCount][3]

Like PC2, MDD carries only positions: the garment's rest mesh comes as an OBJ whose position k is
point k. Unlike PC2, MDD stores each frame's time, so the frame rate is read from the file
(1 / the median step between times). The header is checked against the file size before anything
is allocated.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_HEADER = struct.Struct(">ii")
# The same ceilings as crowdbake.formats.pc2: a garbled header must not become a huge allocation.
MAX_POINTS = 1 << 24
MAX_FRAMES = 1 << 24
# Frame times this far (relative) from evenly spaced are not one frame rate: fps is then None.
EVEN_SPACING_TOLERANCE = 1e-3


@dataclass(frozen=True)
class MddCache:
    """points (F, P, 3) float32 in the file's units; times (F,) float64 seconds; fps from the times or None."""

    points: np.ndarray
    times: np.ndarray
    fps: float | None


def frame_rate(times: np.ndarray) -> float | None:
    """Frames per second of evenly spaced, increasing times (F,) seconds; None for fewer than two
    frames, times that do not increase, or uneven spacing."""
    times = np.asarray(times, dtype=np.float64)
    if len(times) < 2:
        return None
    steps = np.diff(times)
    step = float(np.median(steps))
    if step <= 0 or np.abs(steps - step).max() > EVEN_SPACING_TOLERANCE * step:
        return None
    return 1.0 / step


def read_mdd(path: str | os.PathLike) -> MddCache:
    """Read and validate an MDD file. Raises ValueError naming the file and the problem."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as handle:
        header = handle.read(_HEADER.size)
        if len(header) < _HEADER.size:
            raise ValueError(f"{path}: truncated MDD file: {len(header)} bytes, the header alone is {_HEADER.size}")
        frames, points = _HEADER.unpack(header)
        if not 1 <= frames <= MAX_FRAMES:
            raise ValueError(f"{path}: MDD frameCount {frames} is outside 1..{MAX_FRAMES}")
        if not 1 <= points <= MAX_POINTS:
            raise ValueError(f"{path}: MDD pointCount {points} is outside 1..{MAX_POINTS}")
        expected = _HEADER.size + 4 * frames + 12 * frames * points
        if size != expected:
            kind = "truncated MDD file" if size < expected else "trailing bytes in MDD file"
            raise ValueError(f"{path}: {kind}: header promises {frames} frames of {points} points ({expected} bytes), file has {size}")
        times = np.frombuffer(handle.read(4 * frames), dtype=">f4").astype(np.float64)
        data = handle.read(12 * frames * points)
    if len(data) != 12 * frames * points:
        raise ValueError(f"{path}: truncated MDD file while reading")
    positions = np.frombuffer(data, dtype=">f4").astype(np.float32).reshape(frames, points, 3)
    if not (np.isfinite(positions).all() and np.isfinite(times).all()):
        raise ValueError(f"{path}: MDD holds NaN or infinity")
    return MddCache(points=positions, times=times, fps=frame_rate(times))


def encode_mdd(points: np.ndarray, fps: float, start_time: float = 0.0) -> bytes:
    """MDD bytes for points (F, P, 3), frame k at start_time + k / fps seconds."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 3 or points.shape[2] != 3 or points.shape[0] < 1 or points.shape[1] < 1:
        raise ValueError(f"points must be (F, P, 3) with F, P >= 1, got {points.shape}")
    if not fps > 0:
        raise ValueError(f"fps {fps} must be positive")
    times = start_time + np.arange(points.shape[0]) / fps
    return _HEADER.pack(points.shape[0], points.shape[1]) + times.astype(">f4").tobytes() + points.astype(">f4").tobytes()


def write_mdd(path: str | os.PathLike, points: np.ndarray, fps: float, start_time: float = 0.0) -> None:
    Path(path).write_bytes(encode_mdd(points, fps, start_time))
