"""glTF 2.0 characters: the real sample models load right, our writer round-trips, broken files fail clearly."""
from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from crowdbake.bake.skinning import pose_character
from crowdbake.formats.gltf import (
    CHUNK_BIN,
    CHUNK_JSON,
    Character,
    _Document,
    encode_character,
    load_character,
    parse_glb,
    write_character,
)


def _glb(document: dict, binary: bytes | None) -> bytes:
    """Re-pack a GLB from its JSON and BIN chunk (both padded to 4 bytes as the spec asks)."""
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), CHUNK_JSON) + text
    if binary is not None:
        binary = binary + b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), CHUNK_BIN) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def _edited(path, tmp_path, edit) -> Path:
    document, binary = parse_glb(path.read_bytes(), str(path))
    edit(document)
    out = tmp_path / "edited.glb"
    out.write_bytes(_glb(document, binary))
    return out


# ---------------------------------------------------------------------------------------------- real files


def test_cesium_man_loads(shared_asset):
    character = load_character(shared_asset("CesiumMan.glb"))
    assert character.vertex_count == 3273
    assert character.faces.shape == (4672, 3) and character.faces.dtype == np.uint32
    assert character.joint_count == 19
    assert character.animation_duration == pytest.approx(2.0)
    assert character.texture is not None and character.texture.shape == (1024, 1024, 4)
    assert character.texture.dtype == np.uint8 and (character.texture[..., 3] == 255).all()  # a JPEG has no alpha
    np.testing.assert_allclose(character.weights.sum(axis=1), 1.0, atol=1e-6)
    assert character.joints.max() < 19
    assert (character.joint_parents == -1).sum() == 1
    assert character.uvs.min() >= 0.0 and character.uvs.max() <= 1.0
    np.testing.assert_allclose(np.linalg.norm(character.normals, axis=1), 1.0, atol=1e-4)
    # The skeleton hangs under CesiumMan's Z-up -> Y-up root node: that transform must be kept.
    root = int(np.flatnonzero(character.joint_parents == -1)[0])
    np.testing.assert_allclose(character.joint_parent_transforms[root][:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    assert len(character.channels) == 57  # translation, rotation, scale of each of the 19 joints


def test_rigged_figure_loads(shared_asset):
    character = load_character(shared_asset("RiggedFigure.glb"))
    assert character.vertex_count == 370 and character.faces.shape == (256, 3)
    assert character.joint_count == 19
    assert character.animation_duration == pytest.approx(1.25)
    # Untextured, baseColorFactor 0.8 grey (linear): honoured as a flat sRGB tile, not dropped.
    assert len(character.materials) == 1 and character.materials[0].texture is None
    assert character.texture is not None and character.texture.shape[:2] == (8, 8)
    expected = round((1.055 * 0.8 ** (1 / 2.4) - 0.055) * 255)
    np.testing.assert_array_equal(character.texture[0, 0], [expected, expected, expected, 255])


def test_writer_round_trips_cesium_man(shared_asset, tmp_path):
    original = load_character(shared_asset("CesiumMan.glb"))
    write_character(tmp_path / "copy.glb", original)
    copy = load_character(tmp_path / "copy.glb")
    for name in ("positions", "normals", "uvs", "faces", "joints", "weights", "inverse_bind_matrices", "joint_parents"):
        np.testing.assert_array_equal(getattr(copy, name), getattr(original, name), err_msg=name)
    np.testing.assert_allclose(copy.joint_parent_transforms, original.joint_parent_transforms, atol=1e-15)
    assert copy.animation_duration == original.animation_duration
    np.testing.assert_array_equal(copy.texture, original.texture)  # stored as PNG: lossless
    before, _ = pose_character(original, 24.0, 49)
    after, _ = pose_character(copy, 24.0, 49)
    np.testing.assert_allclose(after, before, atol=1e-6)
    assert encode_character(copy) == encode_character(original)  # deterministic bytes


def test_gltf_with_data_uri_and_external_buffer(shared_asset, tmp_path):
    path = shared_asset("RiggedFigure.glb")
    document, binary = parse_glb(path.read_bytes(), str(path))
    reference = load_character(path)

    embedded = json.loads(json.dumps(document))
    embedded["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    (tmp_path / "embedded.gltf").write_text(json.dumps(embedded))

    external = json.loads(json.dumps(document))
    external["buffers"][0]["uri"] = "figure%20data.bin"  # URIs are percent-encoded
    (tmp_path / "figure data.bin").write_bytes(binary)
    (tmp_path / "external.gltf").write_text(json.dumps(external))

    for name in ("embedded.gltf", "external.gltf"):
        character = load_character(tmp_path / name)
        np.testing.assert_array_equal(character.positions, reference.positions)
        np.testing.assert_array_equal(character.faces, reference.faces)

    external["buffers"][0]["uri"] = "missing.bin"
    (tmp_path / "broken.gltf").write_text(json.dumps(external))
    with pytest.raises(ValueError, match="missing.bin"):
        load_character(tmp_path / "broken.gltf")


def test_mesh_node_transform_is_ignored_but_skeleton_parents_count(shared_asset, tmp_path):
    """glTF: a skinned mesh's own node transform does not apply; the joints' ancestors' transforms do."""
    path = shared_asset("RiggedFigure.glb")
    reference, _ = pose_character(load_character(path), 24.0, 5)

    def move_mesh_node(document):
        mesh_node = next(n for n in document["nodes"] if "skin" in n)
        mesh_node["translation"] = [5.0, 5.0, 5.0]

    moved_mesh, _ = pose_character(load_character(_edited(path, tmp_path, move_mesh_node)), 24.0, 5)
    np.testing.assert_allclose(moved_mesh, reference, atol=1e-6)

    def move_scene_root(document):
        root = document["scenes"][0]["nodes"][0]
        document["nodes"][root]["matrix"][12:15] = [1.0, 2.0, 3.0]  # translation column

    moved_root, _ = pose_character(load_character(_edited(path, tmp_path, move_scene_root)), 24.0, 5)
    np.testing.assert_allclose(moved_root - reference, np.broadcast_to([1.0, 2.0, 3.0], reference.shape), atol=1e-5)


def test_root_transform_survives_write_and_read(shared_asset, tmp_path):
    character = load_character(shared_asset("CesiumMan.glb"))
    write_character(tmp_path / "c.glb", character)
    document, _ = parse_glb((tmp_path / "c.glb").read_bytes(), "c.glb")
    helpers = [node for node in document["nodes"] if "matrix" in node]
    assert len(helpers) == 1  # the Z-up -> Y-up parent of the root joint, written as its own node


# ---------------------------------------------------------------------------------------------- broken files


def test_garbled_containers_fail_with_clear_errors(shared_asset, tmp_path):
    data = shared_asset("RiggedFigure.glb").read_bytes()
    cases = {
        "bad magic": (b"gLTF" + data[4:], "not a GLB file"),
        "version 1": (data[:4] + struct.pack("<I", 1) + data[8:], "version 1"),
        "truncated": (data[:-100], "truncated GLB"),
        "trailing": (data + b"\0\0\0\0", "trailing bytes"),
        "chunk header cut": (data[:8] + struct.pack("<I", len(data) + 4) + data[12:] + b"\0\0\0\0", "chunk header"),
        "chunk lies": (data[:12] + struct.pack("<I", len(data)) + data[16:], "claims"),
        "json garbage": (data[:20] + b"x" + data[21:], "does not parse"),
    }
    for name, (payload, message) in cases.items():
        path = tmp_path / f"{name}.glb"
        path.write_bytes(payload)
        with pytest.raises(ValueError, match=message) as error:
            load_character(path)
        assert str(path) in str(error.value), name


def test_every_truncation_fails_cleanly(shared_asset, tmp_path):
    data = shared_asset("RiggedFigure.glb").read_bytes()
    path = tmp_path / "cut.glb"
    lengths = list(range(0, 64)) + list(range(64, len(data), 509))
    for length in lengths:
        path.write_bytes(data[:length])
        with pytest.raises(ValueError):
            load_character(path)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["accessors"][3].update(count=10**6), r"accessors\[3\]"),
        (lambda d: d["bufferViews"][2].update(byteOffset=10**6), r"bufferViews\[2\].*outside"),
        (lambda d: d["accessors"][0].update(componentType=1234), "unknown componentType"),
        (lambda d: d["skins"][0].update(joints=[0, 0]), "twice"),
        (lambda d: d["nodes"][2].setdefault("children", []).append(2), "two parents|cycle"),
        (lambda d: d["buffers"][0].update(byteLength=10**7), "declares"),
        (lambda d: d["animations"][0]["samplers"][0].update(interpolation="QUADRATIC"), "interpolation"),
        (lambda d: d.pop("skins"), "no skin"),
        (lambda d: d["asset"].update(version="1.0"), "only glTF 2"),
    ],
)
def test_inconsistent_json_is_rejected(shared_asset, tmp_path, edit, message):
    with pytest.raises(ValueError, match=message):
        load_character(_edited(shared_asset("RiggedFigure.glb"), tmp_path, edit))


def test_index_out_of_range_is_rejected(shared_asset, tmp_path):
    path = shared_asset("RiggedFigure.glb")
    document, binary = parse_glb(path.read_bytes(), str(path))
    view = document["bufferViews"][document["accessors"][0]["bufferView"]]
    binary = bytearray(binary)
    struct.pack_into("<H", binary, view["byteOffset"], 60000)  # first index far past 370 vertices
    (tmp_path / "x.glb").write_bytes(_glb(document, bytes(binary)))
    with pytest.raises(ValueError, match="out of range"):
        load_character(tmp_path / "x.glb")


# ---------------------------------------------------------------------------------------------- accessors


def test_accessor_strides_normalisation_and_sparse():
    """A strided normalised uint8 VEC2 accessor with a sparse override, decoded by hand."""
    raw = bytes([0, 255, 9, 9, 128, 0, 9, 9, 255, 51, 9, 9])  # three VEC2 elements, stride 4
    sparse_indices = struct.pack("<H", 2)
    sparse_values = bytes([0, 0])
    buffer = raw + sparse_indices + b"\0\0" + sparse_values + b"\0\0"
    gltf = {
        "asset": {"version": "2.0"},
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 12, "byteStride": 4},
            {"buffer": 0, "byteOffset": 12, "byteLength": 2},
            {"buffer": 0, "byteOffset": 16, "byteLength": 2},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5121, "normalized": True, "count": 3, "type": "VEC2"},
            {
                "bufferView": 0, "componentType": 5121, "normalized": True, "count": 3, "type": "VEC2",
                "sparse": {"count": 1, "indices": {"bufferView": 1, "componentType": 5123}, "values": {"bufferView": 2}},
            },
        ],
    }
    document = _Document(gltf, [buffer], "synthetic", None)
    np.testing.assert_allclose(document.accessor(0), [[0, 1], [128 / 255, 0], [1, 0.2]], atol=1e-6)
    np.testing.assert_allclose(document.accessor(1), [[0, 1], [128 / 255, 0], [0, 0]], atol=1e-6)


def test_character_dataclass_is_what_the_writer_needs():
    """A two-joint character built by hand writes and reads back with its animation."""
    from crowdbake.formats.gltf import AnimationChannel

    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=np.float32)
    character = Character(
        positions=positions,
        normals=np.tile([0, 0, 1], (4, 1)).astype(np.float32),
        uvs=np.zeros((4, 2), np.float32),
        faces=np.array([[0, 1, 2], [1, 3, 2]], np.uint32),
        joints=np.array([[0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0]], np.uint16),
        weights=np.array([[1, 0, 0, 0]] * 4, np.float32),
        joint_names=["root", "tip"],
        joint_parents=np.array([-1, 0]),
        joint_parent_transforms=np.tile(np.eye(4), (2, 1, 1)),
        inverse_bind_matrices=np.stack([np.eye(4), np.linalg.inv(np.array([[1, 0, 0, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1.0]]))]).astype(np.float32),
        rest_translations=np.array([[0, 0, 0], [0, 1, 0]], float),
        rest_rotations=np.array([[0, 0, 0, 1], [0, 0, 0, 1]], float),
        rest_scales=np.ones((2, 3)),
        channels=[AnimationChannel(1, "translation", np.array([0, 1], np.float32), np.array([[0, 1, 0], [0, 2, 0]], np.float32))],
        animation_duration=1.0,
    )
    data = encode_character(character)
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "two.glb"
        path.write_bytes(data)
        loaded = load_character(path)
    posed, _ = pose_character(loaded, 2.0, 3)  # t = 0, 0.5, 1
    np.testing.assert_allclose(posed[:, 2:, 1], [[1, 1], [1.5, 1.5], [2, 2]], atol=1e-6)
    np.testing.assert_allclose(posed[:, :2], np.broadcast_to(positions[:2], (3, 2, 3)), atol=1e-6)
