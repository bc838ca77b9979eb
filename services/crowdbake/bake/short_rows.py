"""Reductions along short rows ((N, k) arrays with k of 2 to 4) at the cost of their arithmetic.

numpy's reductions over a short last axis (`x.sum(axis=1)`, `x.min(axis=1)`, `np.linalg.norm(x, axis=1)`)
pay a set-up per row, about twenty times the arithmetic for (N, 3); these add the columns left to right,
which is bitwise what numpy gives for such rows (services/tests/test_impostor.py checks it)."""
from __future__ import annotations

import numpy as np


def row_sum(values: np.ndarray) -> np.ndarray:
    """(N,) sums of the rows of (N, k) `values`, added left to right: bitwise what values.sum(axis=1) gives
    for a short row (numpy adds it in order), at a twentieth of the cost (numpy's reduction pays per row)."""
    total = values[:, 0].copy()
    for column in range(1, values.shape[1]):
        total += values[:, column]
    return total


def row_norm(values: np.ndarray) -> np.ndarray:
    """(N,) Euclidean lengths of the rows of (N, k) `values`: bitwise np.linalg.norm(values, axis=1)."""
    return np.sqrt(row_sum(values * values))


def row_min(values: np.ndarray) -> np.ndarray:
    """(N,) smallest value of each row of (N, k) `values` (values.min(axis=1), without its per-row cost)."""
    smallest = values[:, 0].copy()
    for column in range(1, values.shape[1]):
        np.minimum(smallest, values[:, column], out=smallest)
    return smallest
