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

# Bounds on what one OBJ may hold, checked while parsing so memory stays proportional to a mesh a
# crowd can use, whatever the file claims. A closed triangle mesh has about 2 triangles per position
# (Euler), so more than MAX_TRIANGLES_PER_POSITION means faces repeated over a few positions (3
# vertices and 4 million faces, say): no garment, only work. Faces can only name positions written
# before them, so the ratio holds at every point of the file and is checked chunk by chunk.
MAX_POSITIONS = 1 << 21
MAX_TRIANGLES = 1 << 22
MAX_TRIANGLES_PER_POSITION = 8
MAX_LINE_BYTES = 1 << 20
# Bytes parsed at once: the vectorised parse holds about ten temporaries of this size.
_CHUNK_BYTES = 1 << 20

_SPACE, _NEWLINE, _CR, _HASH, _SLASH = 32, 10, 13, 35, 47
_V, _VT, _F = 1, 2, 3


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


class _Problem(Exception):
    """A parse error at a line of the current chunk (0-based), turned into ValueError by read_obj."""

    def __init__(self, line: int, message: str):
        super().__init__(message)
        self.line, self.message = line, message


def _chunks(handle, chunk_bytes: int):
    """Yield blocks of whole lines (each ends with a line break) and the count of lines before each."""
    pending = b""
    lines_before = 0
    while True:
        block = handle.read(chunk_bytes)
        data = pending + block
        if not block:
            if data:
                yield data + b"\n", lines_before
            return
        cut = max(data.rfind(b"\n"), data.rfind(b"\r", 0, len(data) - 1))
        if cut < 0:
            if len(data) > MAX_LINE_BYTES:
                raise _Problem(0, f"a line is longer than {MAX_LINE_BYTES} bytes") from None
            pending = data
            continue
        piece, pending = data[: cut + 1], data[cut + 1 :]
        if len(pending) > MAX_LINE_BYTES:
            raise _Problem(0, f"a line is longer than {MAX_LINE_BYTES} bytes")
        yield piece, lines_before
        lines_before += piece.count(b"\n") + piece.count(b"\r") - piece.count(b"\r\n")


def _byte_mask(size: int, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(size,) bool: True inside every [start, end) range (ranges do not overlap)."""
    delta = np.zeros(size + 1, dtype=np.int8)
    delta[starts] += 1
    delta[ends] -= 1
    return np.cumsum(delta[:-1], dtype=np.int32) > 0


def _numbers(arr: np.ndarray, starts: np.ndarray, ends: np.ndarray, dtype) -> np.ndarray | None:
    """The tokens [starts, ends) of `arr` parsed as `dtype` in C (numpy), or None if one does not parse."""
    if len(starts) == 0:
        return np.zeros(0, dtype)
    keep = _byte_mask(len(arr), starts, ends)
    keep[ends] = True  # the whitespace after each token separates it from the next
    text = arr.copy()
    text[ends] = _SPACE
    try:
        values = np.fromstring(text[keep].tobytes(), dtype=dtype, sep=" ")
    except ValueError:
        return None
    return values if len(values) == len(starts) else None


def _token_text(arr: np.ndarray, start: int, end: int) -> str:
    return arr[start:end].tobytes().decode("utf-8", "replace")


def _python_numbers(arr, starts, ends, lines, convert, describe) -> np.ndarray:
    """The slow, exact path for tokens numpy refused: the first that Python refuses too is the error."""
    values = []
    for start, end, line in zip(starts.tolist(), ends.tolist(), lines.tolist()):
        try:
            values.append(convert(_token_text(arr, start, end)))
        except ValueError:
            raise _Problem(line, describe(line, _token_text(arr, start, end))) from None
    return np.asarray(values)


def _parse_chunk(data: bytes, positions_before: int, texcoords_before: int):
    """Parse whole lines of OBJ text with numpy (no Python object per line).

    Returns (positions (P, 3) float64, texcoords (U, 2) float64, corner positions (C,) int64 resolved,
    corner texcoords (C,) int64 resolved or -1, triangle corner indices (T, 3) into this chunk's corners).
    Raises _Problem at the first bad line of the chunk.
    """
    arr = np.frombuffer(data, dtype=np.uint8).copy()
    # Line breaks as Python's text mode reads them: \n, \r\n and a lone \r each end one line.
    cr = np.flatnonzero(arr == _CR)
    if len(cr):
        before_newline = np.zeros(len(cr), dtype=bool)
        inside = cr + 1 < len(arr)
        before_newline[inside] = arr[cr[inside] + 1] == _NEWLINE
        arr[cr[before_newline]] = _SPACE
        arr[cr[~before_newline]] = _NEWLINE
    arr[(arr == 9) | (arr == 11) | (arr == 12)] = _SPACE
    newlines = np.flatnonzero(arr == _NEWLINE)
    line_count = len(newlines)
    # Comments: blank everything from the first '#' of a line to its end.
    hashes = np.flatnonzero(arr == _HASH)
    if len(hashes):
        hash_lines = np.searchsorted(newlines, hashes)
        first = np.r_[True, hash_lines[1:] != hash_lines[:-1]]
        arr[_byte_mask(len(arr), hashes[first], newlines[hash_lines[first]])] = _SPACE

    solid = (arr != _SPACE) & (arr != _NEWLINE)
    edges = np.diff(solid.astype(np.int8), prepend=np.int8(0), append=np.int8(0))
    del solid
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    del edges
    token_line = np.searchsorted(newlines, starts)
    first_token = np.r_[True, token_line[1:] != token_line[:-1]] if len(starts) else np.zeros(0, bool)

    # Each line's keyword: v, vt or f (everything else carries nothing this reader keeps).
    key_start, key_length, key_line = starts[first_token], (ends - starts)[first_token], token_line[first_token]
    byte0 = arr[key_start]
    byte1 = arr[np.minimum(key_start + 1, len(arr) - 1)]
    kind = np.zeros(line_count, dtype=np.int8)
    kind[key_line[(key_length == 1) & (byte0 == ord("v"))]] = _V
    kind[key_line[(key_length == 2) & (byte0 == ord("v")) & (byte1 == ord("t"))]] = _VT
    kind[key_line[(key_length == 1) & (byte0 == ord("f"))]] = _F
    value_kind = np.where(first_token, 0, kind[token_line])
    counts = {k: np.bincount(token_line[value_kind == k], minlength=line_count) for k in (_V, _VT, _F)}

    problems: list[_Problem] = []

    def first_bad(mask: np.ndarray, message) -> None:
        bad = np.flatnonzero(mask)
        if len(bad):
            problems.append(_Problem(int(bad[0]), message(int(bad[0]))))

    def line_values(line: int) -> str:
        chosen = (token_line == line) & ~first_token
        return " ".join(_token_text(arr, a, b) for a, b in zip(starts[chosen].tolist(), ends[chosen].tolist()))

    first_bad((kind == _V) & ((counts[_V] < 3) | (counts[_V] > 7)), lambda line: f"'v' needs 3 to 7 numbers, got {counts[_V][line]}")
    first_bad((kind == _VT) & ((counts[_VT] < 1) | (counts[_VT] > 3)), lambda line: f"'vt' needs 1 to 3 numbers, got {counts[_VT][line]}")
    first_bad((kind == _F) & (counts[_F] < 3), lambda line: f"a face needs at least 3 corners, got {counts[_F][line]}")
    if problems:
        raise min(problems, key=lambda problem: problem.line)

    def floats(k: int, name: str, keep: int) -> np.ndarray:
        chosen = value_kind == k
        token_starts, token_ends, lines = starts[chosen], ends[chosen], token_line[chosen]
        values = _numbers(arr, token_starts, token_ends, np.float64)
        if values is None:
            try:
                values = _python_numbers(arr, token_starts, token_ends, lines, float,
                                         lambda line, _text: f"'{name}' has a value that is not a number: {line_values(line)!r}").astype(np.float64)
            except _Problem as problem:
                problems.append(problem)
                values = np.zeros(len(token_starts))
        finite = np.isfinite(values)
        if not finite.all():
            line = int(lines[np.argmin(finite)])
            problems.append(_Problem(line, f"'{name}' has NaN or infinity: {line_values(line)!r}"))
        # The first `keep` numbers of every line (a 'v' may carry w or a colour; a 'vt' may lack v).
        line_first = np.searchsorted(lines, lines)  # index of each value's line's first value
        rank = np.arange(len(values)) - line_first
        rows = np.cumsum(np.r_[True, lines[1:] != lines[:-1]]) - 1 if len(lines) else np.zeros(0, np.int64)
        table = np.zeros((int(rows[-1]) + 1 if len(rows) else 0, keep), dtype=np.float64)
        table[rows[rank < keep], rank[rank < keep]] = values[rank < keep]
        return table

    positions = floats(_V, "v", 3)
    texcoords = floats(_VT, "vt", 2)

    # Face corners: 'v', 'v/vt', 'v//vn' or 'v/vt/vn'; the field of each byte is the slashes before it.
    chosen = value_kind == _F
    corner_starts, corner_ends, corner_lines = starts[chosen], ends[chosen], token_line[chosen]
    corner_count = len(corner_starts)
    corner_v = np.zeros(0, np.int64)
    corner_t = np.zeros(0, np.int64)
    triangles = np.zeros((0, 3), np.int64)
    if corner_count:
        inside = _byte_mask(len(arr), corner_starts, corner_ends)
        slash = (arr == _SLASH) & inside
        marks = np.zeros(len(arr), dtype=np.int8)
        marks[corner_starts] = 1
        token_of_byte = np.cumsum(marks, dtype=np.int32) - 1
        del marks
        slash_total = np.cumsum(slash, dtype=np.int32)
        before = slash_total[corner_starts] - slash[corner_starts]
        field = slash_total - before[np.maximum(token_of_byte, 0)] - slash
        del slash_total
        slashes = np.bincount(token_of_byte[slash], minlength=corner_count)
        digits = inside & ~slash
        field0 = np.bincount(token_of_byte[digits & (field == 0)], minlength=corner_count)
        field1 = np.bincount(token_of_byte[digits & (field == 1)], minlength=corner_count)
        malformed = (slashes > 2) | (field0 == 0)
        if malformed.any():
            k = int(np.argmax(malformed))
            problems.append(_Problem(int(corner_lines[k]), f"malformed face corner {_token_text(arr, corner_starts[k], corner_ends[k])!r}"))
            raise min(problems, key=lambda problem: problem.line)
        # Field 0 and field 1 of every corner, each as its own run of bytes.
        v_bytes = np.flatnonzero(digits & (field == 0))
        t_bytes = np.flatnonzero(digits & (field == 1))
        del inside, slash, digits, field, token_of_byte

        def runs(byte_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if len(byte_index) == 0:
                return np.zeros(0, np.int64), np.zeros(0, np.int64)
            breaks = np.flatnonzero(np.diff(byte_index) != 1)
            return byte_index[np.r_[0, breaks + 1]], byte_index[np.r_[breaks, len(byte_index) - 1]] + 1

        v_starts, v_ends = runs(v_bytes)
        t_starts, t_ends = runs(t_bytes)
        has_t = field1 > 0
        v_counts_so_far = positions_before + np.cumsum(kind == _V)[corner_lines]
        t_counts_so_far = texcoords_before + np.cumsum(kind == _VT)[corner_lines]

        def indices(run_starts, run_ends, lines, so_far, name) -> np.ndarray:
            values = _numbers(arr, run_starts, run_ends, np.int64)
            if values is None:
                try:
                    values = _python_numbers(arr, run_starts, run_ends, lines, int,
                                             lambda _line, text: f"{name} index {text!r} is not an integer").astype(np.int64)
                except _Problem as problem:
                    problems.append(problem)
                    return np.zeros(len(run_starts), np.int64)
            resolved = np.where(values > 0, values - 1, so_far + values)
            bad = (values == 0) | (resolved < 0) | (resolved >= so_far)
            if bad.any():
                k = int(np.argmax(bad))
                problems.append(_Problem(int(lines[k]), f"{name} index {values[k]} is out of range (there are {so_far[k]} so far)"))
            return resolved

        corner_v = indices(v_starts, v_ends, corner_lines, v_counts_so_far, "position")
        corner_t = np.full(corner_count, -1, dtype=np.int64)
        if has_t.any():
            corner_t[has_t] = indices(t_starts, t_ends, corner_lines[has_t], t_counts_so_far[has_t], "texture coordinate")
        # Fan triangulation (exact for the convex polygons exporters write): (0, k, k + 1) per face.
        face_lines = np.flatnonzero(kind == _F)
        per_face = counts[_F][face_lines]
        first_corner = np.r_[0, np.cumsum(per_face)[:-1]]
        fan = per_face - 2
        face_of_triangle = np.repeat(np.arange(len(per_face)), fan)
        step = np.arange(len(face_of_triangle)) - np.repeat(np.r_[0, np.cumsum(fan)[:-1]], fan) + 1
        base = first_corner[face_of_triangle]
        triangles = np.stack([base, base + step, base + step + 1], axis=1)
    if problems:
        raise min(problems, key=lambda problem: problem.line)
    return positions, texcoords, corner_v, corner_t, triangles


def read_obj(path: str | os.PathLike) -> ObjMesh:
    """Read an OBJ file into triangulated per-vertex arrays (see the module docstring for UVs and seams).

    Parses blocks of whole lines with numpy, so memory follows the mesh, not the text (a 32 MiB file
    costs tens of MB, not a Python object per line). Raises ValueError with the file and line number
    for malformed lines, indices out of range, NaN/infinite numbers, faces with fewer than 3 corners,
    a file that mixes faces with and without texture coordinates, and meshes over MAX_POSITIONS,
    MAX_TRIANGLES or MAX_TRIANGLES_PER_POSITION triangles per position.
    """
    path = Path(path)
    positions: list[np.ndarray] = []
    texcoords: list[np.ndarray] = []
    corner_v: list[np.ndarray] = []
    corner_t: list[np.ndarray] = []
    triangles: list[np.ndarray] = []
    position_count = texcoord_count = corner_total = triangle_count = 0
    lines_before = 0
    try:
        with open(path, "rb") as handle:
            if handle.read(3) != b"\xef\xbb\xbf":  # a UTF-8 byte order mark is no statement
                handle.seek(0)
            for data, lines_before in _chunks(handle, _CHUNK_BYTES):
                chunk = _parse_chunk(data, position_count, texcoord_count)
                positions.append(chunk[0])
                texcoords.append(chunk[1])
                corner_v.append(chunk[2])
                corner_t.append(chunk[3])
                triangles.append(chunk[4] + corner_total)
                position_count += len(chunk[0])
                texcoord_count += len(chunk[1])
                corner_total += len(chunk[2])
                triangle_count += len(chunk[4])
                last_line = lines_before + data.count(b"\n")
                if position_count > MAX_POSITIONS or texcoord_count > MAX_POSITIONS:
                    raise ValueError(f"{path}:{last_line}: more than {MAX_POSITIONS} vertex positions or texture coordinates")
                if triangle_count > MAX_TRIANGLES:
                    raise ValueError(f"{path}:{last_line}: more than {MAX_TRIANGLES} triangles")
                if triangle_count > MAX_TRIANGLES_PER_POSITION * max(position_count, 1):
                    raise ValueError(f"{path}:{last_line}: {triangle_count} triangles over {position_count} vertex positions; "
                                     f"a mesh has at most {MAX_TRIANGLES_PER_POSITION} per position")
    except _Problem as problem:
        raise ValueError(f"{path}:{lines_before + problem.line + 1}: {problem.message}") from None

    if not position_count:
        raise ValueError(f"{path}: no vertex positions ('v' lines) in the file")
    position_array = np.concatenate(positions).astype(np.float32)
    if not np.isfinite(position_array).all():
        raise ValueError(f"{path}: a position overflows float32")
    if not triangle_count:
        return ObjMesh(position_array, np.zeros((0, 3), np.uint32), None, np.arange(position_count), position_count)
    all_v, all_t = np.concatenate(corner_v), np.concatenate(corner_t)
    triangle_corners = np.concatenate(triangles).ravel()
    del corner_v, corner_t, triangles
    corner_position, corner_texcoord = all_v[triangle_corners], all_t[triangle_corners]
    has_uv = corner_texcoord >= 0
    if not has_uv.any():
        return ObjMesh(position_array, corner_position.reshape(-1, 3).astype(np.uint32), None, np.arange(position_count), position_count)
    if not has_uv.all():
        triangle = int(np.argmin(has_uv)) // 3
        raise ValueError(f"{path}: triangle {triangle} has a corner without a texture coordinate while others have them")
    source_index, vertex_of_corner, vertex_texcoords = split_uv_seams(corner_position, corner_texcoord, position_count)
    texcoord_array = np.concatenate(texcoords)
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


def split_uv_seams(corner_position: np.ndarray, corner_texcoord: np.ndarray, position_count: int):
    """Give every (position, texcoord) pair the corners use its own vertex.

    corner_position, corner_texcoord (C,) int64 (texcoords >= 0). Position k keeps vertex k with the
    texcoord of its first corner; every other pair becomes a vertex appended after the positions, in
    the order of its first corner. Returns (source_index (V,) int64: the position of each vertex,
    vertex_of_corner (C,) int64, vertex_texcoords (V,) int64: each vertex's texcoord, -1 if unused).
    """
    width = int(corner_texcoord.max()) + 1
    key = corner_position * width + corner_texcoord
    _, first_corner, pair_of_corner = np.unique(key, return_index=True, return_inverse=True)
    pair_position, pair_texcoord = corner_position[first_corner], corner_texcoord[first_corner]
    # Pairs are sorted by position: each position's earliest pair is its own vertex's.
    group_starts = np.flatnonzero(np.r_[True, pair_position[1:] != pair_position[:-1]])
    earliest = np.minimum.reduceat(first_corner, group_starts)
    primary = first_corner == np.repeat(earliest, np.diff(np.r_[group_starts, len(pair_position)]))
    extras = np.flatnonzero(~primary)
    extras = extras[np.argsort(first_corner[extras], kind="stable")]
    vertex_of_pair = np.empty(len(pair_position), dtype=np.int64)
    vertex_of_pair[primary] = pair_position[primary]
    vertex_of_pair[extras] = position_count + np.arange(len(extras))
    first_texcoord = np.full(position_count, -1, dtype=np.int64)
    first_texcoord[pair_position[primary]] = pair_texcoord[primary]
    source_index = np.concatenate([np.arange(position_count), pair_position[extras]])
    vertex_texcoords = np.concatenate([first_texcoord, pair_texcoord[extras]])
    return source_index, vertex_of_pair[pair_of_corner.ravel()], vertex_texcoords


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
