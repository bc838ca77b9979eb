"""Cloth caches as studios export them (PC2, MDD, OBJ sequences, Alembic) read into one ClothCache;
placement checks for Z-up and centimetre caches; JPEG and PNG texture variations."""
from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from crowdbake.bake.placement import check_placement, to_y_up_metres
from crowdbake.formats.cloth_cache import mesh_from_polygons, read_cloth_cache, write_pc2_obj
from crowdbake.formats.mdd import encode_mdd, read_mdd, write_mdd
from crowdbake.formats.obj import write_obj
from crowdbake.formats.pc2 import write_pc2


def _grid_cloth(frames: int = 6, rows: int = 4, cols: int = 5):
    """A hanging sheet (rows x cols points, quads) that sways: points (F, P, 3), quads (N, 4)."""
    u, v = np.meshgrid(np.linspace(-0.2, 0.2, cols), np.linspace(0.5, 1.0, rows))
    rest = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    sway = np.sin(np.arange(frames) / 3.0)[:, None] * (1.0 - rest[None, :, 1]) * 0.1
    points = np.repeat(rest[None], frames, axis=0)
    points[..., 2] += sway
    quads = [[r * cols + c, r * cols + c + 1, (r + 1) * cols + c + 1, (r + 1) * cols + c] for r in range(rows - 1) for c in range(cols - 1)]
    return points.astype(np.float32), np.asarray(quads)


def _triangles(quads: np.ndarray) -> np.ndarray:
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


# ---------------------------------------------------------------------------------------------- MDD


def test_mdd_round_trips_with_its_frame_rate(tmp_path):
    points, quads = _grid_cloth()
    write_mdd(tmp_path / "c.mdd", points, fps=30.0, start_time=1 / 30)
    cache = read_mdd(tmp_path / "c.mdd")
    np.testing.assert_array_equal(cache.points, points)
    assert cache.fps == pytest.approx(30.0, rel=1e-5)

    write_obj(tmp_path / "c.obj", points[0], _triangles(quads))
    cloth = read_cloth_cache(tmp_path / "c.mdd", tmp_path / "c.obj")
    assert cloth.source == "mdd" and cloth.fps == pytest.approx(30.0, rel=1e-5)
    np.testing.assert_array_equal(cloth.frames, points)
    assert cloth.fps_or(24.0) == pytest.approx(30.0, rel=1e-5)


def test_mdd_is_big_endian_and_checked_before_allocating(tmp_path):
    points, _ = _grid_cloth(frames=2)
    data = encode_mdd(points, fps=24.0)
    assert data[:8] == (2).to_bytes(4, "big") + (20).to_bytes(4, "big")
    cases = {
        "truncated": (data[:-1], "truncated MDD"),
        "trailing": (data + b"\0", "trailing bytes"),
        "lying count": ((10**6).to_bytes(4, "big") + data[4:], "truncated MDD"),
        "negative": ((-1).to_bytes(4, "big", signed=True) + data[4:], "frameCount -1"),
        "header cut": (data[:5], "header alone"),
    }
    for name, (payload, message) in cases.items():
        (tmp_path / f"{name}.mdd").write_bytes(payload)
        with pytest.raises(ValueError, match=message):
            read_mdd(tmp_path / f"{name}.mdd")


# ---------------------------------------------------------------------------------------------- PC2, zip, dispatcher


def test_pc2_has_no_frame_rate_but_keeps_its_sample_spacing(tmp_path):
    points, quads = _grid_cloth()
    write_pc2(tmp_path / "c.pc2", points, sample_rate=2.0)
    write_obj(tmp_path / "c.obj", points[0], _triangles(quads))
    cloth = read_cloth_cache(tmp_path / "c.pc2", tmp_path / "c.obj")
    assert cloth.fps is None and cloth.frame_step == 2.0
    assert cloth.fps_or(24.0) == 12.0  # one sample every two frames of 24 fps
    with pytest.raises(ValueError, match="needs its rest mesh"):
        read_cloth_cache(tmp_path / "c.pc2")
    write_obj(tmp_path / "small.obj", points[0][:4], np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="20 points per frame, but small.obj has 4"):
        read_cloth_cache(tmp_path / "c.pc2", tmp_path / "small.obj")
    with pytest.raises(ValueError, match="unknown cloth cache type '.fbx'"):
        read_cloth_cache(tmp_path / "c.fbx")


def test_obj_sequence_zip_reads_in_natural_order(tmp_path):
    points, quads = _grid_cloth(frames=12)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for k in reversed(range(len(points))):  # stored out of order; frame10 must follow frame9
            write_obj(tmp_path / "f.obj", points[k], _triangles(quads))
            archive.write(tmp_path / "f.obj", f"cloth/frame{k}.obj")
    (tmp_path / "seq.zip").write_bytes(buffer.getvalue())
    cloth = read_cloth_cache(tmp_path / "seq.zip")
    assert cloth.source == "obj-sequence" and cloth.frame_count == 12
    np.testing.assert_allclose(cloth.frames, points, atol=1e-6)


def test_mesh_from_polygons_splits_uv_seams_like_the_obj_reader(tmp_path):
    """A strip of two quads whose middle edge has two UVs: the same split as read_obj gives."""
    points = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0]], np.float32)
    sizes = np.array([4, 4])
    corners = np.array([0, 1, 4, 3, 1, 2, 5, 4])
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0, 0], [1, 0], [1, 1], [0, 1]], np.float32)  # v up
    mesh = mesh_from_polygons(points, sizes, corners, uvs)
    assert mesh.position_count == 6 and mesh.vertex_count == 8  # points 1 and 4 split at the seam
    np.testing.assert_array_equal(mesh.source_index[6:], [1, 4])
    assert len(mesh.faces) == 4
    np.testing.assert_allclose(mesh.uvs[mesh.faces[0]], [[0, 1], [1, 1], [1, 0]])  # glTF: v down

    from crowdbake.formats.obj import read_obj

    lines = [f"v {x} {y} {z}" for x, y, z in points] + [f"vt {u} {v}" for u, v in uvs]
    lines += ["f 1/1 2/2 5/3 4/4", "f 2/5 3/6 6/7 5/8"]
    (tmp_path / "strip.obj").write_text("\n".join(lines) + "\n")
    reference = read_obj(tmp_path / "strip.obj")
    np.testing.assert_array_equal(mesh.source_index, reference.source_index)
    np.testing.assert_allclose(mesh.uvs, reference.uvs)
    np.testing.assert_array_equal(mesh.faces, reference.faces)


def test_any_cache_converts_to_the_pc2_obj_pair_the_bake_reads(tmp_path):
    points, quads = _grid_cloth()
    write_mdd(tmp_path / "c.mdd", points, fps=25.0)
    write_obj(tmp_path / "c.obj", points[0], _triangles(quads))
    cloth = read_cloth_cache(tmp_path / "c.mdd", tmp_path / "c.obj")
    write_pc2_obj(cloth, tmp_path / "out.pc2", tmp_path / "out.obj")
    again = read_cloth_cache(tmp_path / "out.pc2", tmp_path / "out.obj")
    np.testing.assert_array_equal(again.frames, cloth.frames)
    np.testing.assert_array_equal(again.faces, cloth.faces)


# ---------------------------------------------------------------------------------------------- Alembic


def test_alembic_without_bpy_names_the_extra(tmp_path, monkeypatch, shared_asset):
    from crowdbake.formats.alembic import read_alembic

    monkeypatch.setenv("CROWDBAKE_BPY_PYTHON", str(tmp_path / "no-python-here"))
    with pytest.raises(ValueError, match=r"crowdbake\[alembic\]"):
        read_alembic(shared_asset("long_skirt/long_skirt.abc"))


def test_non_ogawa_file_is_refused(tmp_path):
    from crowdbake.formats.alembic import read_time_samplings

    (tmp_path / "x.abc").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 64)
    with pytest.raises(ValueError, match="HDF5 Alembic"):
        read_time_samplings(tmp_path / "x.abc")


def test_shared_alembic_time_sampling_is_24_fps(shared_asset):
    from crowdbake.formats.alembic import animated_sampling, read_time_samplings

    path = shared_asset("long_skirt/long_skirt.abc")
    sampling = animated_sampling(read_time_samplings(path), str(path))
    assert sampling.max_samples == 385
    assert sampling.fps == pytest.approx(24.0)


def test_alembic_long_skirt_matches_its_pc2(shared_asset):
    """The same simulation exported as Alembic (parented, Y-up) and as PC2 + OBJ reads to the same points."""
    from crowdbake.formats.alembic import alembic_available

    if not alembic_available():
        pytest.skip("the crowdbake[alembic] extra (bpy) is not installed")
    alembic = read_cloth_cache(shared_asset("long_skirt/long_skirt.abc"))
    pc2 = read_cloth_cache(shared_asset("long_skirt/long_skirt.pc2"), shared_asset("long_skirt/long_skirt.obj"))
    assert alembic.source == "alembic" and alembic.fps == pytest.approx(24.0)
    assert alembic.frames.shape == pc2.frames.shape == (385, 4032, 3)
    gap = np.abs(alembic.frames - pc2.frames).max(axis=(1, 2))
    assert gap.max() < 1e-4, f"largest gap {gap.max():.2e} m at frame {int(gap.argmax())}"
    # Same triangles in point indices (each a set of three points; the split of seams may differ).
    as_points = lambda cache: {tuple(sorted(t)) for t in cache.mesh.source_index[cache.faces.astype(np.int64)].tolist()}
    assert as_points(alembic) == as_points(pc2)
    assert alembic.uvs is not None


# ---------------------------------------------------------------------------------------------- placement


def _body_box(height: float = 1.8, seed: int = 0) -> np.ndarray:
    """Points of a standing figure's box: 0.5 m wide, 0.3 m deep, `height` tall, feet at y = 0."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.25, 0.0, -0.15], [0.25, height, 0.15], size=(500, 3))


def _skirt(points: int = 400, seed: int = 1) -> np.ndarray:
    """A flared skirt around the hips, Y-up metres: radius 0.2 at the waist (1.0 m) to 0.45 at the hem (0.3 m)."""
    rng = np.random.default_rng(seed)
    height = rng.uniform(0.3, 1.0, points)
    radius = 0.2 + (1.0 - height) / 0.7 * 0.25
    angle = rng.uniform(0, 2 * np.pi, points)
    return np.stack([radius * np.cos(angle), height, radius * np.sin(angle)], axis=1)


def test_a_skirt_in_place_is_accepted():
    placement = check_placement(_skirt(), _body_box())
    assert placement.ok and placement.message == ""
    np.testing.assert_allclose(placement.apply(_skirt()), _skirt(), atol=1e-6)


def test_z_up_cache_is_named_and_converted_when_told():
    skirt = _skirt()
    z_up = np.stack([skirt[:, 0], -skirt[:, 2], skirt[:, 1]], axis=1)  # what a Z-up exporter writes
    refused = check_placement(z_up, _body_box())
    assert not refused.ok and refused.suggested_up == "z"
    assert "Z-up" in refused.message and "--up z" in refused.message and "--units" not in refused.message
    told = check_placement(z_up, _body_box(), up="z")
    assert told.ok
    np.testing.assert_allclose(told.apply(z_up), skirt, atol=1e-6)


@pytest.mark.parametrize("units, scale", [("cm", 100.0), ("mm", 1000.0)])
def test_centimetre_and_millimetre_caches_are_named_and_converted(units, scale):
    refused = check_placement(_skirt() * scale, _body_box())
    assert not refused.ok and refused.suggested_units == units and f"--units {units}" in refused.message
    told = check_placement(_skirt() * scale, _body_box(), units=units)
    assert told.ok
    np.testing.assert_allclose(told.apply(_skirt() * scale), _skirt(), atol=1e-5)


def test_z_up_centimetres_names_both_flags():
    skirt = _skirt() * 100
    z_up = np.stack([skirt[:, 0], -skirt[:, 2], skirt[:, 1]], axis=1)
    refused = check_placement(z_up, _body_box())
    assert "--up z --units cm" in refused.message


def test_a_garment_beside_or_dwarfing_the_body_is_never_accepted():
    beside = check_placement(_skirt() + [0.8, 0, 0], _body_box())
    assert not beside.ok and "beside" in beside.message and "--up" not in beside.message
    huge = check_placement(_skirt() * 7, _body_box())  # no unit makes 7x fit
    assert not huge.ok and "times the character's size" in huge.message
    told_wrong = check_placement(_skirt() * 100, _body_box(), units="m")  # the user insists on metres
    assert not told_wrong.ok and "no up axis or unit fixes it" in told_wrong.message


def test_to_y_up_metres_rejects_unknown_frames():
    with pytest.raises(ValueError, match="up must be"):
        to_y_up_metres(np.zeros((1, 3)), up="x")
    with pytest.raises(ValueError, match="units must be"):
        to_y_up_metres(np.zeros((1, 3)), units="ft")


def test_shared_long_skirt_sits_on_cesium_man_and_its_rotations_are_caught(shared_asset):
    from crowdbake.bake.skinning import pose_character
    from crowdbake.formats.gltf import load_character

    cloth = read_cloth_cache(shared_asset("long_skirt/long_skirt.pc2"), shared_asset("long_skirt/long_skirt.obj"))
    body = pose_character(load_character(shared_asset("CesiumMan.glb")), 24.0, 1)[0][0]
    first = cloth.frames[0]
    assert check_placement(first, body).ok
    z_up = np.stack([first[:, 0], -first[:, 2], first[:, 1]], axis=1)
    assert check_placement(z_up, body).suggested_up == "z"
    assert check_placement(first * 100, body).suggested_units == "cm"


# ---------------------------------------------------------------------------------------------- textures


def test_texture_variations_from_png_and_jpeg(tmp_path):
    from PIL import Image

    from crowdbake.formats.images import read_texture_variation

    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[..., :3] = 120
    rgba[..., 3] = 17  # region code 1
    Image.fromarray(rgba, "RGBA").save(tmp_path / "diffuse_0.png")
    Image.fromarray(rgba[..., :3], "RGB").save(tmp_path / "diffuse_1.jpg", quality=95)
    png = read_texture_variation(tmp_path / "diffuse_0.png")
    jpeg = read_texture_variation(tmp_path / "diffuse_1.jpg")
    assert png.has_region_codes and (png.rgba[..., 3] == 17).all()
    assert not jpeg.has_region_codes and (jpeg.rgba[..., 3] == 0).all()  # JPEG: region 0, its own colours
    assert np.abs(jpeg.rgba[..., :3].astype(int) - 120).max() <= 3
    (tmp_path / "x.ktx2").write_bytes(b"\xabKTX 20\xbb\r\n\x1a\n" + b"\0" * 32)
    with pytest.raises(ValueError, match="KTX2"):
        read_texture_variation(tmp_path / "x.ktx2")
