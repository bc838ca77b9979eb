"""The vectorised OBJ reader against a plain per-line reference on generated meshes (polygons, UV
seams, negative indices, comments, CRLF and lone-CR line breaks, extra numbers), and its limits.

The reference is the straightforward reader the vectorised one replaced: one Python list per line.
Both must give the same arrays bit for bit.
"""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.formats import obj as obj_module
from crowdbake.formats.obj import MAX_TRIANGLES_PER_POSITION, read_obj


def reference_read_obj(text: str):
    """(positions (P, 3) float32, corners [(position, texcoord or -1)] fan-triangulated, texcoords)."""
    positions, texcoords, corners = [], [], []
    for line in text.splitlines():
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            positions.append([float(x) for x in parts[1:4]])
        elif parts[0] == "vt":
            uv = [float(x) for x in parts[1:3]]
            texcoords.append([uv[0], uv[1] if len(uv) > 1 else 0.0])
        elif parts[0] == "f":
            polygon = []
            for corner in parts[1:]:
                fields = corner.split("/")
                index = int(fields[0])
                vertex = index - 1 if index > 0 else len(positions) + index
                texcoord = -1
                if len(fields) > 1 and fields[1]:
                    t = int(fields[1])
                    texcoord = t - 1 if t > 0 else len(texcoords) + t
                polygon.append((vertex, texcoord))
            for k in range(1, len(polygon) - 1):
                corners.extend((polygon[0], polygon[k], polygon[k + 1]))
    return np.asarray(positions, np.float32), corners, np.asarray(texcoords, np.float64)


def reference_split(corners, position_count):
    """The seam split as a loop: position k keeps its first texcoord; other pairs append, in order."""
    first = [-1] * position_count
    extra: dict[tuple[int, int], int] = {}
    sources, vertex_of_corner = [], []
    for vertex, texcoord in corners:
        if first[vertex] < 0:
            first[vertex] = texcoord
        if first[vertex] == texcoord:
            vertex_of_corner.append(vertex)
            continue
        if (vertex, texcoord) not in extra:
            extra[(vertex, texcoord)] = position_count + len(sources)
            sources.append(vertex)
        vertex_of_corner.append(extra[(vertex, texcoord)])
    return np.r_[np.arange(position_count), np.asarray(sources, np.int64)], np.asarray(vertex_of_corner)


def generated_obj(rng: np.random.Generator, uv: bool) -> str:
    lines = ["# generated", ""]
    positions = texcoords = 0
    for _ in range(int(rng.integers(20, 60))):
        what = rng.random()
        if what < 0.4 or positions < 3:
            extra = " 1" if rng.random() < 0.2 else ""
            lines.append(f"v {rng.normal():.6g} {rng.normal():.6g} {rng.normal():.6g}{extra}" + ("  # a comment" if rng.random() < 0.1 else ""))
            positions += 1
        elif what < 0.6 and uv:
            lines.append(f"vt {rng.random():.5g}" + (f" {rng.random():.5g}" if rng.random() < 0.9 else ""))
            texcoords += 1
        elif uv and texcoords == 0:
            continue
        else:
            corners = []
            for _ in range(int(rng.integers(3, 7))):
                p = int(rng.integers(1, positions + 1))
                p_text = str(p) if rng.random() < 0.7 else str(p - positions - 1)  # negative: from the end
                if uv:
                    t = int(rng.integers(1, texcoords + 1))
                    corners.append(f"{p_text}/{t}" + ("/1" if rng.random() < 0.3 else ""))
                else:
                    corners.append(p_text + ("//1" if rng.random() < 0.3 else ""))
            lines.append("f\t" + " ".join(corners))
        if rng.random() < 0.05:
            lines.append("g group  ")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r"])
def test_vectorised_reader_matches_the_per_line_reference(tmp_path, seed, newline):
    rng = np.random.default_rng(seed)
    uv = seed % 2 == 0
    text = generated_obj(rng, uv)
    path = tmp_path / "mesh.obj"
    path.write_bytes(text.replace("\n", newline).encode())
    mesh = read_obj(path)
    positions, corners, texcoords = reference_read_obj(text)
    assert mesh.position_count == len(positions)
    if not corners:
        assert len(mesh.faces) == 0
        return
    if uv:
        source_index, vertex_of_corner = reference_split(corners, len(positions))
        np.testing.assert_array_equal(mesh.source_index, source_index)
        np.testing.assert_array_equal(mesh.faces.ravel(), vertex_of_corner)
        texcoord_of_corner = np.asarray([t for _, t in corners])
        np.testing.assert_array_equal(mesh.uvs[vertex_of_corner, 0], texcoords[texcoord_of_corner, 0].astype(np.float32))
    else:
        np.testing.assert_array_equal(mesh.faces.ravel(), [v for v, _ in corners])
    np.testing.assert_array_equal(mesh.positions, positions[mesh.source_index])


def test_lines_split_across_chunks_give_the_same_mesh(tmp_path, monkeypatch):
    text = generated_obj(np.random.default_rng(99), uv=True)
    path = tmp_path / "mesh.obj"
    path.write_text(text)
    whole = read_obj(path)
    monkeypatch.setattr(obj_module, "_CHUNK_BYTES", 7)  # every few lines a new chunk
    pieces = read_obj(path)
    for name in ("positions", "faces", "uvs", "source_index"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(pieces, name))


def test_errors_in_a_later_chunk_name_the_right_line(tmp_path, monkeypatch):
    monkeypatch.setattr(obj_module, "_CHUNK_BYTES", 16)
    path = tmp_path / "bad.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 3\nf 1 2 9\n")
    with pytest.raises(ValueError, match=r":6: position index 9 is out of range \(there are 3 so far\)"):
        read_obj(path)


def test_faces_repeated_over_few_positions_are_refused(tmp_path):
    path = tmp_path / "cloth.obj"
    faces = MAX_TRIANGLES_PER_POSITION * 3 + 1
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n" + "f 1 2 3\n" * faces)
    with pytest.raises(ValueError, match=f"{faces} triangles over 3 vertex positions"):
        read_obj(path)


def test_a_line_longer_than_the_limit_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(obj_module, "MAX_LINE_BYTES", 64)
    monkeypatch.setattr(obj_module, "_CHUNK_BYTES", 16)
    path = tmp_path / "long.obj"
    path.write_text("v 0 0 0\n" + "#" * 200 + "\n")
    with pytest.raises(ValueError, match="longer than 64 bytes"):
        read_obj(path)
