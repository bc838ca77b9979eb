"""PC2 point caches: the vertex-animation format of 3ds Max, Blender and Houdini.

Layout (little-endian), 32-byte header then samples:

    char[12] magic        b"POINTCACHE2\\0"
    int32    version      1
    int32    numPoints
    float32  startFrame
    float32  sampleRate   frames between samples (1.0 = one sample per frame)
    int32    numSamples
    float32  points[numSamples][numPoints][3]

Users bring their offline cloth simulation as a PC2 file plus the garment's rest
mesh as an OBJ (crowdbake.formats.obj); point k of every sample is OBJ position
k. The reader validates the header against the file size *before* allocating,
so a lying header cannot ask for gigabytes.
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PC2_MAGIC = b"POINTCACHE2\0"
PC2_VERSION = 1
_HEADER = struct.Struct("<12siiffi")  # magic, version, numPoints, startFrame, sampleRate, numSamples
HEADER_SIZE = _HEADER.size
assert HEADER_SIZE == 32
_BYTES_PER_POINT = 12  # three float32

# A cache this large is not a garment; refusing it early keeps a garbled header from
# turning into a multi-gigabyte allocation even if the file were that large.
MAX_POINTS = 1 << 24
MAX_SAMPLES = 1 << 24


@dataclass(frozen=True)
class PointCache:
    """points: (F, V, 3) float32 in the file's units; sample k is at frame start_frame + k * sample_rate."""

    points: np.ndarray
    start_frame: float
    sample_rate: float

    @property
    def sample_count(self) -> int:
        return int(self.points.shape[0])

    @property
    def point_count(self) -> int:
        return int(self.points.shape[1])


def read_pc2(path: str | os.PathLike) -> PointCache:
    """Read and validate a PC2 file.

    Raises ValueError naming the file and the problem: bad magic, unsupported
    version, negative or huge counts, a size that disagrees with the header
    (truncated or trailing bytes), a non-positive sample rate, NaN or infinity.
    """
    path = Path(path)
    file_size = path.stat().st_size
    with open(path, "rb") as handle:
        header = handle.read(HEADER_SIZE)
        if len(header) < HEADER_SIZE:
            raise ValueError(f"{path}: truncated PC2 file: {len(header)} bytes, the header alone is {HEADER_SIZE}")
        magic, version, point_count, start_frame, sample_rate, sample_count = _HEADER.unpack(header)
        if magic != PC2_MAGIC:
            raise ValueError(f"{path}: not a PC2 file: magic is {magic!r}, expected {PC2_MAGIC!r}")
        if version != PC2_VERSION:
            raise ValueError(f"{path}: PC2 version {version} is not supported (only {PC2_VERSION})")
        if not 0 <= point_count <= MAX_POINTS:
            raise ValueError(f"{path}: PC2 numPoints {point_count} is outside 0..{MAX_POINTS}")
        if not 0 <= sample_count <= MAX_SAMPLES:
            raise ValueError(f"{path}: PC2 numSamples {sample_count} is outside 0..{MAX_SAMPLES}")
        if not (np.isfinite(start_frame) and np.isfinite(sample_rate)):
            raise ValueError(f"{path}: PC2 startFrame {start_frame} / sampleRate {sample_rate} must be finite")
        if sample_rate <= 0:
            raise ValueError(f"{path}: PC2 sampleRate {sample_rate} must be positive")
        expected = HEADER_SIZE + _BYTES_PER_POINT * point_count * sample_count
        if file_size < expected:
            raise ValueError(
                f"{path}: truncated PC2 file: header promises {sample_count} samples of {point_count} points "
                f"({expected} bytes), file has {file_size}"
            )
        if file_size > expected:
            raise ValueError(
                f"{path}: {file_size - expected} trailing bytes after the {sample_count} samples of "
                f"{point_count} points the header declares"
            )
        data = handle.read(expected - HEADER_SIZE)
    if len(data) != expected - HEADER_SIZE:  # the file changed under us
        raise ValueError(f"{path}: truncated PC2 file while reading ({len(data)} of {expected - HEADER_SIZE} bytes)")
    points = np.frombuffer(data, dtype="<f4").astype(np.float32).reshape(sample_count, point_count, 3)
    if not np.isfinite(points).all():
        bad = np.argwhere(~np.isfinite(points))[0]
        raise ValueError(f"{path}: PC2 point {bad[1]} of sample {bad[0]} is NaN or infinite")
    return PointCache(points=points, start_frame=float(start_frame), sample_rate=float(sample_rate))


def pc2_header(point_count: int, sample_count: int, start_frame: float = 0.0, sample_rate: float = 1.0) -> bytes:
    """The 32-byte header of a PC2 of `sample_count` frames of `point_count` points; the frames follow
    it as (point_count, 3) little-endian float32 each (lets a writer stream frames one at a time)."""
    return _HEADER.pack(PC2_MAGIC, PC2_VERSION, int(point_count), float(start_frame), float(sample_rate), int(sample_count))


def encode_pc2(points: np.ndarray, start_frame: float = 0.0, sample_rate: float = 1.0) -> bytes:
    """PC2 bytes for points (F, V, 3) float; see write_pc2."""
    points = np.asarray(points)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points must be (F, V, 3), got shape {points.shape}")
    if points.shape[0] > MAX_SAMPLES or points.shape[1] > MAX_POINTS:
        raise ValueError(f"points {points.shape} exceed the reader's limits ({MAX_SAMPLES} samples, {MAX_POINTS} points)")
    if not np.isfinite(points).all():
        raise ValueError("points contain NaN or infinity")
    if not (np.isfinite(start_frame) and np.isfinite(sample_rate) and sample_rate > 0):
        raise ValueError(f"start_frame {start_frame} must be finite and sample_rate {sample_rate} positive")
    header = _HEADER.pack(PC2_MAGIC, PC2_VERSION, points.shape[1], float(start_frame), float(sample_rate), points.shape[0])
    return header + np.ascontiguousarray(points, dtype="<f4").tobytes()


def write_pc2(
    path: str | os.PathLike, points: np.ndarray, start_frame: float = 0.0, sample_rate: float = 1.0
) -> None:
    """Write points (F, V, 3) as a PC2 file (float32, little-endian): F samples of V points."""
    data = encode_pc2(points, start_frame, sample_rate)
    Path(path).write_bytes(data)
