"""Upload checks (crowdbake.ingest.uploads): each bad input is refused with the field, the file and where
in it the problem is; good inputs come back with what was measured."""
from __future__ import annotations

import io
import stat
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from crowdbake.formats.pc2 import read_pc2
from crowdbake.ingest.obj_sequence import ZipLimits, convert_obj_sequence
from crowdbake.ingest.rejections import FORMAT_MISMATCH, INVALID_FILE, UNSAFE_ARCHIVE, UNSUPPORTED_FORMAT, UploadRejected, sniff_format
from crowdbake.ingest.uploads import check_character, check_cloth, check_texture
from service_fixtures import obj_bytes, obj_sequence_zip, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth

LIMITS = ZipLimits(max_entries=100, max_uncompressed_bytes=50 << 20, max_ratio=200.0)


def write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def rejected(call) -> UploadRejected:
    with pytest.raises(UploadRejected) as info:
        call()
    return info.value


@pytest.fixture
def cloth_files(tmp_path):
    points, faces = tiny_cloth(frames=12)
    cache = write(tmp_path, "cloth.pc2", pc2_bytes(points))
    mesh = write(tmp_path, "cloth.obj", obj_bytes(points[0], faces, tmp_path))
    return points, faces, cache, mesh


def test_formats_are_recognised_by_content(tmp_path, cloth_files):
    _, _, cache, mesh = cloth_files
    assert sniff_format(write(tmp_path, "a", tiny_character_glb())) == "glb"
    assert sniff_format(write(tmp_path, "b", png_bytes())) == "png"
    assert sniff_format(cache) == "pc2"
    assert sniff_format(mesh) == "obj"
    assert sniff_format(write(tmp_path, "c", b'{"asset": {"version": "2.0"}}')) == "gltf"
    assert sniff_format(write(tmp_path, "d", b"\x00\x01garbage")) is None


# -------------------------------------------------------------------------------------- character


def test_good_character_reports_its_counts(tmp_path):
    info = check_character(write(tmp_path, "upload", tiny_character_glb()), "walker.glb")
    assert info["format"] == "glb"
    assert (info["vertex_count"], info["triangle_count"], info["joint_count"]) == (4, 4, 1)
    assert info["animation_seconds"] == pytest.approx(0.25)


def test_unknown_extension_is_unsupported(tmp_path):
    error = rejected(lambda: check_character(write(tmp_path, "upload", tiny_character_glb()), "walker.fbx"))
    assert error.kind == UNSUPPORTED_FORMAT
    assert error.errors[0].field == "file" and "walker.fbx" in error.errors[0].message


def test_png_named_glb_is_a_mismatch(tmp_path):
    error = rejected(lambda: check_character(write(tmp_path, "upload", png_bytes()), "walker.glb"))
    assert error.kind == FORMAT_MISMATCH
    assert error.errors[0].where == "byte 0" and "PNG" in error.errors[0].message


def test_truncated_glb_points_at_the_length_field(tmp_path):
    data = tiny_character_glb()
    error = rejected(lambda: check_character(write(tmp_path, "upload", data[: len(data) // 2]), "walker.glb"))
    assert error.kind == INVALID_FILE
    assert error.errors[0].where == "byte 8"  # the GLB header's length disagrees with the file
    assert "upload" not in error.errors[0].message  # the staging path is replaced by the client's name
    assert "walker.glb" in error.errors[0].message


def test_gltf_with_external_buffer_is_refused(tmp_path):
    document = b'{"asset": {"version": "2.0"}, "buffers": [{"uri": "../../secret.bin", "byteLength": 4}]}'
    error = rejected(lambda: check_character(write(tmp_path, "upload", document), "walker.gltf"))
    assert error.kind == INVALID_FILE and "../../secret.bin" in error.errors[0].message


def test_empty_file_is_invalid(tmp_path):
    error = rejected(lambda: check_character(write(tmp_path, "upload", b""), "walker.glb"))
    assert error.kind == INVALID_FILE and error.errors[0].message == "the file is empty"


# ------------------------------------------------------------------------------------------ cloth


def test_good_cloth_reports_frames_and_vertices(cloth_files):
    points, faces, cache, mesh = cloth_files
    info = check_cloth(cache, "cloth.pc2", mesh, "cloth.obj")
    assert info["frame_count"] == len(points) and info["vertex_count"] == points.shape[1]
    assert info["triangle_count"] == len(faces)


def test_truncated_pc2_names_where_it_ends(tmp_path, cloth_files):
    _, _, cache, mesh = cloth_files
    data = cache.read_bytes()
    short = write(tmp_path, "short.pc2", data[:-5])
    error = rejected(lambda: check_cloth(short, "short.pc2", mesh, "cloth.obj"))
    assert error.kind == INVALID_FILE
    assert error.errors[0].field == "cache" and error.errors[0].file == "short.pc2"
    assert error.errors[0].where == f"byte {len(data) - 5}"
    assert "truncated" in error.errors[0].message


def test_nan_in_pc2_names_its_byte_offset(tmp_path, cloth_files):
    points, faces, _, mesh = cloth_files
    data = bytearray(pc2_bytes(points))
    frame, vertex, axis = 3, 2, 1
    offset = 32 + 4 * ((frame * points.shape[1] + vertex) * 3 + axis)
    data[offset:offset + 4] = struct.pack("<f", float("nan"))
    bad = write(tmp_path, "nan.pc2", bytes(data))
    error = rejected(lambda: check_cloth(bad, "nan.pc2", mesh, "cloth.obj"))
    assert error.errors[0].where == f"byte {offset}"
    assert "NaN" in error.errors[0].message


def test_vertex_counts_must_agree(tmp_path, cloth_files):
    points, faces, _, mesh = cloth_files
    cache = write(tmp_path, "fewer.pc2", pc2_bytes(points[:, :-1]))
    error = rejected(lambda: check_cloth(cache, "fewer.pc2", mesh, "cloth.obj"))
    assert error.kind == INVALID_FILE
    assert f"{points.shape[1] - 1} points" in error.errors[0].message and f"{points.shape[1]} vertex positions" in error.errors[0].message
    assert error.errors[0].where == "byte 16"  # PC2 numPoints


def test_too_few_frames_for_two_cycles(cloth_files):
    points, _, cache, mesh = cloth_files
    error = rejected(lambda: check_cloth(cache, "cloth.pc2", mesh, "cloth.obj", cycle_frames=len(points) // 2 + 1))
    assert "too few frames for two cycles" in error.errors[0].message
    assert error.errors[0].where == "byte 28"  # PC2 numSamples
    check_cloth(cache, "cloth.pc2", mesh, "cloth.obj", cycle_frames=len(points) // 2)  # exactly two cycles: fine


def test_obj_errors_name_the_line(tmp_path, cloth_files):
    _, _, cache, mesh = cloth_files
    lines = mesh.read_text().splitlines()
    lines[2] = "v 1.0 nan 0.0"
    bad = write(tmp_path, "bad.obj", ("\n".join(lines) + "\n").encode())
    error = rejected(lambda: check_cloth(cache, "cloth.pc2", bad, "bad.obj"))
    assert error.errors[0].field == "mesh" and error.errors[0].where == "line 3"


# ------------------------------------------------------------------------------------ OBJ sequences


class Sink:
    def __init__(self):
        self.data = bytearray()

    def write(self, chunk: bytes) -> None:
        self.data += chunk


def convert(tmp_path: Path, data: bytes, limits: ZipLimits = LIMITS):
    cache, mesh = Sink(), Sink()
    info = convert_obj_sequence(write(tmp_path, "seq.zip", data), "seq.zip", limits, cache, mesh)
    return info, bytes(cache.data), bytes(mesh.data)


def test_sequence_becomes_a_pc2_in_frame_order(tmp_path):
    points, faces = tiny_cloth(frames=12)
    info, cache, mesh = convert(tmp_path, obj_sequence_zip(points, faces, tmp_path))
    assert info["frame_count"] == 12 and info["vertex_count"] == points.shape[1]
    decoded = read_pc2(write(tmp_path, "out.pc2", cache)).points
    # frame10 sorts after frame9 (natural order), so the cache is the frames in their true order
    np.testing.assert_allclose(decoded, points, atol=1e-6)
    assert mesh.startswith(b"v ")


def zip_with(entries: dict[str, bytes], symlinks: tuple[str, ...] = ()) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries.items():
            info = zipfile.ZipInfo(name)
            info.compress_type = zipfile.ZIP_DEFLATED
            if name in symlinks:
                info.external_attr = (stat.S_IFLNK | 0o777) << 16
            archive.writestr(info, data)
    return buffer.getvalue()


@pytest.mark.parametrize("name,reason", [
    ("../escape.obj", "'..'"),
    ("frames/../../escape.obj", "'..'"),
    ("/etc/escape.obj", "absolute"),
    ("C:/escape.obj", "absolute"),
    ("frames\\..\\escape.obj", "backslash"),
])
def test_entries_escaping_the_folder_are_refused(tmp_path, name, reason):
    error = rejected(lambda: convert(tmp_path, zip_with({"frames/frame0.obj": b"v 0 0 0\n", name: b"v 0 0 0\n"})))
    assert error.kind == UNSAFE_ARCHIVE
    assert error.errors[0].where == f"entry {name}" and reason in error.errors[0].message


def test_symlink_entries_are_refused(tmp_path):
    error = rejected(lambda: convert(tmp_path, zip_with({"frames/link.obj": b"/etc/passwd"}, symlinks=("frames/link.obj",))))
    assert error.kind == UNSAFE_ARCHIVE and "symbolic link" in error.errors[0].message


def test_zip_bomb_by_ratio_is_refused(tmp_path):
    bomb = zip_with({"frames/frame0.obj": b"\n" * (8 << 20)})  # 8 MiB of newlines deflate ~1000:1
    error = rejected(lambda: convert(tmp_path, bomb))
    assert error.kind == UNSAFE_ARCHIVE and "compresses" in error.errors[0].message


def test_zip_bomb_by_total_size_is_refused(tmp_path):
    limits = ZipLimits(max_entries=100, max_uncompressed_bytes=1000, max_ratio=200.0)
    points, faces = tiny_cloth(frames=12)
    error = rejected(lambda: convert(tmp_path, obj_sequence_zip(points, faces, tmp_path), limits))
    assert error.kind == UNSAFE_ARCHIVE and "expand to" in error.errors[0].message


def test_too_many_entries_are_refused(tmp_path):
    limits = ZipLimits(max_entries=5, max_uncompressed_bytes=50 << 20, max_ratio=200.0)
    points, faces = tiny_cloth(frames=12)
    error = rejected(lambda: convert(tmp_path, obj_sequence_zip(points, faces, tmp_path), limits))
    assert error.kind == UNSAFE_ARCHIVE and "12 entries" in error.errors[0].message


def test_topology_must_stay_constant(tmp_path):
    points, faces = tiny_cloth(frames=12)
    data = obj_sequence_zip(points, faces, tmp_path)
    entries = {}
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        for name in archive.namelist():
            entries[name] = archive.read(name)
    entries["frames/frame7.obj"] = obj_bytes(points[7], faces[:-1], tmp_path)  # one triangle fewer
    error = rejected(lambda: convert(tmp_path, zip_with(entries)))
    assert error.kind == INVALID_FILE
    assert error.errors[0].file == "frames/frame7.obj" and "topology changes" in error.errors[0].message


def test_sequence_needs_two_cycles_of_frames(tmp_path):
    points, faces = tiny_cloth(frames=3)
    error = rejected(lambda: convert(tmp_path, obj_sequence_zip(points, faces, tmp_path)))
    assert "too few frames for two cycles" in error.errors[0].message


def test_not_a_zip_is_a_mismatch_or_invalid(tmp_path):
    error = rejected(lambda: convert(tmp_path, b"PK\x03\x04" + b"\0" * 40))
    assert error.kind == INVALID_FILE and "zip" in error.errors[0].message


# --------------------------------------------------------------------------------------- textures


def test_good_png(tmp_path):
    assert check_texture(write(tmp_path, "t", png_bytes(16, 8)), "diffuse_0.png", max_pixels=1 << 20) == {"width": 16, "height": 8, "mode": "RGBA"}


def test_truncated_png(tmp_path):
    data = png_bytes(64, 64)
    error = rejected(lambda: check_texture(write(tmp_path, "t", data[: len(data) - 20]), "diffuse_0.png", max_pixels=1 << 20))
    assert error.kind == INVALID_FILE and error.errors[0].file == "diffuse_0.png"


def test_png_too_many_pixels_is_refused_before_decoding(tmp_path):
    error = rejected(lambda: check_texture(write(tmp_path, "t", png_bytes(64, 64)), "diffuse_0.png", max_pixels=1000))
    assert error.kind == INVALID_FILE and "64x64" in error.errors[0].message and error.errors[0].where == "byte 16"


def test_glb_named_png_is_a_mismatch(tmp_path):
    error = rejected(lambda: check_texture(write(tmp_path, "t", tiny_character_glb()), "diffuse_0.png", max_pixels=1 << 20))
    assert error.kind == FORMAT_MISMATCH
