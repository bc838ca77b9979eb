"""Skinned pose caches, CBSK (shared_formats/SPEC.md "Skinned pose cache"): a body stored as its rest
mesh, four joint influences a vertex and each joint's skinning matrix per frame, where a CBPC stores
every vertex of every frame.

The decoder checks in the spec's order (so every strict prefix of a valid file is `truncated`), skins
every frame on the CPU to check the header's bounds, and hands back a `SkinnedPoseCache` whose
`positions` and `normals` are those skinned frames: every reader of pose caches (the export, the
fidelity scores, the references) reads a skinned body as it reads any other.
"""
from __future__ import annotations

import functools
import struct
from dataclasses import dataclass

import numpy as np

from crowdbake.formats.binary import BOUNDS_TOLERANCE, NORMAL_LENGTH_TOLERANCE, _COMMON, _check_common
from crowdbake.formats.errors import FormatError
from crowdbake.geometry import skin

SKINNED_POSE_CACHE_MAGIC = b"CBSK"
SKINNED_POSE_CACHE_VERSION = 1
MAX_JOINTS = 1024
# frame_count x vertex_count at most: a reader skins every frame to check the bounds, and the frames are
# not stored, so a small file could otherwise ask for hours of work (a 32,768-vertex body, 2,048 frames).
MAX_VERTEX_FRAMES = 1 << 26
# Weights are unorm16 codes whose four per vertex sum to exactly this (a partition of unity, stored exactly).
WEIGHT_CODE_SUM = 65535
# A weighted joint's 3 x 3 block must be invertible for the normal's inverse transpose.
MIN_ABS_DETERMINANT = 1e-6
# The reader checks the bounds skinning this many (frame, vertex) pairs at a time (about 8 MB of work arrays).
BOUNDS_CHUNK_PAIRS = 1 << 15
# vertex_count, index_count, frame_count, joint_count, fps, bounds_min, bounds_max, reserved
_FIELDS = struct.Struct("<IIIIf3f3fI")
HEADER_SIZE = _COMMON.size + _FIELDS.size
assert HEADER_SIZE == 64


@dataclass(frozen=True)
class SkinnedPoseCache:
    """A CBSK file, read. indices (T, 3) uint32; uvs (V, 2); rest_positions, rest_normals (V, 3) float32;
    joints (V, 4) uint16; weight_codes (V, 4) uint16; matrices (F, J, 3, 4) float32. `positions`,
    `normals`: (F, V, 3) float32, the frames skinned (SPEC.md's maths) when first asked for, so it reads
    like a crowdbake.formats.binary PoseCache without holding frames nobody reads."""

    indices: np.ndarray
    uvs: np.ndarray
    rest_positions: np.ndarray
    rest_normals: np.ndarray
    joints: np.ndarray
    weight_codes: np.ndarray
    matrices: np.ndarray
    frames_per_second: float
    version: int = SKINNED_POSE_CACHE_VERSION
    magic: bytes = SKINNED_POSE_CACHE_MAGIC

    @functools.cached_property
    def _frames(self) -> tuple[np.ndarray, np.ndarray]:
        return skin_frames(self.rest_positions, self.rest_normals, self.joints, self.weight_codes, self.matrices)

    @property
    def positions(self) -> np.ndarray:
        return self._frames[0]

    @property
    def normals(self) -> np.ndarray:
        return self._frames[1]

    @property
    def vertex_count(self) -> int:
        return int(self.uvs.shape[0])

    @property
    def frame_count(self) -> int:
        return int(self.matrices.shape[0])

    @property
    def triangle_count(self) -> int:
        return int(self.indices.shape[0])

    @property
    def joint_count(self) -> int:
        return int(self.matrices.shape[1])


def file_size(index_count: int, vertex_count: int, frame_count: int, joint_count: int) -> int:
    """Bytes of a CBSK file of these counts (SPEC.md)."""
    return HEADER_SIZE + 4 * index_count + 48 * vertex_count + 48 * frame_count * joint_count


def weight_codes(weights: np.ndarray) -> np.ndarray:
    """(V, 4) weights (any non-negative, not all zero per vertex) -> (V, 4) uint16 codes summing to exactly
    WEIGHT_CODE_SUM per vertex: normalised, rounded, and the rounding's remainder put on each vertex's
    largest weight (it moves that weight by at most 2 / 65535)."""
    weights = np.asarray(weights, dtype=np.float64)
    if weights.ndim != 2 or weights.shape[1] != 4:
        raise ValueError(f"weights must be (V, 4), got {weights.shape}")
    totals = weights.sum(axis=1, keepdims=True)
    if not np.isfinite(weights).all() or (weights < 0).any() or (totals <= 0).any():
        raise ValueError("every vertex needs finite, non-negative weights that do not all vanish")
    codes = np.rint(weights / totals * WEIGHT_CODE_SUM).astype(np.int64)
    largest = np.argmax(weights, axis=1)
    codes[np.arange(len(codes)), largest] += WEIGHT_CODE_SUM - codes.sum(axis=1)
    return codes.astype(np.uint16)


def skin_frames(rest_positions: np.ndarray, rest_normals: np.ndarray, joints: np.ndarray, codes: np.ndarray,
                matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frames a CBSK stores: (F, V, 3) float32 positions and unit normals of the rest mesh skinned by
    (F, J, 3, 4) matrices with weights codes / 65535 (crowdbake.geometry.skin), normals turned by the
    matrices' 3 x 3 blocks (SPEC.md)."""
    return skin(rest_positions, rest_normals, joints, codes.astype(np.float32) / np.float32(WEIGHT_CODE_SUM), matrices,
                inverse_transpose_normals=False)


def encode_skinned_pose_cache(indices: np.ndarray, uvs: np.ndarray, rest_positions: np.ndarray, rest_normals: np.ndarray,
                              joints: np.ndarray, weights: np.ndarray, matrices: np.ndarray, frames_per_second: float) -> bytes:
    """Serialise a CBSK. indices (T, 3) or (3T,); uvs (V, 2); rest_positions, rest_normals (V, 3); joints
    (V, 4) int; weights (V, 4) float (coded by weight_codes); matrices (F, J, 3, 4) or (F, J, 4, 4) (the
    top three rows are stored). The header's bounds are the skinned frames' (skinned_bounds)."""
    indices = np.ascontiguousarray(indices, dtype="<u4").reshape(-1)
    uvs = np.ascontiguousarray(uvs, dtype="<f4")
    rest_positions = np.ascontiguousarray(rest_positions, dtype="<f4")
    rest_normals = np.ascontiguousarray(rest_normals, dtype="<f4")
    joints = np.asarray(joints)
    matrices = np.ascontiguousarray(np.asarray(matrices)[:, :, :3, :], dtype="<f4")
    vertex_count = len(rest_positions)
    frame_count, joint_count = matrices.shape[:2]
    if uvs.shape != (vertex_count, 2) or rest_normals.shape != (vertex_count, 3) or joints.shape != (vertex_count, 4):
        raise ValueError(f"uvs, rest normals and joints must be ({vertex_count}, 2/3/4), got {uvs.shape}, {rest_normals.shape}, {joints.shape}")
    if indices.size == 0 or indices.size % 3 or vertex_count == 0 or frame_count == 0 or not 1 <= joint_count <= MAX_JOINTS:
        raise ValueError("a skinned pose cache needs a triangle, a vertex, a frame and 1 to 1024 joints")
    if int(indices.max()) >= vertex_count or joints.min() < 0 or joints.max() >= joint_count:
        raise ValueError("an index or a joint is out of range")
    if not (frames_per_second > 0 and np.isfinite(matrices).all()):
        raise ValueError("frames_per_second must be positive and the matrices finite")
    codes = weight_codes(weights)
    low, high = skinned_bounds(rest_positions, joints, codes, matrices)  # chunked: no frames held
    header = _COMMON.pack(SKINNED_POSE_CACHE_MAGIC, SKINNED_POSE_CACHE_VERSION, HEADER_SIZE,
                          file_size(indices.size, vertex_count, frame_count, joint_count))
    header += _FIELDS.pack(vertex_count, indices.size, frame_count, joint_count, float(frames_per_second), *low, *high, 0)
    return b"".join([header, indices.tobytes(), uvs.tobytes(), rest_positions.tobytes(), rest_normals.tobytes(),
                     np.ascontiguousarray(joints, dtype="<u2").tobytes(), codes.astype("<u2").tobytes(), matrices.tobytes()])


def _check_fields(fields: tuple, where: str) -> None:
    """The header's own rules, `invalid_header` on the first broken one."""
    vertex_count, index_count, frame_count, joint_count, fps = fields[:5]
    if vertex_count == 0 or frame_count == 0 or index_count == 0 or index_count % 3:
        raise FormatError("invalid_header", f"vertex_count {vertex_count}, index_count {index_count}, frame_count {frame_count}: "
                          "all must be positive and index_count a multiple of 3", where)
    if not 1 <= joint_count <= MAX_JOINTS:
        raise FormatError("invalid_header", f"joint_count {joint_count} must be 1 to {MAX_JOINTS}", where)
    if vertex_count * frame_count > MAX_VERTEX_FRAMES:
        raise FormatError("invalid_header", f"{frame_count} frames of {vertex_count} vertices: more than the {MAX_VERTEX_FRAMES} "
                          "a skinned pose cache holds", where)
    if fields[11] != 0:
        raise FormatError("invalid_header", "reserved must be 0", where)
    if not (np.isfinite(fps) and fps > 0):
        raise FormatError("invalid_header", f"frames_per_second {fps} must be positive", where)


def _check_skinning(joints: np.ndarray, codes: np.ndarray, rest_normals: np.ndarray, matrices: np.ndarray, where: str) -> None:
    """The payload's rules before skinning: joints in range, weights summing to 65535, unit rest normals,
    finite matrices, and every weighted joint's 3 x 3 block invertible in every frame."""
    joint_count = matrices.shape[1]
    if joints.max() >= joint_count:
        raise FormatError("invalid_data", f"joint {int(joints.max())} >= joint_count {joint_count}", where)
    sums = codes.astype(np.int64).sum(axis=1)
    if (sums != WEIGHT_CODE_SUM).any():
        vertex = int(np.argmax(sums != WEIGHT_CODE_SUM))
        raise FormatError("invalid_data", f"vertex {vertex}'s weight codes sum to {int(sums[vertex])}, not {WEIGHT_CODE_SUM}", where)
    if np.abs(np.linalg.norm(rest_normals, axis=1) - 1.0).max() > NORMAL_LENGTH_TOLERANCE:
        raise FormatError("invalid_data", "rest normals are not unit length", where)
    if not np.isfinite(matrices).all():
        raise FormatError("invalid_data", "matrices contain NaN or infinity", where)
    used = np.unique(joints[codes > 0])
    determinants = np.abs(np.linalg.det(matrices[:, used, :, :3].astype(np.float64)))
    if used.size and determinants.min() < MIN_ABS_DETERMINANT:
        frame, joint = np.unravel_index(int(np.argmin(determinants)), determinants.shape)
        raise FormatError("invalid_data", f"joint {int(used[joint])}'s matrix at frame {int(frame)} is singular", where)


def decode_skinned_pose_cache(data: bytes, where: str = "skinned pose cache") -> SkinnedPoseCache:
    """Parse and validate a CBSK file; FormatError with the spec's error code. Skins every frame."""
    _check_common(data, SKINNED_POSE_CACHE_MAGIC, SKINNED_POSE_CACHE_VERSION, HEADER_SIZE, where)
    fields = _FIELDS.unpack_from(data, _COMMON.size)
    _check_fields(fields, where)
    vertex_count, index_count, frame_count, joint_count, fps = fields[:5]
    expected = file_size(index_count, vertex_count, frame_count, joint_count)
    if expected != len(data):
        raise FormatError("size_mismatch", f"counts imply {expected} bytes, file has {len(data)}", where)
    offset = HEADER_SIZE

    def take(dtype: str, count: int) -> np.ndarray:
        nonlocal offset
        array = np.frombuffer(data, dtype, count, offset)
        offset += array.nbytes
        return array

    indices = take("<u4", index_count).reshape(-1, 3)
    uvs = take("<f4", 2 * vertex_count).reshape(-1, 2)
    rest_positions = take("<f4", 3 * vertex_count).reshape(-1, 3)
    rest_normals = take("<f4", 3 * vertex_count).reshape(-1, 3)
    joints = take("<u2", 4 * vertex_count).reshape(-1, 4)
    codes = take("<u2", 4 * vertex_count).reshape(-1, 4)
    matrices = take("<f4", 12 * frame_count * joint_count).reshape(frame_count, joint_count, 3, 4)
    if int(indices.max()) >= vertex_count:
        raise FormatError("invalid_data", f"index {int(indices.max())} >= vertex_count {vertex_count}", where)
    for name, array in (("uvs", uvs), ("rest positions", rest_positions), ("rest normals", rest_normals), ("bounds", fields[5:11])):
        if not np.isfinite(array).all():
            raise FormatError("invalid_data", f"{name} contain NaN or infinity", where)
    _check_skinning(joints, codes, rest_normals, matrices, where)
    low, high = skinned_bounds(rest_positions, joints, codes, matrices)
    if (low < np.array(fields[5:8]) - BOUNDS_TOLERANCE).any() or (high > np.array(fields[8:11]) + BOUNDS_TOLERANCE).any():
        raise FormatError("invalid_data", "skinned positions lie outside the header's bounds", where)
    return SkinnedPoseCache(indices, uvs, rest_positions, rest_normals, joints, codes, matrices, float(fps))


def skinned_bounds(rest_positions: np.ndarray, joints: np.ndarray, codes: np.ndarray, matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) minimum and maximum of every skinned position of every frame, skinned BOUNDS_CHUNK_PAIRS
    (frame, vertex) pairs at a time: a reader's memory stays bounded however many frames a file says
    it skins (its frames are not stored, so they could be far larger than the file)."""
    weights = codes.astype(np.float32) / np.float32(WEIGHT_CODE_SUM)
    rest = np.asarray(rest_positions, dtype=np.float32)
    low, high = np.full(3, np.inf, np.float32), np.full(3, -np.inf, np.float32)
    step = max(1, BOUNDS_CHUNK_PAIRS // max(len(rest), 1))
    vertex_step = min(len(rest), BOUNDS_CHUNK_PAIRS)
    for start in range(0, matrices.shape[0], step):
        for first in range(0, len(rest), vertex_step):
            rows = slice(first, first + vertex_step)
            blended = np.einsum("vk,fvkij->fvij", weights[rows], matrices[start:start + step][:, joints[rows]])
            positions = np.einsum("fvij,vj->fvi", blended[..., :3], rest[rows]) + blended[..., 3]
            low, high = np.minimum(low, positions.min(axis=(0, 1))), np.maximum(high, positions.max(axis=(0, 1)))
    return low, high


def is_skinned_pose_cache(data: bytes) -> bool:
    """Whether `data` starts with the CBSK magic (a reader picks its decoder by the file's magic)."""
    return data[:4] == SKINNED_POSE_CACHE_MAGIC


def read_skinned_frame(path, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame of a CBSK file, as crowdbake.formats.binary.read_pose_frame gives a CBPC's: (indices (T, 3)
    uint32, uvs (V, 2), positions (V, 3), normals (V, 3) float32). Checks the header and sizes, then skins
    that frame alone (the whole file's values are checked by decode_skinned_pose_cache when a bundle is
    verified). IndexError for a frame outside."""
    from pathlib import Path

    path = Path(path)
    data = path.read_bytes()
    _check_common(data, SKINNED_POSE_CACHE_MAGIC, SKINNED_POSE_CACHE_VERSION, HEADER_SIZE, path.name)
    fields = _FIELDS.unpack_from(data, _COMMON.size)
    _check_fields(fields, path.name)
    vertex_count, index_count, frame_count, joint_count = fields[:4]
    if file_size(index_count, vertex_count, frame_count, joint_count) != len(data):
        raise FormatError("size_mismatch", "counts disagree with the file's size", path.name)
    if not 0 <= frame < frame_count:
        raise IndexError(f"{path.name}: frame {frame} outside its {frame_count} frames")
    offset = HEADER_SIZE
    indices = np.frombuffer(data, "<u4", index_count, offset).reshape(-1, 3)
    offset += 4 * index_count
    uvs = np.frombuffer(data, "<f4", 2 * vertex_count, offset).reshape(-1, 2)
    offset += 8 * vertex_count
    rest = np.frombuffer(data, "<f4", 6 * vertex_count, offset).reshape(2, -1, 3)
    offset += 24 * vertex_count
    joints = np.frombuffer(data, "<u2", 4 * vertex_count, offset).reshape(-1, 4)
    codes = np.frombuffer(data, "<u2", 4 * vertex_count, offset + 8 * vertex_count).reshape(-1, 4)
    offset += 16 * vertex_count + 48 * joint_count * frame
    matrices = np.frombuffer(data, "<f4", 12 * joint_count, offset).reshape(1, joint_count, 3, 4)
    positions, normals = skin_frames(rest[0], rest[1], joints, codes, matrices)
    return indices.copy(), uvs.copy(), positions[0], normals[0]


def read_any_pose_frame(path, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame of a pose cache of either kind, by its magic: CBSK (read_skinned_frame) or CBPC
    (crowdbake.formats.binary.read_pose_frame)."""
    from crowdbake.formats.binary import read_pose_frame

    with open(path, "rb") as handle:
        skinned = is_skinned_pose_cache(handle.read(4))
    return read_skinned_frame(path, frame) if skinned else read_pose_frame(path, frame)
