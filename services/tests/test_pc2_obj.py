"""PC2 point caches and OBJ rest meshes: round trips, seam splitting, and clear errors on bad files."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from crowdbake.formats.obj import read_obj, write_obj
from crowdbake.formats.pc2 import HEADER_SIZE, PC2_MAGIC, encode_pc2, read_pc2, write_pc2


def _points(frames: int = 5, vertices: int = 7) -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.normal(size=(frames, vertices, 3)).astype(np.float32)


# ---------------------------------------------------------------------------------------------- PC2


def test_pc2_round_trip_is_exact(tmp_path):
    points = _points()
    path = tmp_path / "cache.pc2"
    write_pc2(path, points, start_frame=10.0, sample_rate=0.5)
    cache = read_pc2(path)
    assert cache.points.dtype == np.float32 and cache.points.shape == (5, 7, 3)
    np.testing.assert_array_equal(cache.points, points)
    assert (cache.start_frame, cache.sample_rate) == (10.0, 0.5)


def test_pc2_header_layout_matches_the_format():
    """Bytes laid out as 3ds Max / Blender write them: 12-byte magic, int32 version, int32 points,
    float32 start, float32 rate, int32 samples, then float32 xyz per point per sample."""
    points = _points(2, 3)
    data = encode_pc2(points, start_frame=1.0, sample_rate=1.0)
    assert data[:12] == b"POINTCACHE2\0"
    assert struct.unpack_from("<iiffi", data, 12) == (1, 3, 1.0, 1.0, 2)
    assert len(data) == 32 + 2 * 3 * 12
    np.testing.assert_array_equal(np.frombuffer(data, "<f4", offset=32).reshape(2, 3, 3), points)


def _corrupt(tmp_path, data: bytes):
    path = tmp_path / "bad.pc2"
    path.write_bytes(data)
    return path


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: b"POINTCACHE3\0" + d[12:], "magic"),
        (lambda d: d[:12] + struct.pack("<i", 2) + d[16:], "version 2"),
        (lambda d: d[:16] + struct.pack("<i", -4) + d[20:], "numPoints -4"),
        (lambda d: d[:28] + struct.pack("<i", -1) + d[32:], "numSamples -1"),
        (lambda d: d[:16] + struct.pack("<i", 1 << 30) + d[20:], "numPoints"),
        (lambda d: d[:28] + struct.pack("<i", 1 << 20) + d[32:], "truncated"),
        (lambda d: d[:-1], "truncated"),
        (lambda d: d + b"\0\0\0\0", "trailing"),
        (lambda d: d[:24] + struct.pack("<f", 0.0) + d[28:], "sampleRate"),
        (lambda d: d[:20] + struct.pack("<f", float("nan")) + d[24:], "finite"),
        (lambda d: d[:40] + struct.pack("<f", float("inf")) + d[44:], "NaN or infinite"),
        (lambda d: d[:10], "truncated"),
    ],
)
def test_pc2_reader_rejects_bad_files_with_the_file_name(tmp_path, mutate, message):
    path = _corrupt(tmp_path, mutate(encode_pc2(_points())))
    with pytest.raises(ValueError, match=message) as error:
        read_pc2(path)
    assert str(path) in str(error.value)


def test_pc2_every_truncation_fails_cleanly(tmp_path):
    data = encode_pc2(_points(3, 4))
    for length in range(len(data)):
        with pytest.raises(ValueError):
            read_pc2(_corrupt(tmp_path, data[:length]))


def test_pc2_huge_header_is_refused_before_allocating(tmp_path):
    """A header promising 2^24 points x 2^24 samples must fail on the size check, not in numpy."""
    header = PC2_MAGIC + struct.pack("<iiffi", 1, 1 << 24, 0.0, 1.0, 1 << 24)
    with pytest.raises(ValueError, match="truncated"):
        read_pc2(_corrupt(tmp_path, header + b"\0" * 12))
    assert HEADER_SIZE == 32


def test_pc2_writer_validates(tmp_path):
    with pytest.raises(ValueError, match=r"\(F, V, 3\)"):
        write_pc2(tmp_path / "x.pc2", np.zeros((4, 3)))
    bad = _points()
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_pc2(tmp_path / "x.pc2", bad)
    with pytest.raises(ValueError, match="sample_rate"):
        write_pc2(tmp_path / "x.pc2", _points(), sample_rate=0.0)


# ---------------------------------------------------------------------------------------------- OBJ


def _cylinder(rows: int = 3, columns: int = 4):
    """A closed cylinder grid: positions shared across the seam, UVs split there (like the sample garment)."""
    angles = 2 * np.pi * np.arange(columns) / columns
    positions = np.array([[np.cos(a), -r, np.sin(a)] for r in range(rows) for a in angles], dtype=np.float32)
    faces, uv_faces = [], []
    for r in range(rows - 1):
        for c in range(columns):
            n = (c + 1) % columns
            faces += [[r * columns + c, r * columns + n, (r + 1) * columns + c], [r * columns + n, (r + 1) * columns + n, (r + 1) * columns + c]]
            w = columns + 1
            uv_faces += [[r * w + c, r * w + c + 1, (r + 1) * w + c], [r * w + c + 1, (r + 1) * w + c + 1, (r + 1) * w + c]]
    uvs = np.array([[c / columns, r / (rows - 1)] for r in range(rows) for c in range(columns + 1)], dtype=np.float32)
    return positions, np.array(faces), uvs, np.array(uv_faces)


def test_obj_round_trip_without_seams(tmp_path):
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]], dtype=np.float32)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    uvs = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float32)
    write_obj(tmp_path / "quad.obj", positions, faces, uvs)
    mesh = read_obj(tmp_path / "quad.obj")
    np.testing.assert_array_equal(mesh.positions, positions)
    np.testing.assert_array_equal(mesh.faces, faces)
    np.testing.assert_allclose(mesh.uvs, uvs, atol=1e-7)
    np.testing.assert_array_equal(mesh.source_index, np.arange(4))
    assert mesh.faces.dtype == np.uint32 and mesh.positions.dtype == np.float32


def test_obj_flips_v_to_the_gltf_convention(tmp_path):
    """OBJ's v points up; crowdbake's (glTF's) points down. The file holds 1 - v."""
    write_obj(tmp_path / "t.obj", np.eye(3), [[0, 1, 2]], np.array([[0.25, 0.1], [0.5, 0.2], [0.75, 0.9]]))
    text = (tmp_path / "t.obj").read_text()
    assert "vt 0.25 0.9" in text
    mesh = read_obj(tmp_path / "t.obj")
    np.testing.assert_allclose(mesh.uvs[:, 1], [0.1, 0.2, 0.9], atol=1e-7)


def test_obj_seams_split_vertices_and_map_back_to_positions(tmp_path):
    positions, faces, uvs, uv_faces = _cylinder()
    write_obj(tmp_path / "cyl.obj", positions, faces, uvs, uv_faces)
    mesh = read_obj(tmp_path / "cyl.obj")
    assert mesh.position_count == 12
    # One extra vertex per ring: the seam column carries u = 0 and u = 1.
    assert mesh.vertex_count == 12 + 3
    np.testing.assert_array_equal(mesh.source_index[:12], np.arange(12))
    np.testing.assert_array_equal(mesh.positions, positions[mesh.source_index])
    # Faces use the split vertices: every corner's UV is the one the file gave that corner.
    corner_uv = uvs[uv_faces.reshape(-1)]
    np.testing.assert_allclose(mesh.uvs[mesh.faces.reshape(-1).astype(int)], corner_uv, atol=1e-7)
    # And the faces still describe the same surface.
    np.testing.assert_array_equal(mesh.source_index[mesh.faces.astype(int)], faces)
    # A PC2 cache in OBJ position order maps onto the split vertices through source_index.
    cache = np.random.default_rng(0).normal(size=(2, 12, 3))
    per_vertex = cache[:, mesh.source_index]
    assert per_vertex.shape == (2, 15, 3)
    np.testing.assert_array_equal(per_vertex[:, 12:], cache[:, mesh.source_index[12:]])


def test_obj_reads_polygons_negative_indices_and_ignores_the_rest(tmp_path):
    text = """# a quad and a pentagon
mtllib x.mtl
o thing
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vn 0 0 1
s off
usemtl red
f 1//1 2//1 3//1 4//1
v 2 0 0
f -1 2 3
l 1 2
"""
    (tmp_path / "p.obj").write_text(text)
    mesh = read_obj(tmp_path / "p.obj")
    assert mesh.uvs is None
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [4, 1, 2]])


@pytest.mark.parametrize(
    "body, message",
    [
        ("v 0 0 0\nv 1 0 0\nf 1 2 3\n", ":3: position index 3 is out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", ":4: position index 0"),
        ("v 0 0 nan\n", ":1: 'v' has NaN"),
        ("v 0 0\n", ":1: 'v' needs 3"),
        ("v 0 0 x\n", ":1: 'v' has a value that is not a number"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", ":4: a face needs at least 3"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/2 3/1\n", ":5: texture coordinate index 2"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/a 2 3\n", ":4: texture coordinate index 'a'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1/1/1 2 3\n", ":4: malformed face corner"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3\n", "without a texture coordinate"),
        ("# nothing\n", "no vertex positions"),
    ],
)
def test_obj_errors_name_file_and_line(tmp_path, body, message):
    path = tmp_path / "bad.obj"
    path.write_text(body)
    with pytest.raises(ValueError, match=message) as error:
        read_obj(path)
    assert str(path) in str(error.value)


def test_obj_writer_validates(tmp_path):
    with pytest.raises(ValueError, match="face indices"):
        write_obj(tmp_path / "x.obj", np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(ValueError, match="per-position uvs"):
        write_obj(tmp_path / "x.obj", np.zeros((3, 3)), [[0, 1, 2]], np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        write_obj(tmp_path / "x.obj", np.full((3, 3), np.nan), [[0, 1, 2]])
