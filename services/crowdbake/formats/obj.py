"""Wavefront OBJ meshes: the rest mesh that goes with a PC2 cloth cache.

Only geometry is read: `v`, `vt` and `f` (polygons are fan-triangulated;
`v`, `v/vt`, `v//vn` and `v/vt/vn` corners; negative indices count back from
the end as the OBJ spec says). Normals (`vn`) are ignored because crowdbake
recomputes them from the animated positions; groups, objects, smoothing groups
and materials are ignored too.

Texture coordinates: OBJ puts the origin of `vt` at the bottom-left of the
image, glTF at the top-left. crowdbake uses the glTF convention everywhere
(u right, v down, (0, 0) = first texel row), so `read_obj` returns
(u, 1 - v_obj) and `write_obj` writes 1 - v. A body from a .glb and a garment
from an OBJ can therefore share one texture with no special case.

UV seams: an OBJ position may be used with different `vt` in different faces
(the seam of a cylinder, say). Per-vertex arrays need one UV per vertex, so
such positions are split. The first len(OBJ positions) vertices of the result
are the OBJ positions in file order, each with the UV of its first use; the
extra copies made for seams are appended after them. `source_index[k]` is the
OBJ position index of vertex k, so a PC2 cache (which is in OBJ position order)
maps onto the split vertices with ``cache.points[:, mesh.source_index]``.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

# Statements that carry no geometry we use; anything else unknown is logged once.
_IGNORED = frozenset({"vn", "vp", "o", "g", "s", "usemtl", "mtllib", "l", "p", "#"})


@dataclass(frozen=True)
class ObjMesh:
    """positions (V, 3) float32; faces (T, 3) uint32; uvs (V, 2) float32 (glTF convention, v down) or None
    when the file has no `vt`; source_index (V,) int64: OBJ position index of each vertex (identity unless
    UV seams were split); position_count: number of `v` lines in the file (= points of a matching PC2)."""

    positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None
    source_index: np.ndarray
    position_count: int

    @property
    def vertex_count(self) -> int:
        return int(self.positions.shape[0])


def _floats(parts: list[str], minimum: int, maximum: int, where: str) -> list[float]:
    values = parts[1:]
    if not minimum <= len(values) <= maximum:
        raise ValueError(f"{where}: '{parts[0]}' needs {minimum} to {maximum} numbers, got {len(values)}")
    try:
        numbers = [float(value) for value in values]
    except ValueError:
        raise ValueError(f"{where}: '{parts[0]}' has a value that is not a number: {' '.join(values)!r}") from None
    if not all(np.isfinite(numbers)):
        raise ValueError(f"{where}: '{parts[0]}' has NaN or infinity: {' '.join(values)!r}")
    return numbers


def _resolve(index_text: str, count: int, kind: str, where: str) -> int:
    """OBJ index (1-based, or negative = relative to the current end) -> 0-based."""
    try:
        index = int(index_text)
    except ValueError:
        raise ValueError(f"{where}: {kind} index {index_text!r} is not an integer") from None
    resolved = index - 1 if index > 0 else count + index
    if index == 0 or not 0 <= resolved < count:
        raise ValueError(f"{where}: {kind} index {index} is out of range (there are {count} so far)")
    return resolved


def read_obj(path: str | os.PathLike) -> ObjMesh:
    """Read an OBJ file into triangulated per-vertex arrays (see the module docstring for UVs and seams).

    Raises ValueError with the file and line number for malformed lines, indices out of range,
    NaN/infinite numbers, faces with fewer than 3 corners, or a file that mixes faces with and
    without texture coordinates.
    """
    path = Path(path)
    positions: list[list[float]] = []
    texcoords: list[list[float]] = []
    corners: list[tuple[int, int]] = []  # (position index, texcoord index or -1), 3 per triangle
    unknown: set[str] = set()
    with open(path, "r", encoding="utf-8", errors="replace") as handle:
        for line_number, line in enumerate(handle, start=1):
            parts = line.split("#", 1)[0].split()
            if not parts:
                continue
            where = f"{path}:{line_number}"
            keyword = parts[0]
            if keyword == "v":
                # x y z, optionally w or an r g b vertex colour after them: keep xyz.
                positions.append(_floats(parts, 3, 7, where)[:3])
            elif keyword == "vt":
                uv = _floats(parts, 1, 3, where)
                texcoords.append([uv[0], uv[1] if len(uv) > 1 else 0.0])
            elif keyword == "f":
                if len(parts) < 4:
                    raise ValueError(f"{where}: a face needs at least 3 corners, got {len(parts) - 1}")
                polygon = []
                for corner in parts[1:]:
                    fields = corner.split("/")
                    if len(fields) > 3 or fields[0] == "":
                        raise ValueError(f"{where}: malformed face corner {corner!r}")
                    vertex = _resolve(fields[0], len(positions), "position", where)
                    texcoord = -1
                    if len(fields) > 1 and fields[1] != "":
                        texcoord = _resolve(fields[1], len(texcoords), "texture coordinate", where)
                    polygon.append((vertex, texcoord))
                # Fan triangulation: exact for the convex polygons exporters write.
                for k in range(1, len(polygon) - 1):
                    corners.extend((polygon[0], polygon[k], polygon[k + 1]))
            elif keyword not in _IGNORED and keyword not in unknown:
                unknown.add(keyword)
                logger.debug("%s: ignoring OBJ statement %r", where, keyword)

    if not positions:
        raise ValueError(f"{path}: no vertex positions ('v' lines) in the file")
    position_array = np.asarray(positions, dtype=np.float64).astype(np.float32)
    if not np.isfinite(position_array).all():
        raise ValueError(f"{path}: a position overflows float32")
    if not corners:
        return ObjMesh(position_array, np.zeros((0, 3), np.uint32), None, np.arange(len(positions)), len(positions))

    corner_array = np.asarray(corners, dtype=np.int64)
    has_uv = corner_array[:, 1] >= 0
    if not has_uv.any():
        faces = corner_array[:, 0].reshape(-1, 3).astype(np.uint32)
        return ObjMesh(position_array, faces, None, np.arange(len(positions)), len(positions))
    if not has_uv.all():
        triangle = int(np.argmin(has_uv)) // 3
        raise ValueError(f"{path}: triangle {triangle} has a corner without a texture coordinate while others have them")

    # Split positions used with more than one vt. Vertex k < len(positions) keeps OBJ order.
    position_count = len(positions)
    texcoord_array = np.asarray(texcoords, dtype=np.float64)
    first_texcoord = np.full(position_count, -1, dtype=np.int64)
    extra: dict[tuple[int, int], int] = {}
    extra_sources: list[int] = []
    extra_texcoords: list[int] = []
    vertex_of_corner = np.empty(len(corner_array), dtype=np.int64)
    for k, (vertex, texcoord) in enumerate(corner_array.tolist()):
        if first_texcoord[vertex] < 0:
            first_texcoord[vertex] = texcoord
        if first_texcoord[vertex] == texcoord:
            vertex_of_corner[k] = vertex
            continue
        key = (vertex, texcoord)
        split = extra.get(key)
        if split is None:
            split = position_count + len(extra_sources)
            extra[key] = split
            extra_sources.append(vertex)
            extra_texcoords.append(texcoord)
        vertex_of_corner[k] = split

    source_index = np.concatenate([np.arange(position_count), np.asarray(extra_sources, dtype=np.int64)])
    vertex_texcoords = np.concatenate([first_texcoord, np.asarray(extra_texcoords, dtype=np.int64)])
    uvs = np.zeros((len(source_index), 2), dtype=np.float64)
    used = vertex_texcoords >= 0  # positions no face uses keep (0, 0)
    uvs[used] = texcoord_array[vertex_texcoords[used]]
    uvs[used, 1] = 1.0 - uvs[used, 1]  # OBJ v up -> glTF v down
    return ObjMesh(
        positions=position_array[source_index],
        faces=vertex_of_corner.reshape(-1, 3).astype(np.uint32),
        uvs=uvs.astype(np.float32),
        source_index=source_index,
        position_count=position_count,
    )


def _format_row(values: np.ndarray) -> str:
    # repr-exact float32 -> shortest decimal that round-trips, so read(write(x)) == x bit for bit.
    return " ".join(np.format_float_positional(v, unique=True, trim="-") for v in values)


def write_obj(
    path: str | os.PathLike,
    positions: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray | None = None,
    uv_faces: np.ndarray | None = None,
    comment: str | None = None,
) -> None:
    """Write a triangle mesh as OBJ.

    positions (V, 3) float; faces (T, 3) int, 0-based; uvs (U, 2) float in the glTF convention (v down;
    written as 1 - v). Without uv_faces, uvs are per position (U == V) and every corner uses the UV of its
    position. With uv_faces (T, 3) int indexing uvs, a position can carry different UVs in different faces
    (a seam), which is how a closed garment keeps one point per position for its PC2 cache.
    """
    positions = np.asarray(positions, dtype=np.float32)
    faces = np.asarray(faces)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must be (V, 3), got {positions.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (T, 3), got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(positions)):
        raise ValueError(f"face indices must lie in 0..{len(positions) - 1}")
    if not np.isfinite(positions).all():
        raise ValueError("positions contain NaN or infinity")
    if uvs is not None:
        uvs = np.asarray(uvs, dtype=np.float32)
        if uvs.ndim != 2 or uvs.shape[1] != 2 or not np.isfinite(uvs).all():
            raise ValueError(f"uvs must be finite (U, 2), got {uvs.shape}")
        if uv_faces is None:
            if len(uvs) != len(positions):
                raise ValueError(f"per-position uvs must be ({len(positions)}, 2), got {uvs.shape}; or pass uv_faces")
            uv_faces = faces
        uv_faces = np.asarray(uv_faces)
        if uv_faces.shape != faces.shape or (uv_faces.size and (uv_faces.min() < 0 or uv_faces.max() >= len(uvs))):
            raise ValueError(f"uv_faces must be {faces.shape} with indices into the {len(uvs)} uvs")
    elif uv_faces is not None:
        raise ValueError("uv_faces given without uvs")

    lines = [f"# {line}" for line in (comment or "").splitlines()]
    lines += [f"v {_format_row(p)}" for p in positions]
    if uvs is not None:
        flipped = uvs.copy()
        flipped[:, 1] = np.float32(1.0) - flipped[:, 1]
        lines += [f"vt {_format_row(t)}" for t in flipped]
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip((faces + 1).tolist(), (uv_faces + 1).tolist())]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in (faces + 1).tolist()]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
