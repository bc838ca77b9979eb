"""Quantized pose frames (shared_formats/SPEC.md, "Pose cache version 2"): 16-bit positions within each
frame's bounds and 16-bit octahedral normals.

Positions: each axis of a frame is stored as `q = round((p - min) / (max - min) · 65535)` and read back as
`min + q · ((max - min) / 65535)` in float32, the same expression crowdview's mesh.vert.glsl evaluates.
Normals: the octahedral map of Meyer et al., "On floating-point normal vectors" (EGSR 2010), section 3.3
(as in Cigolle et al., "A survey of efficient representations for independent unit vectors", JCGT 2014),
each of its two coordinates in [-1, 1] stored as `round((c + 1) / 2 · 65535)`.
"""
from __future__ import annotations

import numpy as np

QUANT_MAX = 65535  # 16 bits per stored coordinate
# The most a decoded position may differ from the baked one, per axis (SPEC.md "Pose cache version 2"):
# a fifth of a millimetre-scale cloth wrinkle. Half a 16-bit step reaches it only for a frame 65 m across;
# a 2 m character's step is 0.03 mm.
MAX_POSITION_ERROR_M = 0.0005
# The largest angle (degrees) between a unit normal and its 2 x 16-bit octahedral code, decoded: measured
# by services/tests/test_pose_codec.py over a dense sphere and stated in SPEC.md.
OCTAHEDRAL_MAX_ERROR_DEG = 0.005


def frame_bounds(positions: np.ndarray) -> np.ndarray:
    """(F, V, 3) float positions → (F, 2, 3) float32: each frame's per-axis minimum, then maximum."""
    positions = np.asarray(positions, dtype=np.float32)
    if positions.ndim != 3 or positions.shape[2] != 3:
        raise ValueError(f"positions must be (F, V, 3), got {positions.shape}")
    return np.stack([positions.min(axis=1), positions.max(axis=1)], axis=1)


def _steps(bounds: np.ndarray) -> np.ndarray:
    """(F, 2, 3) bounds → (F, 1, 3) float32 metres per code step, in the decoder's float32 arithmetic."""
    bounds = np.asarray(bounds, dtype=np.float32)
    return ((bounds[:, 1] - bounds[:, 0]) / np.float32(QUANT_MAX)).astype(np.float32)[:, None, :]


def quantize_positions(positions: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(F, V, 3) float positions inside (F, 2, 3) `bounds` → (F, V, 3) uint16 codes; an axis a frame does
    not extend along codes as 0."""
    positions = np.asarray(positions, dtype=np.float64)
    bounds = np.asarray(bounds, dtype=np.float64)
    extent = (bounds[:, 1] - bounds[:, 0])[:, None, :]
    relative = np.divide(positions - bounds[:, 0][:, None, :], extent, out=np.zeros_like(positions), where=extent > 0)
    return np.clip(np.rint(relative * QUANT_MAX), 0, QUANT_MAX).astype(np.uint16)


def check_position_error(positions: np.ndarray, decoded: np.ndarray) -> float:
    """The largest per-axis distance (metres) between (F, V, 3) `positions` and their `decoded` codes;
    ValueError naming the frame where it passes MAX_POSITION_ERROR_M."""
    error = np.abs(np.asarray(decoded, dtype=np.float64) - np.asarray(positions, dtype=np.float64)).max(axis=(1, 2))
    worst = int(np.argmax(error))
    if error[worst] > MAX_POSITION_ERROR_M:
        raise ValueError(f"frame {worst} spans too far for 16-bit positions: error {error[worst] * 1000:.3f} mm, "
                         f"the bound is {MAX_POSITION_ERROR_M * 1000:.1f} mm")
    return float(error[worst])


def dequantize_positions(codes: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """(F, V, 3) uint16 codes and (F, 2, 3) bounds → (F, V, 3) float32 positions (the shader's expression)."""
    bounds = np.asarray(bounds, dtype=np.float32)
    return (bounds[:, 0][:, None, :] + np.asarray(codes).astype(np.float32) * _steps(bounds)).astype(np.float32)


def position_error_bound(bounds: np.ndarray) -> np.ndarray:
    """(F, 2, 3) bounds → (F,) the largest per-axis distance (metres) between a position and its decoded
    code: half a step, plus float32 rounding of the decode (a few ulps of the coordinate)."""
    bounds = np.asarray(bounds, dtype=np.float64)
    half_step = (bounds[:, 1] - bounds[:, 0]).max(axis=1) / (2 * QUANT_MAX)
    magnitude = np.abs(bounds).max(axis=(1, 2))
    return half_step + 4 * np.finfo(np.float32).eps * magnitude


def stored_frames(positions: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, V, 3) positions and unit normals as a reader of a version-2 pose cache gets them back, float32:
    for whatever must match the pose caches to the bit without reading them."""
    positions = np.asarray(positions, dtype=np.float32)
    bounds = frame_bounds(positions)
    normals = np.asarray(normals, dtype=np.float32)  # the writer codes float32 normals
    return dequantize_positions(quantize_positions(positions, bounds), bounds), decode_octahedral(encode_octahedral(normals))


def _sign_not_zero(values: np.ndarray) -> np.ndarray:
    return np.where(values >= 0, 1.0, -1.0)


def encode_octahedral(normals: np.ndarray, code_max: int = QUANT_MAX) -> np.ndarray:
    """(..., 3) unit normals → (..., 2) uint16 octahedral codes in [0, code_max] (the pose caches' 16 bits
    by default; the export's VAT packs two 8-bit codes in one word)."""
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape[-1] != 3:
        raise ValueError(f"normals must be (..., 3), got {normals.shape}")
    projected = normals / np.maximum(np.abs(normals).sum(axis=-1, keepdims=True), 1e-30)
    x, y, z = projected[..., 0], projected[..., 1], projected[..., 2]
    folded_x = np.where(z < 0, (1 - np.abs(y)) * _sign_not_zero(x), x)
    folded_y = np.where(z < 0, (1 - np.abs(x)) * _sign_not_zero(y), y)
    octahedral = np.stack([folded_x, folded_y], axis=-1)
    return np.clip(np.rint((octahedral + 1) * 0.5 * code_max), 0, code_max).astype(np.uint16)


def decode_octahedral(codes: np.ndarray, code_max: int = QUANT_MAX) -> np.ndarray:
    """(..., 2) uint16 octahedral codes in [0, code_max] → (..., 3) float32 unit normals (mesh.vert.glsl
    decodes alike)."""
    octahedral = np.asarray(codes).astype(np.float32) * np.float32(2.0 / code_max) - np.float32(1.0)
    x, y = octahedral[..., 0], octahedral[..., 1]
    z = 1 - np.abs(x) - np.abs(y)
    unfolded_x = np.where(z < 0, (1 - np.abs(y)) * _sign_not_zero(x), x)
    unfolded_y = np.where(z < 0, (1 - np.abs(x)) * _sign_not_zero(y), y)
    vectors = np.stack([unfolded_x, unfolded_y, z], axis=-1)
    return (vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)).astype(np.float32)
