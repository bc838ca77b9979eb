"""The node hierarchy: local transforms, parents, and each node's nearest joint above it; TRS matrix helpers.

Column vectors and glTF's column-major matrices throughout. The hierarchy is walked once, parents
before children (linear in the node count: a 16,000-node chain loads in milliseconds).
"""
from __future__ import annotations

import numpy as np

from crowdbake.formats.gltf.document import _Document
from crowdbake.geometry import quaternion_matrices


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> (4,) unit quaternion (x, y, z, w) with w >= 0 (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def trs_matrix(translation: np.ndarray, rotation: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(..., 3), (..., 4) xyzw, (..., 3) -> (..., 4, 4) float64 matrices T @ R @ S."""
    translation = np.asarray(translation, dtype=np.float64)
    rotation_matrix = quaternion_matrices(rotation)
    out = np.zeros(rotation_matrix.shape[:-2] + (4, 4))
    out[..., :3, :3] = rotation_matrix * np.asarray(scale, dtype=np.float64)[..., None, :]
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def decompose_matrix(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(4, 4) affine matrix without shear -> translation (3,), rotation (4,) xyzw, scale (3,)."""
    m = np.asarray(m, dtype=np.float64)
    translation = m[:3, 3].copy()
    scale = np.linalg.norm(m[:3, :3], axis=0)
    if np.any(scale == 0):
        raise ValueError("matrix has a zero scale and cannot be decomposed")
    rotation = m[:3, :3] / scale
    if np.linalg.det(rotation) < 0:  # a mirror: put it in the x scale
        scale[0] = -scale[0]
        rotation[:, 0] = -rotation[:, 0]
    return translation, matrix_to_quaternion(rotation), scale



def local_matrices(doc: _Document) -> np.ndarray:
    """Every node's local transform -> (N, 4, 4) float64, TRS nodes converted in one vectorised call."""
    nodes = doc.gltf.nodes
    count = len(nodes)
    columns = {"translation": [[0.0] * 3] * count, "rotation": [[0.0, 0.0, 0.0, 1.0]] * count, "scale": [[1.0] * 3] * count}
    matrices: dict[int, list] = {}
    for index, node in enumerate(nodes):
        if node.matrix is not None:
            matrices[index] = node.matrix
            continue
        for name, column in columns.items():
            value = getattr(node, name)
            if value is not None:
                column[index] = value  # type: ignore[index]
    arrays = {}
    for name, width in (("translation", 3), ("rotation", 4), ("scale", 3)):
        try:
            arrays[name] = np.array(columns[name], dtype=np.float64)
        except (ValueError, TypeError):
            arrays[name] = np.zeros(0)
        if arrays[name].shape != (count, width) or not np.isfinite(arrays[name]).all():
            bad = next(k for k, v in enumerate(columns[name]) if not (isinstance(v, list) and len(v) == width and np.isfinite(np.asarray(v, dtype=float)).all()))
            raise ValueError(f"{doc.where}: nodes[{bad}].{name} must be {width} finite numbers")
    length = np.linalg.norm(arrays["rotation"], axis=1)
    if (length < 1e-6).any():
        raise ValueError(f"{doc.where}: nodes[{int(np.argmax(length < 1e-6))}] has the zero quaternion as rotation")
    local = trs_matrix(arrays["translation"], arrays["rotation"], arrays["scale"])
    for index, matrix in matrices.items():
        values = np.asarray(matrix, dtype=np.float64)
        if values.shape != (16,) or not np.isfinite(values).all():
            raise ValueError(f"{doc.where}: nodes[{index}].matrix must be 16 finite numbers")
        local[index] = values.reshape(4, 4).T  # glTF stores column-major
    return local


def node_parents(doc: _Document) -> tuple[np.ndarray, list[int]]:
    """Each node's parent (-1 for roots) and the nodes in parent-before-child order.

    Linear in the node count. Raises ValueError for a missing child, a node with two parents, or a cycle
    (with one parent per node, a node no root reaches lies on or below a cycle)."""
    nodes = doc.gltf.nodes
    parents = np.full(len(nodes), -1, dtype=np.int64)
    for index, node in enumerate(nodes):
        for child in node.children or []:
            if not isinstance(child, int) or not 0 <= child < len(nodes):
                raise ValueError(f"{doc.where}: nodes[{index}] has child {child}, which does not exist")
            if parents[child] != -1 or child == index:
                raise ValueError(f"{doc.where}: nodes[{child}] has two parents ({parents[child]} and {index})")
            parents[child] = index
    order = [int(n) for n in np.flatnonzero(parents == -1)]
    cursor = 0
    while cursor < len(order):
        order.extend(nodes[order[cursor]].children or [])
        cursor += 1
    if len(order) != len(nodes):
        stranded = sorted(set(range(len(nodes))) - set(order))[0]
        raise ValueError(f"{doc.where}: the node hierarchy has a cycle through nodes[{stranded}]")
    return parents, order


def joint_anchors(parents: np.ndarray, order: list[int], local: np.ndarray, node_to_joint: dict[int, int]):
    """For every node: its nearest joint ancestor (-1 if none) and the product of the non-joint nodes'
    local transforms strictly between that ancestor and the node (N, 4, 4). One pass, parents first."""
    anchor = np.full(len(parents), -1, dtype=np.int64)
    between = np.empty((len(parents), 4, 4))
    identity = np.eye(4)
    for node in order:
        parent = parents[node]
        if parent < 0:
            between[node] = identity
        elif parent in node_to_joint:
            anchor[node], between[node] = node_to_joint[parent], identity
        else:
            anchor[node], between[node] = anchor[parent], between[parent] @ local[parent]
    return anchor, between
