"""The low-resolution LOD: a real mesh simplifier whose output keeps a subset of the input vertices.

Dobbyn et al. 2006, section 6: the high-resolution clothed character has 13,056 triangles and the low one
1,899 (PAPER_LOD_RATIO). Because the pose caches are keyframed meshes, the low LOD must follow the *same*
motion as the high one: meshoptimizer's simplifier (edge collapses onto existing vertices) returns indices
into the input vertex buffer, so the low LOD is the high LOD's triangles replaced by fewer triangles over a
subset of its vertices, and every frame's positions and normals carry over by indexing (`kept`).

What is preserved, and why:
- UV seams: meshoptimizer welds vertices with identical positions to find the topology, so a seam (one
  position, two texture coordinates) is classified as a seam and collapses only along itself; the texture
  does not tear.
- Garment borders (hems, waist, cuffs): `meshopt_SimplifyLockBorder` keeps every vertex on an open border
  where it is, so the garment's outline and its fit to the body do not shrink.
- Texture coordinates enter the error metric (`simplify_with_attributes`), so collapses that would smear
  the texture cost more.

The simplification runs on one frame's positions (the caller picks it; the first frame of the cycle). Pure:
arrays in, arrays out.
"""
from __future__ import annotations

import ctypes
import logging
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

# Section 6 of the paper: 13,056 triangles for the high LOD and 1,899 for the low one.
PAPER_HIGH_TRIANGLES = 13_056
PAPER_LOW_TRIANGLES = 1_899
PAPER_LOD_RATIO = PAPER_LOW_TRIANGLES / PAPER_HIGH_TRIANGLES
# meshoptimizer's error is relative to the mesh's extent; 1 means "no limit", so the triangle target decides.
UNBOUNDED_RELATIVE_ERROR = 1.0
# Weight of texture coordinates against positions in the error metric. UVs span [0, 1] while positions are
# normalised to the mesh's extent, so 1 makes a full-texture smear cost as much as a full-body move; a
# quarter keeps geometry first while still steering collapses away from UV distortion.
UV_ATTRIBUTE_WEIGHT = 0.25
# A low LOD within this fraction of its target triangle count is on target (the tests hold it to this).
TARGET_TOLERANCE = 0.05


@dataclass(frozen=True)
class Simplified:
    """A low LOD of one mesh part.

    faces: (T', 3) uint32, counter-clockwise, indexing the *kept* vertices (0 .. len(kept) - 1).
    kept: (V',) int64, ascending indices of the input vertices the low LOD uses; positions[:, kept] and
        normals[:, kept] of any frame are the low LOD's.
    target_triangles: what was asked; relative_error: meshoptimizer's reported error (fraction of extent).
    locked_border: whether open-border vertices were locked.
    """

    faces: np.ndarray
    kept: np.ndarray
    target_triangles: int
    relative_error: float
    locked_border: bool

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])


def _check_mesh(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    positions = np.ascontiguousarray(positions, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) == 0:
        raise ValueError(f"expected (V, 3) positions, got {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"expected (T, 3) faces, got {faces.shape}")
    if int(faces.max()) >= len(positions):
        raise ValueError(f"a face index {int(faces.max())} is out of range for {len(positions)} vertices")
    if not np.isfinite(positions).all():
        raise ValueError("positions contain NaN or infinity")
    return positions, faces


def target_for_parts(triangle_counts: list[int], total_target: int) -> list[int]:
    """Split a whole-character triangle target over its parts in proportion to their triangle counts.

    Largest-remainder rounding, so the parts' targets add up to `total_target` exactly; every part keeps
    at least one triangle.
    """
    counts = np.asarray(triangle_counts, dtype=np.float64)
    if counts.ndim != 1 or len(counts) == 0 or (counts <= 0).any():
        raise ValueError(f"target_for_parts: need positive triangle counts, got {triangle_counts}")
    if total_target < len(counts):
        raise ValueError(f"target_for_parts: {total_target} triangles cannot cover {len(counts)} parts")
    exact = counts / counts.sum() * total_target
    shares = np.floor(exact).astype(np.int64)
    for index in np.argsort(-(exact - shares), kind="stable")[: total_target - int(shares.sum())]:
        shares[index] += 1
    return [max(1, int(share)) for share in shares]


def weld_by_position(positions: np.ndarray) -> np.ndarray:
    """(V,) int64: for each vertex the smallest index of a vertex at exactly the same position.

    Seams split one position into several vertices; welding them recovers the surface's topology.
    """
    positions = np.ascontiguousarray(positions, dtype=np.float32)
    _, first, inverse = np.unique(positions, axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)].astype(np.int64)


def boundary_edges(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(E, 2) int64 sorted pairs of welded vertex ids on open borders (edges used by exactly one triangle).

    Vertices are welded by position first, so UV seams are not borders.
    """
    weld = weld_by_position(positions)
    welded = weld[np.asarray(faces, dtype=np.int64)]
    edges = np.sort(np.concatenate([welded[:, [0, 1]], welded[:, [1, 2]], welded[:, [2, 0]]]), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


def border_vertex_mask(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) bool: vertices whose position lies on an open border of the welded surface."""
    weld = weld_by_position(positions)
    on_border = np.zeros(len(positions), dtype=bool)
    on_border[np.unique(boundary_edges(positions, faces))] = True
    return on_border[weld]


def _simplify_with_attributes(
    destination: np.ndarray,
    indices: np.ndarray,
    positions: np.ndarray,
    uvs: np.ndarray,
    target_triangles: int,
    options: int,
    result_error: np.ndarray,
) -> int:
    """meshopt_simplifyWithAttributes through ctypes with every argument typed.

    The binding (meshoptimizer 0.2.30a0 on PyPI) declares no argtypes for this function, so ctypes cannot
    pass its float argument and the binding's wrapper fails; the C signature is meshoptimizer's
    (destination, indices, index_count, positions, vertex_count, positions_stride, attributes,
    attributes_stride, attribute_weights, attribute_count, vertex_lock, target_index_count, target_error,
    options, result_error).
    """
    from meshoptimizer._loader import lib

    attributes = np.ascontiguousarray(uvs, dtype=np.float32)
    weights = np.full(attributes.shape[1], UV_ATTRIBUTE_WEIGHT, dtype=np.float32)
    error = ctypes.c_float(0.0)
    count = lib.meshopt_simplifyWithAttributes(
        destination.ctypes.data_as(ctypes.POINTER(ctypes.c_uint)),
        indices.ctypes.data_as(ctypes.POINTER(ctypes.c_uint)),
        ctypes.c_size_t(indices.size),
        positions.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),
        ctypes.c_size_t(len(positions)),
        ctypes.c_size_t(positions.strides[0]),
        attributes.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),
        ctypes.c_size_t(attributes.strides[0]),
        weights.ctypes.data_as(ctypes.POINTER(ctypes.c_float)),
        ctypes.c_size_t(len(weights)),
        ctypes.POINTER(ctypes.c_ubyte)(),  # no per-vertex locks: borders are locked by the option
        ctypes.c_size_t(3 * target_triangles),
        ctypes.c_float(UNBOUNDED_RELATIVE_ERROR),
        ctypes.c_uint(options),
        ctypes.byref(error),
    )
    result_error[0] = error.value
    return int(count)


def _run_meshoptimizer(
    positions: np.ndarray, faces: np.ndarray, uvs: np.ndarray | None, target_triangles: int, options: int
) -> tuple[np.ndarray, float]:
    import meshoptimizer  # C library behind a ctypes binding

    indices = faces.reshape(-1)
    destination = np.zeros(indices.size, dtype=np.uint32)
    result_error = np.zeros(1, dtype=np.float32)
    if uvs is None:
        count = meshoptimizer.simplify(
            destination,
            indices,
            positions,
            target_index_count=3 * target_triangles,
            target_error=UNBOUNDED_RELATIVE_ERROR,
            options=options,
            result_error=result_error,
        )
    else:
        count = _simplify_with_attributes(destination, indices, positions, uvs, target_triangles, options, result_error)
    return destination[:count].reshape(-1, 3), float(result_error[0])


def _sloppy_near_target(positions: np.ndarray, faces: np.ndarray, target_triangles: int) -> tuple[np.ndarray, float]:
    """meshopt_simplifySloppy's result nearest `target_triangles`: (T', 3) uint32 indices into `positions`
    and its relative error. Its grid makes the count move in steps, so the asked count is searched (by
    bisection between the target and the input's size) for the result closest to the target."""
    import meshoptimizer

    indices = faces.reshape(-1)

    def run(asked: int) -> tuple[np.ndarray, float]:
        destination = np.zeros(indices.size, dtype=np.uint32)
        result_error = np.zeros(1, dtype=np.float32)
        count = meshoptimizer.simplify_sloppy(destination, indices, positions, target_index_count=3 * asked,
                                              target_error=UNBOUNDED_RELATIVE_ERROR, result_error=result_error)
        return destination[:count].reshape(-1, 3), float(result_error[0])

    best = run(target_triangles)
    low, high = target_triangles, len(faces)
    while len(best[0]) != target_triangles and high - low > 1:
        middle = (low + high) // 2
        tried = run(middle)
        if abs(len(tried[0]) - target_triangles) < abs(len(best[0]) - target_triangles):
            best = tried
        low, high = (middle, high) if len(tried[0]) < target_triangles else (low, middle)
    return best


def simplify(
    positions: np.ndarray,
    faces: np.ndarray,
    target_triangles: int,
    uvs: np.ndarray | None = None,
    lock_border: bool = False,
) -> Simplified:
    """Simplify one mesh part to about `target_triangles` triangles, keeping a subset of its vertices.

    positions: (V, 3) float, one frame (metres); faces: (T, 3) int; uvs: (V, 2) float or None.
    lock_border: keep every open-border vertex (garment hems). When the locked border leaves too few
    collapsible edges to get within TARGET_TOLERANCE of the target, the simplification is redone with the
    border free to collapse along itself (meshoptimizer never moves a border vertex off the border) and a
    warning says so.
    """
    import meshoptimizer

    positions, faces = _check_mesh(positions, faces)
    if uvs is not None:
        uvs = np.asarray(uvs, dtype=np.float32)
        if uvs.shape != (len(positions), 2):
            raise ValueError(f"uvs must be ({len(positions)}, 2), got {uvs.shape}")
    target_triangles = int(target_triangles)
    if target_triangles < 1:
        raise ValueError(f"simplify: target_triangles must be at least 1, got {target_triangles}")
    if target_triangles >= len(faces):
        kept = np.unique(faces).astype(np.int64)
        remap = np.full(len(positions), -1, dtype=np.int64)
        remap[kept] = np.arange(len(kept))
        return Simplified(remap[faces].astype(np.uint32), kept, target_triangles, 0.0, lock_border)

    options = meshoptimizer.SIMPLIFY_LOCK_BORDER if lock_border else 0
    simplified, error = _run_meshoptimizer(positions, faces, uvs, target_triangles, options)
    locked = lock_border
    if lock_border and len(simplified) > target_triangles * (1 + TARGET_TOLERANCE):
        logger.warning(
            "locking the %d border vertices leaves %d triangles for a target of %d; letting the border "
            "collapse along itself",
            int(border_vertex_mask(positions, faces).sum()),
            len(simplified),
            target_triangles,
        )
        simplified, error = _run_meshoptimizer(positions, faces, uvs, target_triangles, 0)
        locked = False
    if len(simplified) > target_triangles * (1 + TARGET_TOLERANCE):
        # Edge collapses cannot get there: a flat-shaded mesh of many small closed parts (a robot of boxes)
        # has every edge on a normal seam, and a box cannot lose a triangle without losing its shape. Vertex
        # clustering can: it keeps a subset of the vertices too, but may tear texture seams, so it is the
        # fallback only, and said.
        sloppy, sloppy_error = _sloppy_near_target(positions, faces, target_triangles)
        logger.warning("edge collapses leave %d triangles for a target of %d (a flat-shaded or many-part mesh); "
                       "clustering vertices instead: %d triangles", len(simplified), target_triangles, len(sloppy))
        if len(sloppy):
            simplified, error, locked = sloppy, sloppy_error, False
    if len(simplified) == 0:
        raise ValueError(f"simplify: nothing left of {len(faces)} triangles for a target of {target_triangles}")
    kept = np.unique(simplified).astype(np.int64)
    remap = np.full(len(positions), -1, dtype=np.int64)
    remap[kept] = np.arange(len(kept))
    return Simplified(remap[simplified].astype(np.uint32), kept, target_triangles, error, locked)
