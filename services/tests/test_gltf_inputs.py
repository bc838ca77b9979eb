"""glTF as studios export it: Draco and meshopt compression, several materials and animations, KTX2,
required extensions, external files, deep hierarchies. Each file is made here with pygltflib (and
DracoPy's or meshoptimizer's encoder) from the shared CesiumMan, whose plain load is the reference."""
from __future__ import annotations

import copy
import io
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from crowdbake.bake.skinning import pose_character
from crowdbake.formats.gltf import load_character


def _load(path: Path) -> pygltflib.GLTF2:
    return pygltflib.GLTF2.load(str(path))


def _append_view(gltf: pygltflib.GLTF2, data: bytes, **view) -> int:
    """Append `data` to the GLB's BIN chunk (4-byte aligned) as a new bufferView; returns its index."""
    blob = gltf.binary_blob() or b""
    blob += b"\0" * (-len(blob) % 4)
    gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), **view))
    blob += data
    gltf.set_binary_blob(blob)
    gltf.buffers[0].byteLength = len(blob)
    return len(gltf.bufferViews) - 1


def _save(gltf: pygltflib.GLTF2, path: Path) -> Path:
    """Pack a GLB by hand: pygltflib's save_to_bytes merges every buffer into one, which would drop
    the data-less fallback buffer EXT_meshopt_compression files carry."""
    text = gltf.gltf_to_json(separators=(",", ":"), indent=None).encode()
    text += b" " * (-len(text) % 4)
    blob = gltf.binary_blob() or b""
    blob += b"\0" * (-len(blob) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
    return path


def _accessor_array(gltf: pygltflib.GLTF2, index: int) -> np.ndarray:
    accessor = gltf.accessors[index]
    view = gltf.bufferViews[accessor.bufferView]
    dtype = {5121: "u1", 5123: "<u2", 5125: "<u4", 5126: "<f4"}[accessor.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[accessor.type]
    start = (view.byteOffset or 0) + (accessor.byteOffset or 0)
    return np.frombuffer(gltf.binary_blob(), dtype=dtype, count=accessor.count * width, offset=start).reshape(accessor.count, width)


def _posed(character, frames: int = 12) -> np.ndarray:
    return pose_character(character, 24.0, frames)[0]


# ---------------------------------------------------------------------------------------------- compression


def test_draco_compressed_character_keeps_its_skin(shared_asset, tmp_path):
    """KHR_draco_mesh_compression: the mesh decodes with DracoPy and skins as the plain file does.

    Before, the reader ignored the extension and failed with "3273 vertices have no skin weight"."""
    import DracoPy

    source = shared_asset("CesiumMan.glb")
    reference = load_character(source)
    gltf = _load(source)
    primitive = gltf.meshes[0].primitives[0]
    names = ("POSITION", "NORMAL", "TEXCOORD_0", "JOINTS_0", "WEIGHTS_0")
    arrays = {name: _accessor_array(gltf, getattr(primitive.attributes, name)) for name in names}
    faces = _accessor_array(gltf, primitive.indices).reshape(-1, 3)
    encoded = DracoPy.encode(
        arrays["POSITION"], faces, quantization_bits=16, preserve_order=True,
        normals=arrays["NORMAL"].astype(np.float64), tex_coord=arrays["TEXCOORD_0"].astype(np.float64),
        generic_attributes={10: arrays["JOINTS_0"], 11: arrays["WEIGHTS_0"]},
    )
    decoded = DracoPy.decode(encoded)
    ids = {attribute["attribute_type"]: attribute["unique_id"] for attribute in decoded.attributes}
    unique_ids = {"POSITION": ids[0], "NORMAL": ids[1], "TEXCOORD_0": ids[3], "JOINTS_0": 10, "WEIGHTS_0": 11}
    view = _append_view(gltf, encoded)
    for name in names:  # the accessors keep type and count; their data now lives in the Draco stream
        gltf.accessors[getattr(primitive.attributes, name)].bufferView = None
        gltf.accessors[getattr(primitive.attributes, name)].byteOffset = None
    gltf.accessors[primitive.indices].bufferView = None
    gltf.accessors[primitive.indices].byteOffset = None
    primitive.extensions = {"KHR_draco_mesh_compression": {"bufferView": view, "attributes": unique_ids}}
    gltf.extensionsUsed = ["KHR_draco_mesh_compression"]
    gltf.extensionsRequired = ["KHR_draco_mesh_compression"]
    character = load_character(_save(gltf, tmp_path / "draco.glb"))

    assert character.vertex_count == reference.vertex_count
    np.testing.assert_array_equal(character.faces, reference.faces)
    np.testing.assert_array_equal(character.joints, reference.joints)
    np.testing.assert_allclose(character.weights, reference.weights, atol=1e-6)
    extent = np.ptp(reference.positions, axis=0).max()
    np.testing.assert_allclose(character.positions, reference.positions, atol=extent / 2**15)  # 16-bit quantisation
    np.testing.assert_allclose(_posed(character), _posed(reference), atol=1e-3)


def _meshopt_view(gltf: pygltflib.GLTF2, count: int, stride: int, mode: str, encoded: bytes, filter_name: str = "NONE") -> int:
    """A new bufferView whose bytes are meshopt-compressed in buffer 0; its own buffer (1) is the
    data-less fallback, as gltfpack writes it. Returns the view's index."""
    blob = gltf.binary_blob()
    blob += b"\0" * (-len(blob) % 4)
    extension = {"buffer": 0, "byteOffset": len(blob), "byteLength": len(encoded), "byteStride": stride,
                 "count": count, "mode": mode, "filter": filter_name}
    gltf.set_binary_blob(blob + encoded)
    gltf.buffers[0].byteLength = len(blob) + len(encoded)
    gltf.bufferViews.append(pygltflib.BufferView(buffer=1, byteOffset=0, byteLength=count * stride,
                                                 byteStride=stride if mode == "ATTRIBUTES" else None,
                                                 extensions={"EXT_meshopt_compression": extension}))
    return len(gltf.bufferViews) - 1


def _with_fallback_buffer(gltf: pygltflib.GLTF2) -> None:
    gltf.buffers.append(pygltflib.Buffer(byteLength=1 << 24, extensions={"EXT_meshopt_compression": {"fallback": True}}))
    gltf.extensionsUsed = ["EXT_meshopt_compression"]
    gltf.extensionsRequired = ["EXT_meshopt_compression"]


def _compress_attribute(gltf: pygltflib.GLTF2, accessor_index: int, values: np.ndarray, filter_name: str = "NONE") -> None:
    import meshoptimizer

    values = np.ascontiguousarray(values)
    count, stride = len(values), values.dtype.itemsize * values[0].size
    raw = values.view(np.uint8).reshape(count, stride).copy()
    view = _meshopt_view(gltf, count, stride, "ATTRIBUTES", meshoptimizer.encode_vertex_buffer(raw, count, stride), filter_name)
    gltf.accessors[accessor_index].bufferView, gltf.accessors[accessor_index].byteOffset = view, 0


def _rotate_to_smallest(faces: np.ndarray) -> np.ndarray:
    shift = np.argmin(faces, axis=1)
    return np.stack([faces[np.arange(len(faces)), (shift + k) % 3] for k in range(3)], axis=1)


def test_meshopt_compressed_character_is_bit_exact(shared_asset, tmp_path):
    """EXT_meshopt_compression (lossless vertex and index codecs): the load equals the plain file's.

    Before, the reader failed with "buffers[1] has no uri and there is no GLB BIN chunk"."""
    import meshoptimizer

    source = shared_asset("CesiumMan.glb")
    reference = load_character(source)
    gltf = _load(source)
    _with_fallback_buffer(gltf)
    primitive = gltf.meshes[0].primitives[0]
    for name in ("POSITION", "NORMAL", "TEXCOORD_0", "JOINTS_0", "WEIGHTS_0"):
        index = getattr(primitive.attributes, name)
        _compress_attribute(gltf, index, _accessor_array(gltf, index))
    indices = _accessor_array(gltf, primitive.indices)[:, 0]
    view = _meshopt_view(gltf, len(indices), 2, "TRIANGLES", meshoptimizer.encode_index_buffer(indices.astype(np.uint32), len(indices), reference.vertex_count))
    gltf.accessors[primitive.indices].bufferView, gltf.accessors[primitive.indices].byteOffset = view, 0
    character = load_character(_save(gltf, tmp_path / "meshopt.glb"))
    for name in ("positions", "normals", "uvs", "joints", "weights"):
        np.testing.assert_array_equal(getattr(character, name), getattr(reference, name), err_msg=name)
    # The index codec may start a triangle at another corner (same winding): compare rotated to the smallest.
    np.testing.assert_array_equal(_rotate_to_smallest(character.faces), _rotate_to_smallest(reference.faces))


def test_meshopt_exponential_filter_decodes_positions(shared_asset, tmp_path):
    """The EXPONENTIAL filter stores mantissa (24 bits) and exponent (8 bits) per float; with a fixed
    exponent of -16 every position comes back within 2^-17 m."""
    source = shared_asset("CesiumMan.glb")
    reference = load_character(source)
    gltf = _load(source)
    _with_fallback_buffer(gltf)
    index = gltf.meshes[0].primitives[0].attributes.POSITION
    positions = _accessor_array(gltf, index).astype(np.float64)
    exponent = -16
    mantissa = np.round(positions * 2.0**-exponent).astype(np.int64)
    packed = ((exponent & 0xFF) << 24 | (mantissa & 0xFFFFFF)).astype(np.uint32)
    _compress_attribute(gltf, index, packed, "EXPONENTIAL")
    character = load_character(_save(gltf, tmp_path / "exp.glb"))
    np.testing.assert_allclose(character.positions, reference.positions, atol=2.0**-17)
    assert not np.array_equal(character.positions, reference.positions)  # the filter really ran


def test_meshopt_view_that_claims_a_huge_count_is_refused(shared_asset, tmp_path):
    gltf = _load(shared_asset("CesiumMan.glb"))
    _with_fallback_buffer(gltf)
    index = gltf.meshes[0].primitives[0].attributes.POSITION
    _compress_attribute(gltf, index, _accessor_array(gltf, index))
    gltf.bufferViews[-1].extensions["EXT_meshopt_compression"]["count"] = 10**9
    with pytest.raises(ValueError, match=r"claims 12000000000 decoded bytes .*bufferViews\[\d+\] \(EXT_meshopt_compression\) 12000000000"):
        load_character(_save(gltf, tmp_path / "bomb.glb"))



def _views_sharing_one_stream(gltf: pygltflib.GLTF2, views: int, count: int, stride: int) -> None:
    """`views` EXT_meshopt_compression views (each read by its own accessor) that all point at one real
    stream of `count` zero vertices of `stride` bytes: every view decodes, each to count * stride bytes."""
    import meshoptimizer

    encoded = meshoptimizer.encode_vertex_buffer(np.zeros((count, stride), np.uint8), count, stride)
    first = _meshopt_view(gltf, count, stride, "ATTRIBUTES", encoded)
    for _ in range(views):
        gltf.bufferViews.append(copy.deepcopy(gltf.bufferViews[first]))
        gltf.accessors.append(pygltflib.Accessor(bufferView=len(gltf.bufferViews) - 1, componentType=pygltflib.FLOAT,
                                                 count=count, type="VEC3"))


def test_meshopt_views_are_budgeted_per_document_before_decoding(shared_asset, tmp_path):
    """Regression: the decoded-size cap was per view, so eight views of one small stream, each under
    the cap, decoded 8x their claim (a 4.2 MB .glb of eight 256 MiB views: 2.3 GB in the API, then a 201).
    The document's claims are now summed before anything decodes; here 8 x 24 MiB > 128 MiB."""
    from crowdbake.formats.gltf.compression import MAX_DECODED_DOCUMENT_BYTES

    gltf = _load(shared_asset("CesiumMan.glb"))
    _with_fallback_buffer(gltf)
    count = (24 << 20) // 12
    _views_sharing_one_stream(gltf, 8, count, 12)
    assert 8 * count * 12 > MAX_DECODED_DOCUMENT_BYTES
    path = _save(gltf, tmp_path / "eight-views.glb")
    start = time.perf_counter()
    with pytest.raises(ValueError, match=rf"claims {8 * count * 12} decoded bytes in 8 parts, more than the {MAX_DECODED_DOCUMENT_BYTES} one document may decode"):
        load_character(path)
    assert time.perf_counter() - start < 2.0  # refused from the JSON, nothing decoded


def test_meshopt_budget_counts_only_views_accessors_read(shared_asset, tmp_path):
    """Views no accessor reads are never decoded, so they do not count against the budget: the same
    eight big views without accessors load as the plain file does."""
    reference = load_character(shared_asset("CesiumMan.glb"))
    gltf = _load(shared_asset("CesiumMan.glb"))
    _with_fallback_buffer(gltf)
    count = (24 << 20) // 12
    _views_sharing_one_stream(gltf, 8, count, 12)
    del gltf.accessors[-8:]
    character = load_character(_save(gltf, tmp_path / "unread-views.glb"))
    np.testing.assert_array_equal(character.positions, reference.positions)


def test_accessor_extent_is_checked_before_its_view_decodes(shared_asset, tmp_path):
    """An accessor that reads past its compressed view's claimed size is refused from the sizes alone."""
    gltf = _load(shared_asset("CesiumMan.glb"))
    _with_fallback_buffer(gltf)
    index = gltf.meshes[0].primitives[0].attributes.POSITION
    _compress_attribute(gltf, index, _accessor_array(gltf, index))
    extension = gltf.bufferViews[-1].extensions["EXT_meshopt_compression"]
    extension["byteLength"] = 4  # a stream that cannot decode: only the size check can answer first
    gltf.accessors[index].byteOffset = 12
    with pytest.raises(ValueError, match=r"accessors\[\d+\]: .* its bufferView has"):
        load_character(_save(gltf, tmp_path / "past-the-end.glb"))


# ---------------------------------------------------------------------------------------------- materials


def _split_into_two_primitives(gltf: pygltflib.GLTF2) -> int:
    """Make CesiumMan's one primitive two: the first half of its triangles keeps the textured
    material, the second half gets a new red untextured one. Returns the triangle split."""
    primitive = gltf.meshes[0].primitives[0]
    indices = _accessor_array(gltf, primitive.indices)[:, 0]
    half = len(indices) // 6 * 3
    views = []
    for part in (indices[:half], indices[half:]):
        view = _append_view(gltf, part.astype("<u2").tobytes())
        gltf.accessors.append(pygltflib.Accessor(bufferView=view, componentType=5123, count=len(part), type="SCALAR"))
        views.append(len(gltf.accessors) - 1)
    gltf.materials.append(pygltflib.Material(name="red", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(baseColorFactor=[1.0, 0.0, 0.0, 1.0])))
    second = copy.deepcopy(primitive)
    primitive.indices, second.indices, second.material = views[0], views[1], len(gltf.materials) - 1
    gltf.meshes[0].primitives.append(second)
    return half // 3


def test_two_materials_are_both_kept_in_one_atlas(shared_asset, tmp_path):
    """Two primitives with two materials: both are listed, the texture becomes an atlas with a red tile,
    and every vertex of the textured material still samples the texel it sampled before."""
    source = shared_asset("CesiumMan.glb")
    reference = load_character(source)
    gltf = _load(source)
    split = _split_into_two_primitives(gltf)
    character = load_character(_save(gltf, tmp_path / "two.glb"))

    assert [m.name for m in character.materials] == ["Cesium_Man-effect", "red"]
    np.testing.assert_allclose(character.materials[1].base_color_factor, [1, 0, 0, 1])
    assert character.vertex_count == 2 * reference.vertex_count  # each primitive has its own vertices
    assert (character.vertex_materials[: reference.vertex_count] == 0).all()
    assert (character.vertex_materials[reference.vertex_count :] == 1).all()
    assert len(character.faces) == len(reference.faces)
    np.testing.assert_array_equal(character.faces[:split], reference.faces[:split])
    atlas = character.texture
    height, width = atlas.shape[:2]
    texture = reference.texture

    def texel(image, uv):
        h, w = image.shape[:2]
        return image[np.clip((uv[:, 1] * h).astype(int), 0, h - 1), np.clip((uv[:, 0] * w).astype(int), 0, w - 1)]

    used = np.unique(reference.faces[:split])
    before = texel(texture, reference.uvs[used])
    after = texel(atlas, character.uvs[used])
    assert (np.abs(before.astype(int) - after.astype(int)) <= 1).mean() > 0.99  # texel centres may round
    red = texel(atlas, character.uvs[reference.vertex_count :])
    assert (red == [255, 0, 0, 255]).all()
    assert width == texture.shape[1] + 8 + 8 + 8 and height == texture.shape[0] + 8


def test_base_color_factor_tints_the_texture(shared_asset, tmp_path):
    gltf = _load(shared_asset("CesiumMan.glb"))
    gltf.materials[0].pbrMetallicRoughness.baseColorFactor = [0.5, 1.0, 1.0, 1.0]
    tinted = load_character(_save(gltf, tmp_path / "tint.glb")).texture
    plain = load_character(shared_asset("CesiumMan.glb")).texture
    np.testing.assert_array_equal(tinted[..., 1:], plain[..., 1:])
    assert (tinted[..., 0] <= plain[..., 0]).all() and (tinted[..., 0] < plain[..., 0]).mean() > 0.9


def test_a_mesh_used_by_two_skinned_nodes_is_read_once(shared_asset, tmp_path):
    """Two nodes with the same mesh and skin: for skinned meshes the node transform does not apply,
    so the copies coincide; before, the vertices were doubled."""
    source = shared_asset("CesiumMan.glb")
    gltf = _load(source)
    mesh_node = next(n for n in gltf.nodes if n.skin is not None)
    gltf.nodes.append(copy.deepcopy(mesh_node))
    gltf.scenes[0].nodes.append(len(gltf.nodes) - 1)
    assert load_character(_save(gltf, tmp_path / "twice.glb")).vertex_count == load_character(source).vertex_count


def test_rigid_mesh_under_a_joint_follows_it(shared_asset, tmp_path):
    """A mesh node without a skin under a joint (a hat under the head) is attached to that joint."""
    source = shared_asset("CesiumMan.glb")
    reference = load_character(source)
    gltf = _load(source)
    joint_node = gltf.skins[0].joints[5]
    gltf.nodes.append(pygltflib.Node(mesh=0, translation=[0.0, 0.0, 0.1]))
    gltf.nodes[joint_node].children = (gltf.nodes[joint_node].children or []) + [len(gltf.nodes) - 1]
    character = load_character(_save(gltf, tmp_path / "hat.glb"))
    extra = slice(reference.vertex_count, None)
    assert character.vertex_count == 2 * reference.vertex_count
    assert (character.joints[extra, 0] == 5).all() and (character.weights[extra, 0] == 1).all()
    from crowdbake.bake.skinning import joint_world_matrices

    times = np.arange(6) / 24.0
    world = joint_world_matrices(character, times)[:, 5]
    posed, _ = pose_character(character, 24.0, 6)
    local = np.eye(4)
    local[:3, 3] = [0.0, 0.0, 0.1]
    expected = np.einsum("fij,vj->fvi", world @ local, np.c_[reference.positions, np.ones(reference.vertex_count)])[..., :3]
    np.testing.assert_allclose(posed[:, extra], expected, atol=1e-4)


# ---------------------------------------------------------------------------------------------- animations


def test_animation_chosen_by_name_or_index(shared_asset, tmp_path):
    gltf = _load(shared_asset("CesiumMan.glb"))
    slow = copy.deepcopy(gltf.animations[0])
    slow.name = "slow walk"
    times = _accessor_array(gltf, slow.samplers[0].input)[:, 0]
    view = _append_view(gltf, (times * 2).astype("<f4").tobytes())
    gltf.accessors.append(pygltflib.Accessor(bufferView=view, componentType=5126, count=len(times), type="SCALAR"))
    for sampler in slow.samplers:
        sampler.input = len(gltf.accessors) - 1
    gltf.animations.append(slow)
    path = _save(gltf, tmp_path / "two_animations.glb")

    first = load_character(path)
    by_name = load_character(path, animation="slow walk")
    by_index = load_character(path, animation=1)
    assert first.animation_names == ["animation0", "slow walk"]
    assert first.animation_duration == pytest.approx(2.0)
    assert by_name.animation_duration == pytest.approx(4.0) and by_name.animation_name == "slow walk"
    np.testing.assert_allclose(_posed(by_name, 3), _posed(by_index, 3))
    with pytest.raises(ValueError, match="no animation named 'run'.*'slow walk'"):
        load_character(path, animation="run")
    with pytest.raises(ValueError, match="animation 7 does not exist"):
        load_character(path, animation=7)


# ---------------------------------------------------------------------------------------------- refusals


def _with_ktx2_texture(gltf: pygltflib.GLTF2, ktx2: bytes, fallback: bool = False) -> pygltflib.GLTF2:
    """CesiumMan with its base colour texture replaced by `ktx2` through KHR_texture_basisu (required,
    as exporters write it when they ship no PNG fallback; with `fallback` the plain source stays)."""
    gltf.images.append(pygltflib.Image(mimeType="image/ktx2", bufferView=_append_view(gltf, ktx2)))
    gltf.textures[0].extensions = {"KHR_texture_basisu": {"source": len(gltf.images) - 1}}
    gltf.extensionsUsed = ["KHR_texture_basisu"]
    if not fallback:
        gltf.textures[0].source = None
        gltf.extensionsRequired = ["KHR_texture_basisu"]
    return gltf


def _with_png_texture(gltf: pygltflib.GLTF2, png: bytes) -> pygltflib.GLTF2:
    gltf.images[0] = pygltflib.Image(mimeType="image/png", bufferView=_append_view(gltf, png))
    return gltf


def _basisu_encode(png_path: Path, *options: str) -> bytes:
    """PNG -> KTX2 with the same basisu tool the reader transcodes with."""
    from crowdbake.formats.basisu import basisu_tool

    tool = basisu_tool()
    assert tool is not None, "basisu is not installed: run scripts/setup.sh"
    out = png_path.parent / "ktx2"
    out.mkdir(exist_ok=True)
    subprocess.run([str(tool), "-ktx2", *options, str(png_path), "-output_path", str(out)], check=True, capture_output=True, timeout=120)
    return (out / f"{png_path.stem}.ktx2").read_bytes()


@pytest.fixture(scope="module")
def cesium_texture_png(shared_asset, tmp_path_factory) -> Path:
    """CesiumMan's own diffuse texture at 256x256 with an alpha ramp (so both codecs carry alpha), as PNG."""
    from PIL import Image

    gltf = _load(shared_asset("CesiumMan.glb"))
    view = gltf.bufferViews[gltf.images[0].bufferView]
    jpeg = gltf.binary_blob()[view.byteOffset or 0 : (view.byteOffset or 0) + view.byteLength]
    rgba = np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGBA").resize((256, 256), Image.LANCZOS)).copy()
    rgba[..., 3] = np.linspace(64, 255, 256).astype(np.uint8)[:, None]
    path = tmp_path_factory.mktemp("ktx2") / "cesium.png"
    Image.fromarray(rgba, "RGBA").save(path)
    return path


# Largest mean absolute error per channel (0..255) over the texture: UASTC is near-lossless; ETC1S at
# basisu's default quality is a coarse codec (a shared codebook of endpoints and selectors).
KTX2_MEAN_ERROR = {"ETC1S": 6.0, "UASTC": 1.5}


@pytest.mark.parametrize("codec", ["ETC1S", "UASTC"])
def test_ktx2_texture_bakes_textured(shared_asset, cesium_texture_png, tmp_path, codec):
    """KHR_texture_basisu (KTX2, Basis Universal ETC1S or UASTC) decodes through basisu and matches
    the same texture loaded from PNG within the codec's error. It was refused before."""
    png = cesium_texture_png.read_bytes()
    ktx2 = _basisu_encode(cesium_texture_png, *(["-uastc"] if codec == "UASTC" else []))
    assert ktx2.startswith(b"\xabKTX 20")
    reference = load_character(_save(_with_png_texture(_load(shared_asset("CesiumMan.glb")), png), tmp_path / "png.glb"))
    character = load_character(_save(_with_ktx2_texture(_load(shared_asset("CesiumMan.glb")), ktx2), tmp_path / "ktx2.glb"))

    assert character.texture.shape == reference.texture.shape == (256, 256, 4)
    error = np.abs(character.texture.astype(np.int16) - reference.texture.astype(np.int16))
    assert error.mean(axis=(0, 1)).max() < KTX2_MEAN_ERROR[codec], error.mean(axis=(0, 1))
    # The picture, not a flat colour: the decoded texture varies as the PNG does.
    assert np.corrcoef(character.texture[..., :3].ravel(), reference.texture[..., :3].ravel())[0, 1] > 0.98
    np.testing.assert_array_equal(character.uvs, reference.uvs)


def test_ktx2_with_a_png_fallback_reads_the_png(shared_asset, cesium_texture_png, tmp_path):
    """A texture with both a plain source and a KTX2 one is read from the plain (lossless) one."""
    png = cesium_texture_png.read_bytes()
    ktx2 = _basisu_encode(cesium_texture_png)
    reference = load_character(_save(_with_png_texture(_load(shared_asset("CesiumMan.glb")), png), tmp_path / "png.glb"))
    both = _with_ktx2_texture(_with_png_texture(_load(shared_asset("CesiumMan.glb")), png), ktx2, fallback=True)
    np.testing.assert_array_equal(load_character(_save(both, tmp_path / "both.glb")).texture, reference.texture)


def test_ktx2_texture_is_refused_by_name_without_basisu(shared_asset, cesium_texture_png, tmp_path, monkeypatch):
    """Where the basisu tool is not installed, a KTX2 texture is refused by name, never baked untextured."""
    ktx2 = _basisu_encode(cesium_texture_png)
    monkeypatch.setenv("CROWDBAKE_BASISU", str(tmp_path / "no-such-basisu"))
    gltf = _with_ktx2_texture(_load(shared_asset("CesiumMan.glb")), ktx2)
    with pytest.raises(ValueError, match="requires KHR_texture_basisu: every texture is a KTX2 .KHR_texture_basisu.*basisu is not installed"):
        load_character(_save(gltf, tmp_path / "ktx2_required.glb"))
    gltf.extensionsRequired = []
    with pytest.raises(ValueError, match=r"images\[1\] is a KTX2 .KHR_texture_basisu. image.*basisu is not installed"):
        load_character(_save(gltf, tmp_path / "ktx2_used.glb"))


def test_broken_ktx2_textures_are_refused_naming_the_image(shared_asset, cesium_texture_png, tmp_path):
    """Truncated, corrupted, oversized, or not Basis Universal: one line naming the image, from the
    header check or from basisu's own error."""
    from crowdbake.export import ktx2 as ktx2_writer

    good = _basisu_encode(cesium_texture_png, "-uastc")
    oversized = bytearray(good)
    struct.pack_into("<2I", oversized, 20, 20000, 20000)  # pixelWidth, pixelHeight
    corrupted = bytearray(good)
    corrupted[-200:] = bytes(200)  # the Zstandard-compressed level data
    rgba8 = ktx2_writer.encode_ktx2(ktx2_writer.VK_FORMAT_R8G8B8A8_UNORM, np.zeros((1, 8, 8, 4), np.uint8), array=False)
    cases = {
        "truncated": (good[:40], "KTX2 image is truncated"),
        "oversized": (bytes(oversized), "image is 20000x20000, more than"),
        "corrupted": (bytes(corrupted), r"KTX2 image does not transcode \(basisu exit"),
        "rgba8": (rgba8, "KTX2 image is vkFormat 37, not Basis Universal"),
    }
    for name, (data, message) in cases.items():
        gltf = _with_ktx2_texture(_load(shared_asset("CesiumMan.glb")), data)
        with pytest.raises(ValueError, match=r"images\[1\]: " + message):
            load_character(_save(gltf, tmp_path / f"{name}.glb"))


def test_unknown_required_extension_is_refused_by_name(shared_asset, tmp_path):
    gltf = _load(shared_asset("CesiumMan.glb"))
    gltf.extensionsRequired = ["KHR_materials_pbrSpecularGlossiness", "EXT_mesh_gpu_instancing"]
    with pytest.raises(ValueError, match="EXT_mesh_gpu_instancing, KHR_materials_pbrSpecularGlossiness"):
        load_character(_save(gltf, tmp_path / "required.glb"))


# ---------------------------------------------------------------------------------------------- files and limits


def test_gltf_with_external_bin_and_image(shared_asset, tmp_path):
    """A .gltf whose buffer and JPEG image are files beside it reads like the .glb."""
    source = shared_asset("CesiumMan.glb")
    reference = load_character(source)
    gltf = _load(source)
    image_view = gltf.bufferViews[gltf.images[0].bufferView]
    blob = gltf.binary_blob()
    (tmp_path / "skin.jpg").write_bytes(blob[image_view.byteOffset : image_view.byteOffset + image_view.byteLength])
    gltf.images[0].bufferView, gltf.images[0].uri = None, "skin.jpg"
    (tmp_path / "body.bin").write_bytes(blob)
    gltf.buffers[0].uri = "body.bin"
    gltf.set_binary_blob(None)
    gltf.save_json(str(tmp_path / "man.gltf"))
    character = load_character(tmp_path / "man.gltf")
    np.testing.assert_array_equal(character.positions, reference.positions)
    np.testing.assert_array_equal(character.texture, reference.texture)


def test_sixteen_thousand_node_chain_loads_fast(shared_asset, tmp_path):
    """A chain of 16,000 nodes above the skeleton: the hierarchy is walked in linear time (a quadratic
    cycle check took minutes), and the chain's transforms all reach the root joint."""
    gltf = _load(shared_asset("RiggedFigure.glb"))
    root = gltf.scenes[0].nodes[0]
    first = len(gltf.nodes)
    chain = 16000
    for k in range(chain):
        gltf.nodes.append(pygltflib.Node(children=[first + k + 1] if k < chain - 1 else [root], translation=[0.0, 1e-4, 0.0]))
    gltf.scenes[0].nodes[0] = first
    path = _save(gltf, tmp_path / "chain.glb")
    started = time.perf_counter()
    character = load_character(path)
    elapsed = time.perf_counter() - started
    assert elapsed < 1.0, f"{elapsed:.2f} s"  # about 0.25 s on a busy 2-core machine
    top = int(np.flatnonzero(character.joint_parents == -1)[0])
    np.testing.assert_allclose(character.joint_parent_transforms[top][1, 3] - load_character(shared_asset("RiggedFigure.glb")).joint_parent_transforms[top][1, 3], chain * 1e-4, atol=1e-6)

    gltf.nodes[first + chain - 1].children = [first]  # close the chain into a cycle
    gltf.scenes[0].nodes[0] = root
    cyclic = _save(gltf, tmp_path / "cycle.glb")
    started = time.perf_counter()
    with pytest.raises(ValueError, match="cycle|two parents"):
        load_character(cyclic)
    assert time.perf_counter() - started < 1.0


def _zero_accessor(gltf: pygltflib.GLTF2, count: int, type_: str = "VEC3") -> int:
    """An accessor with no bufferView: `count` zeros, claimed by a few bytes of JSON."""
    gltf.accessors.append(pygltflib.Accessor(componentType=pygltflib.FLOAT, count=count, type=type_, min=[0.0] * 3 if type_ == "VEC3" else None,
                                             max=[0.0] * 3 if type_ == "VEC3" else None))
    return len(gltf.accessors) - 1


def test_morph_targets_naming_one_big_accessor_are_budgeted_per_read(shared_asset, tmp_path):
    """Regression: CesiumMan plus a rigid mesh of 999,999 zero vertices whose 200 morph targets all name one
    zero-filled accessor, 0.5 MB of file, took +3.6 GB in the API before a 201: every target expanded the
    same accessor again. Every read is now counted before any accessor is read, and this is refused."""
    from crowdbake.formats.gltf.document import MAX_READ_DOCUMENT_BYTES

    gltf = _load(shared_asset("CesiumMan.glb"))
    zeros = _zero_accessor(gltf, 999_999)
    primitive = pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=zeros), targets=[{"POSITION": zeros}] * 200)
    gltf.meshes.append(pygltflib.Mesh(primitives=[primitive], weights=[0.0] * 200))
    gltf.nodes.append(pygltflib.Node(mesh=len(gltf.meshes) - 1))
    gltf.scenes[gltf.scene or 0].nodes.append(len(gltf.nodes) - 1)
    path = _save(gltf, tmp_path / "targets.glb")
    assert path.stat().st_size < 1 << 20 and 201 * 999_999 * 12 > MAX_READ_DOCUMENT_BYTES
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"reading its accessors would take \d+ bytes .* more than the \d+ one document may take "
                                         r"\(largest: meshes\[1\] morph targets 2399997600"):
        load_character(path)
    assert time.perf_counter() - start < 2.0  # refused from the JSON


def test_weights_channels_sharing_one_long_sampler_count_each_time(shared_asset, tmp_path):
    """200 "weights" channels sharing one sampler of a million keys (8.5 MB of file) took +1.5 GB: each
    channel reads the sampler again, so each counts."""
    gltf = _load(shared_asset("CesiumMan.glb"))
    times, values = _zero_accessor(gltf, 1_000_000, "SCALAR"), _zero_accessor(gltf, 1_000_000, "SCALAR")
    sampler = pygltflib.AnimationSampler(input=times, output=values)
    channels = [pygltflib.AnimationChannel(sampler=0, target=pygltflib.AnimationChannelTarget(node=0, path="weights"))] * 200
    gltf.animations.append(pygltflib.Animation(name="many", samplers=[sampler], channels=channels))
    with pytest.raises(ValueError, match=r"largest: animations\[1\] 1600000000"):
        load_character(_save(gltf, tmp_path / "channels.glb"))
