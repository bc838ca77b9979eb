"""Morph-target normals: what a glTF reader adds to a base normal to turn it towards a frame's, within
the [-1, 1] a normalized int8 holds. Shared by the morph targets of crowdbake.export.glb and the corrective
targets of crowdbake.export.body_skin. Pure numpy."""
from __future__ import annotations

import numpy as np

# Scales of frame k's normal tried by normal_deltas; 1 (the plain difference) first, so it wins ties.
_NORMAL_SCALES = (1.0, 0.5, 2.0, 4.0, 8.0)


def normal_deltas(base: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """base (V, 3), frames (F, V, 3) unit normals -> (F, V, 3) morph NORMAL deltas within [-1, 1], what a
    normalized int8 holds. A reader normalises base + delta, so the delta may aim at frame k's normal scaled
    by any a > 0: of delta = clip(a · n_k - n_b, -1, 1) for a in _NORMAL_SCALES, the one whose sum points
    closest to n_k. Unclipped (a normal turned less than about 90 degrees) that is the plain difference; a
    normal turned further (cloth folding over) can only be approached, the sum staying within one unit of
    n_b in each component: turned 143 degrees off an axis, it lands 37 degrees short. (Weights above 1 with
    halved deltas would hold every normal, but Blender clamps shape keys to 1.)"""
    base = np.asarray(base, dtype=np.float64)[None]
    frames = np.asarray(frames, dtype=np.float64)
    best = np.clip(frames - base, -1.0, 1.0)
    best_cos = _cosine(base + best, frames)
    for scale in _NORMAL_SCALES[1:]:
        delta = np.clip(scale * frames - base, -1.0, 1.0)
        cos = _cosine(base + delta, frames)
        better = cos > best_cos + 1e-9
        best = np.where(better[..., None], delta, best)
        best_cos = np.maximum(best_cos, cos)
    return best


def _cosine(vectors: np.ndarray, units: np.ndarray) -> np.ndarray:
    """(..., 3) vectors against (..., 3) unit vectors -> (...) cosines; 0-length vectors give -1."""
    lengths = np.linalg.norm(vectors, axis=-1)
    return np.where(lengths > 1e-12, (vectors * units).sum(-1) / np.maximum(lengths, 1e-12), -1.0)
