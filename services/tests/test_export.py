"""`crowdbake export` (crowdbake.export): glTF 2.0 + KTX2 + vertex-animation textures from a bundle.

The pure parts are checked on synthetic data whose answer is known; the export of a real small bake
(the procedural sample) and of CesiumMan with its long skirt is then read back three ways: every .glb
through the Khronos glTF-Validator (node), every KTX2 through ktx-parse (the parser three.js uses,
node) and our own reader, and the glTF's morph targets and VATs against the bundle's pose caches.
"""
from __future__ import annotations

import hashlib
import io
import os
import json
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pygltflib
import pytest

from repo_paths import REPO_ROOT, SHARED_ASSETS
from crowdbake.cli import main as cli_main
from crowdbake.bake import compression
from crowdbake.export import ktx2
from crowdbake.export.textures import (
    IMPOSTOR_NORMAL_ZSTD_LEVEL, layer_digest, model_space_normal_bc1, model_space_normals, rgba8_layers,
)
from crowdbake.export.vat import VertexAnimation, decode_vat, vat_layout
from crowdbake.export.animations import animation_plans
from crowdbake.formats.bundle import verify_bundle
from crowdbake.formats.skinned_cache import SkinnedPoseCache

PREVIEW_DIR = REPO_ROOT / "services" / "crowdbake" / "api" / "static" / "preview"
NODE = shutil.which("node")
NODE_TIMEOUT_S = 300
# Morph targets on int16's 13-bit grid (crowdbake.export.glb.POSITION_GRID): each frame rounded once, within
# half a step (0.05 mm on the sample); a millimetre is the promise.
MORPH_TOLERANCE_M = 1e-3
# 8-bit normals and deltas, summed along the frames' tree aiming at length 63 (glb.quantize_part): 0.8 degrees.
MORPH_NORMAL_DEGREES = 1.0
# VATs: 16-bit positions on a power-of-two grid of codes, within vat.POSITION_BOUND_M as a distance (0.144 mm
# an axis), plus up to vat.SHARED_POSITION_TOLERANCE_M where a LOD reads a finer LOD's texels; or a skin's rest
# pose and joint matrices rounded to 16 bits each (the export states what it measures, and it must be small);
# octahedral 8-bit normals (vat.OCTAHEDRAL_MAX_ERROR_DEG), turned by a skin's matrices.
VAT_TOLERANCE_M = 2.5e-4
VAT_NORMAL_DEGREES = 1.2


def node_tool(script: str, *files: Path) -> list[dict]:
    """Run one of the preview's node tools (tools/*.mjs) on `files`; skips when node or its packages are missing."""
    if NODE is None:
        pytest.skip("node is not installed (scripts/apt-packages.txt lists nodejs)")
    if not (PREVIEW_DIR / "node_modules" / "gltf-validator").is_dir():
        pytest.skip(f"npm packages missing: run `npm ci` in {PREVIEW_DIR} (scripts/setup.sh does)")
    result = subprocess.run([NODE, f"tools/{script}", *map(str, files)], cwd=PREVIEW_DIR, capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert result.stdout, result.stderr[-2000:]
    return json.loads(result.stdout)


# ----------------------------------------------------------------------------- pure parts, synthetic


def test_quantized_part_dequantizes_within_its_grid():
    """KHR_mesh_quantization as glb.quantize_part writes it: offset + scale · (base + the deltas on frame k's
    path) / 32767 gives every frame back within max_position_error_m; values lie on the 13-bit grid; every
    target fits its int16 and int8; the normals, a fold's flip between two frames included, come back within
    a degree (a sum aimed at length 63, normalised: glb._NORMAL_AIMS)."""
    from crowdbake.export.glb import POSITION_GRID, quantize_part

    rng = np.random.default_rng(3)
    walk = np.cumsum(rng.normal(scale=0.01, size=(12, 50, 3)), axis=0)  # a cloth-like loop: small steps
    positions = rng.uniform([-0.3, 0.0, -0.2], [0.3, 1.7, 0.2], size=(1, 50, 3)) + walk
    normals = rng.normal(size=(12, 50, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals[6] = -normals[5]  # every normal flips between frames 5 and 6
    part = quantize_part(positions, normals)
    assert part.positions.dtype == np.int16 and part.normals.dtype == np.int8 and part.position_deltas.shape == (12, 50, 4)
    assert not (part.positions[..., :3] % POSITION_GRID).any() and not part.positions[..., 3].any() and not part.position_deltas[..., 3].any()
    assert (part.parents < 0).sum() == 1 and part.parents.shape == (12,)
    played, played_normals = part.played()
    error = np.abs(played - positions).max()
    assert error <= part.max_position_error_m and error > part.max_position_error_m / 10
    # Weights 1 on frame k's path and nothing else show frame k: the deltas along it sum to its code.
    weights = part.path_weights(np.arange(12))
    assert set(np.unique(weights)) == {0.0, 1.0} and (np.diag(weights) == 1).all()
    summed = part.positions[0, :, :3] + np.einsum("kf,fvi->kvi", weights, part.position_deltas[..., :3].astype(float))
    np.testing.assert_allclose(part.offset + part.scale * summed / 32767, played)
    angles = np.degrees(np.arccos(np.clip((played_normals * normals).sum(-1), -1, 1)))
    assert angles.max() < 0.8 and angles.max() > 0.05
    with pytest.raises(ValueError, match=r"\(F, V, 3\)"):
        quantize_part(positions[..., :2], normals[..., :2])


def test_morph_tree_links_near_frames_within_an_int16():
    """glb.morph_tree: the base's one child is the frame nearest it; the rest hang on their nearest frames
    (a minimum spanning tree), never by an edge a target could not hold; a frame out of every other's
    reach hangs on the base, which holds every code."""
    from crowdbake.export.glb import morph_tree, path_weights

    codes = np.array([[10], [20], [0], [30000], [30010], [-30000]])
    parents = morph_tree(codes, 32767)
    # 0 is nearest the base; 10 and 20 follow it; 30000 is 29,980 from 20; -30000 is 30,000 from 0.
    assert parents.tolist() == [2, 0, -1, 1, 3, 2]
    np.testing.assert_array_equal(path_weights(parents, [4]), [[1, 1, 1, 1, 1, 0]])
    assert morph_tree(np.array([[30000], [-30000]]), 32767).tolist() == [-1, -1]  # 60,000 apart: both from the base
    with pytest.raises(ValueError, match="tree"):
        path_weights(np.array([1, 0]), [0])  # a cycle, no base


def test_only_blocks_with_a_covered_texel_keep_their_normals():
    """The model-space normal map keeps a BC1 block only where the exported UV map covers one of its texels
    (textures.blocks_covering); a reader draws nothing elsewhere. Coverage reads from uv32's bit 31 or
    rgba16's alpha."""
    from crowdbake.export.textures import BC1_BLOCK_BYTES, blocks_covering, covered_texels

    words = np.zeros((1, 8, 12), np.uint32)
    words[0, 5, 9] = (1 << 31) | 77  # one texel of block (row 1, column 2)
    words[0, 0, 0] = 77  # a word without its covered bit: background
    covered = covered_texels(words)
    assert covered.sum() == 1 and covered[0, 5, 9]
    rgba16 = np.zeros((1, 8, 12, 4), np.uint16)
    rgba16[0, 5, 9, 3] = 65535
    np.testing.assert_array_equal(covered_texels(rgba16), covered)
    blocks = bytes(range(1, 6 * BC1_BLOCK_BYTES + 1))
    kept = np.frombuffer(blocks_covering(blocks, covered[0], BC1_BLOCK_BYTES), np.uint8).reshape(2, 3, BC1_BLOCK_BYTES)
    assert kept[1, 2].tobytes() == blocks[5 * BC1_BLOCK_BYTES:] and not np.delete(kept.reshape(6, -1), 5, axis=0).any()


def test_a_normal_turned_past_reach_is_approached():
    """A normalized int8 delta keeps base + delta within one unit of the base in each component: from (0, 0, 1)
    a normal turned 143 degrees to (0.8, 0, -0.6) is out of reach. The delta aims at it scaled, so the sum
    lands on (1, 0, 0), 37 degrees short, the closest reachable, and never on zero."""
    from crowdbake.export.morph_normals import normal_deltas

    base = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    frames = np.array([[[0.8, 0.0, -0.6], [0.6, 0.0, 0.8]]])
    deltas = normal_deltas(base, frames)
    assert np.abs(deltas).max() <= 1.0
    np.testing.assert_allclose(deltas[0, 1], frames[0, 1] - base[1])  # within reach: the plain difference
    turned = base[0] + deltas[0, 0]
    assert abs(np.degrees(np.arccos(turned @ frames[0, 0] / np.linalg.norm(turned))) - 36.87) < 0.5


@pytest.mark.parametrize(
    "vk_format, dtype, channels",
    [(ktx2.VK_FORMAT_R8G8B8A8_UNORM, np.uint8, 4), (ktx2.VK_FORMAT_R8G8B8A8_SRGB, np.uint8, 4), (ktx2.VK_FORMAT_R16G16B16A16_UNORM, np.uint16, 4), (ktx2.VK_FORMAT_R32_UINT, np.uint32, 1)],
)
@pytest.mark.parametrize("zstd_level", [None, ktx2.ZSTD_LEVEL])
def test_ktx2_round_trips_texels_bit_for_bit(vk_format, dtype, channels, zstd_level):
    rng = np.random.default_rng(vk_format)
    layers = rng.integers(0, np.iinfo(dtype).max, size=(3, 5, 7, channels), dtype=dtype, endpoint=True)
    layers[:, :2] = 0  # something for zstd to take away
    data = ktx2.encode_ktx2(vk_format, layers, zstd_level=zstd_level)
    image = ktx2.decode_ktx2(data)
    assert image.vk_format == vk_format and image.layer_count == 3
    np.testing.assert_array_equal(image.texels, layers)
    assert image.key_values == {"KTXorientation": "rd", "KTXwriter": "crowdbake 0.1.0"}
    level_offset, level_length, uncompressed = np.frombuffer(data[80:104], "<u8")
    assert uncompressed == layers.nbytes
    if zstd_level is None:
        # Level data starts aligned to lcm(texel size, 4), as the KTX2 spec asks; typeSize is the word's.
        assert level_offset % max(4, layers.dtype.itemsize * channels) == 0 and level_length == uncompressed
        assert image.supercompression == 0 and int.from_bytes(data[16:20], "little") == layers.dtype.itemsize
    else:
        # Supercompressed: scheme 2, typeSize 1, the level smaller than its texels.
        assert image.supercompression == 2 and int.from_bytes(data[44:48], "little") == 2 and int.from_bytes(data[16:20], "little") == 1
        assert level_length < uncompressed


def test_a_level_over_8_mib_is_compressed_with_a_window_over_all_of_it():
    """An impostor UV map's layers repeat a layer apart (several MiB): a level over LARGE_LEVEL_FROM_BYTES
    gets a window over the whole level (within every decoder's default 2^27), so a repeat 9 MiB back is
    found that level 12's own 8 MiB window misses, and the KTX2 reads back with default decoder limits."""
    import zstandard

    half = np.random.default_rng(3).integers(0, 1 << 32, size=9 << 18, dtype=np.uint32)  # 9 MiB of words
    layers = np.concatenate([half, half]).reshape(1, -1, 1024, 1)  # one layer of 1024-word rows, its halves equal
    data = ktx2.encode_ktx2(ktx2.VK_FORMAT_R32_UINT, layers)
    level_offset, level_length, uncompressed = np.frombuffer(data[80:104], "<u8")
    assert uncompressed == 18 << 20 > ktx2.LARGE_LEVEL_FROM_BYTES
    assert level_length < 0.55 * uncompressed  # the second half found 9 MiB back
    assert len(zstandard.ZstdCompressor(level=ktx2.ZSTD_LEVEL).compress(layers.tobytes())) > 0.95 * uncompressed  # level 12 alone cannot
    window = zstandard.get_frame_parameters(data[level_offset:level_offset + level_length]).window_size
    assert uncompressed <= window <= 1 << ktx2.LONGEST_WINDOW_LOG
    np.testing.assert_array_equal(ktx2.decode_ktx2(data).texels.reshape(-1), layers.reshape(-1))


def test_ktx2_reader_refuses_a_broken_zstd_level():
    data = bytearray(ktx2.encode_ktx2(ktx2.VK_FORMAT_R8G8B8A8_UNORM, np.zeros((1, 8, 8, 4), np.uint8)))
    data[-4:] = b"\xff\xff\xff\xff"
    with pytest.raises(ValueError, match="zstd|size"):
        ktx2.decode_ktx2(bytes(data))


def texture2ddecoder_rgba(blocks: bytes, vk_format: int, width: int, height: int) -> np.ndarray:
    """(H, W, 4) uint8 RGBA of one layer of BC1/BC2 blocks, decoded by texture2ddecoder (an independent
    decoder). It has no BC2, so a BC2 block's colour half goes through its BC3 path behind an opaque
    alpha block (BC2 and BC3 decode colour alike, always in 4-colour mode) and the explicit 4-bit alpha
    is expanded by the format's definition, nibble * 17."""
    texture2ddecoder = pytest.importorskip("texture2ddecoder")
    if ktx2.BLOCK_LAYOUTS[vk_format].block_bytes == 8:
        bgra = texture2ddecoder.decode_bc1(bytes(blocks), width, height)
        return np.frombuffer(bgra, np.uint8).reshape(height, width, 4)[..., [2, 1, 0, 3]].copy()
    pairs = np.frombuffer(bytes(blocks), np.uint8).reshape(-1, 16)
    opaque = np.tile(np.array([255, 255, 0, 0, 0, 0, 0, 0], np.uint8), (len(pairs), 1))
    bgra = texture2ddecoder.decode_bc3(np.concatenate([opaque, pairs[:, 8:]], axis=1).tobytes(), width, height)
    rgba = np.frombuffer(bgra, np.uint8).reshape(height, width, 4)[..., [2, 1, 0, 3]].copy()
    nibbles = np.stack([pairs[:, :8] & 15, pairs[:, :8] >> 4], axis=-1).reshape(-1, 4, 4)  # per block, rows of 4
    alpha = nibbles.reshape(height // 4, width // 4, 4, 4).transpose(0, 2, 1, 3).reshape(height, width)
    rgba[..., 3] = alpha * 17
    return rgba


@pytest.mark.parametrize("pixel_format, colour", [("bc1", False), ("bc1", True), ("bc2", False), ("bc2", True)])
def test_bc_ktx2_keeps_the_blocks_and_decodes_to_the_bundles_texels(pixel_format, colour):
    """The block path copies a TextureArray's layers byte for byte; texture2ddecoder decoding the KTX2's
    blocks gives exactly the texels crowdbake's own decoder gives for the bundle layer."""
    from crowdbake.bake import compression
    from crowdbake.export.textures import colour_ktx2
    from crowdbake.formats.binary import TextureArray

    rng = np.random.default_rng(11)
    width, height = 24, 16
    images = rng.integers(0, 256, size=(3, height, width, 4), dtype=np.uint8)
    images[..., 3] = 17 * rng.integers(0, 16, size=(3, height, width))  # region codes survive BC2 exactly
    texture = TextureArray(width, height, pixel_format, [compression.encode(image, pixel_format) for image in images])
    vk_format, data = colour_ktx2(texture, colour, "bc")
    assert ktx2.format_name(vk_format) == f"{pixel_format.upper()}{'_RGB' if pixel_format == 'bc1' else ''}_{'SRGB' if colour else 'UNORM'}_BLOCK"
    image = ktx2.decode_ktx2(data)
    assert image.texels is None and image.layer_count == 3 and (image.width, image.height) == (width, height)
    assert [layer.tobytes() for layer in image.blocks] == list(texture.layers)
    for k, layer in enumerate(image.blocks):
        ours = compression.decode(texture.layers[k], pixel_format, width, height)
        np.testing.assert_array_equal(texture2ddecoder_rgba(layer, vk_format, width, height), ours)
    header = np.frombuffer(data[:80], "<u4", 17, 12)
    assert header[1] == 1, "typeSize of a block format is 1"
    level_offset, level_length, uncompressed = np.frombuffer(data[80:104], "<u8")
    assert uncompressed == 3 * len(texture.layers[0]) and image.supercompression == 2
    # rgba8 mode: the same texels, decoded, in an RGBA8 file 4x (BC2) or 8x (BC1) the size of the blocks.
    vk_rgba8, data_rgba8 = colour_ktx2(texture, colour, "rgba8")
    assert vk_rgba8 == (ktx2.VK_FORMAT_R8G8B8A8_SRGB if colour else ktx2.VK_FORMAT_R8G8B8A8_UNORM)
    np.testing.assert_array_equal(ktx2.decode_ktx2(data_rgba8).texels, np.stack([compression.decode(layer, pixel_format, width, height) for layer in texture.layers]))


def test_ktx2_block_writer_refuses_sizes_that_do_not_fit():
    with pytest.raises(ValueError, match="multiples of 4"):
        ktx2.encode_ktx2_blocks(ktx2.VK_FORMAT_BC1_RGB_UNORM_BLOCK, 6, 4, [b"\0" * 16])
    with pytest.raises(ValueError, match="layers of 8 bytes"):
        ktx2.encode_ktx2_blocks(ktx2.VK_FORMAT_BC1_RGB_UNORM_BLOCK, 4, 4, [b"\0" * 16])
    with pytest.raises(ValueError, match="block format"):
        ktx2.encode_ktx2_blocks(ktx2.VK_FORMAT_R8G8B8A8_UNORM, 4, 4, [b"\0" * 64])


def test_ktx2_refuses_texels_that_do_not_fit_the_format():
    with pytest.raises(ValueError, match="uint8"):
        ktx2.encode_ktx2(ktx2.VK_FORMAT_R8G8B8A8_UNORM, np.zeros((1, 4, 4, 4), np.uint16))
    with pytest.raises(ValueError, match=r"\(L, H, W, 4\)"):
        ktx2.encode_ktx2(ktx2.VK_FORMAT_R8G8B8A8_UNORM, np.zeros((1, 4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="vkFormat"):
        ktx2.encode_ktx2(131, np.zeros((1, 4, 4, 4), np.uint8))


# ----------------------------------------------------------------------------- a real small bake


@pytest.fixture(scope="module")
def sample_bundle(tmp_path_factory) -> Path:
    pytest.importorskip("pyrender")
    from crowdbake.params import BakeParams
    from crowdbake.stages.runner import run_bake
    from crowdbake.stages.validate import BakeInputs
    from crowdbake.sample.generate import generate_sample

    root = tmp_path_factory.mktemp("export_sample")
    generate_sample(root / "sample", garment="loose", cycles=3, seed=1, cycle_frames=24, texture_size=64)
    params = BakeParams(impostor_frames=2, azimuths=4, elevations_deg=(0.0, 30.0), tile_size=32, lod_triangles=1200, cycle_views=3, candidates=3,
                        detail_map=True)
    inputs = BakeInputs(
        character=root / "sample" / "character.glb", cloth=root / "sample" / "cloth.pc2", cloth_mesh=root / "sample" / "cloth.obj",
        textures=root / "sample" / "textures", cycle=None, name="sample", version="1.0", params=params,
    )
    return run_bake(inputs, root / "bundles", work=root / "work").bundle


@pytest.fixture(scope="module")
def sample_export(sample_bundle, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export_out") / "sample"
    assert cli_main(["export", str(sample_bundle), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def sample_export_rgba8(sample_bundle, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export_out_rgba8") / "sample"
    assert cli_main(["export", str(sample_bundle), "--out", str(out), "--ktx2", "rgba8", "--vat-png"]) == 0  # check_export reads the PNGs
    return out


def read_vat_texture(out: Path, files: dict) -> np.ndarray:
    """A VAT's (H, W, 4) uint16 texels from its KTX2, and the same from its PNG where there is one (--vat-png)."""
    image = ktx2.decode_ktx2((out / files["ktx2"]).read_bytes())
    assert image.vk_format == ktx2.VK_FORMAT_R16G16B16A16_UNORM and image.layer_count == 0
    texels = image.texels[0]
    if "png" in files:
        np.testing.assert_array_equal(cv2.cvtColor(cv2.imread(str(out / files["png"]), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA), texels)
    return texels


def vat_played(out: Path, vat: dict, texcoords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(positions, normals), each (F, V, 3): what a part's VAT gives each mesh vertex, the vertex found by its
    TEXCOORD_1 (`texcoords`, (V, 2)) as a shader finds it, decoded as export.json's `vat` block says."""
    from crowdbake.export.vat import SKIN_BLOCKS, JOINT_ROWS, JointTexture, SkinTexture, play_skin

    skinned = vat["kind"] == "skin"
    layout = vat_layout(vat["vertex_count"], SKIN_BLOCKS if skinned else vat["frame_count"], vat["width"])
    assert (layout.height, layout.rows_per_frame) == (vat["height"], vat["rows_per_frame"])
    texels = read_vat_texture(out, vat["texture"])
    assert texels.shape == (layout.height, layout.width, 4)
    column, row = np.floor(texcoords * [layout.width, layout.height]).astype(int).T
    assert (row < layout.rows_per_frame).all()  # every vertex addresses block 0
    vertices = row * layout.width + column
    bounds = np.array(vat["bounds_min"]), np.array(vat["bounds_max"])
    if not skinned:
        positions, normals = decode_vat(VertexAnimation(layout, texels, *bounds))
        return positions[:, vertices], normals[:, vertices]
    block = vat["joints"]
    joint_layout = vat_layout(block["joint_count"] * JOINT_ROWS, vat["frame_count"], block["width"])
    assert (joint_layout.height, joint_layout.rows_per_frame) == (block["height"], block["rows_per_frame"])
    joints = JointTexture(joint_layout, read_vat_texture(out, block), block["joint_count"], np.array(block["min"]), np.array(block["max"]))
    positions, normals = play_skin(SkinTexture(layout, texels, *bounds), joints)
    return positions[:, vertices], normals[:, vertices]


def check_export(bundle_dir: Path, out: Path, surface_map: bool = False) -> None:
    """Everything this module promises about an export of `bundle_dir` at `out`."""
    bundle = verify_bundle(bundle_dir)
    sidecar = json.loads((out / "export.json").read_text())
    manifest = bundle.manifest

    # 1. Every .glb passes the Khronos glTF-Validator with no error (and no warning).
    glbs = sorted(out.glob("*.glb"))
    assert [lod["glb"] for lod in sidecar["lods"]] == [p.name for p in glbs] and glbs
    for report in node_tool("validate-gltf.mjs", *glbs):
        assert report["errors"] == 0 and report["warnings"] == 0, report["messages"][:5]

    # 2. Morph targets (KHR_mesh_quantization: int16 on a 13-bit grid, dequantized by the node's scale and
    # translation) and VATs reproduce the pose caches.
    for lod in sidecar["lods"]:
        gltf = pygltflib.GLTF2.load(out / lod["glb"])
        blob = gltf.binary_blob()
        meshes = {mesh.name: mesh for mesh in gltf.meshes}
        assert len(gltf.animations) == 1 and gltf.animations[0].name == "cycle"
        assert gltf.extensionsRequired == ["KHR_mesh_quantization"]
        for part in lod["parts"]:
            cache = bundle.pose_caches[next(m["file"] for m in manifest["meshes"] if m["lod"] == lod["lod"] and m["part"] == part["part"])]
            mesh_index = next(k for k, mesh in enumerate(gltf.meshes) if mesh.name == part["part"])
            node = next(n for n in gltf.nodes if n.mesh == mesh_index)
            primitive = meshes[part["part"]].primitives[0]
            # A body stored as skinning (a CBSK) is a glTF skin; everything else morph targets.
            assert part["playback"] == ("skin" if isinstance(cache, SkinnedPoseCache) else "morph"), part["part"]
            if part["playback"] == "skin":
                assert node.skin is not None and node.translation is None and node.scale is None
                check_skinned_part(gltf, blob, part, cache, animation_plans(bundle.ranges))
            else:
                check_morph_frame(gltf, blob, part, node, primitive, cache)
            np.testing.assert_array_equal(read_accessor(gltf, blob, primitive.attributes.TEXCOORD_0), cache.uvs)
            vat = part["vat"]
            assert meshes[part["part"]].extras["crowdbake"]["vat"] == vat
            assert vat["kind"] == ("skin" if isinstance(cache, SkinnedPoseCache) else "frames") and vat["frame_count"] == cache.frame_count
            positions, normals = vat_played(out, vat, read_accessor(gltf, blob, primitive.attributes.TEXCOORD_1))
            error = np.abs(positions - cache.positions).max(axis=(0, 1))
            assert (error <= np.array(vat["max_position_error_m"]) + 1e-7).all(), error
            assert (error <= VAT_TOLERANCE_M).all(), error
            turned = np.degrees(np.arccos(np.clip((normals * cache.normals).sum(-1), -1, 1)))
            assert turned.max() < VAT_NORMAL_DEGREES, turned.max()
            if lod["lod"] > 0 and "texels_of_lod" in vat:  # this LOD reads a finer LOD's files
                finer = next(p for entry in sidecar["lods"] if entry["lod"] == vat["texels_of_lod"] for p in entry["parts"] if p["part"] == part["part"])
                assert vat["texture"] == finer["vat"]["texture"] and vat["width"] == finer["vat"]["width"]

    # 3. KTX2: ktx-parse reads every file, its writer gives back the same bytes, and the texels are
    # the bundle's: error 0. In "bc" mode a BC1/BC2 bundle layer is in the file block for block and
    # texture2ddecoder decodes it to the texels crowdbake's decoder gives; in "rgba8" mode the file holds
    # those decoded texels.
    expected, sources = {}, {}
    for material in sidecar["materials"]:
        source = next(m for m in manifest["materials"] if m["name"] == material["name"])
        sources[material["diffuse"]["ktx2"]] = bundle.textures[source["diffuse"]]
    sources[sidecar["outfits"]["ktx2"]] = bundle.textures[manifest["outfits"]["file"]]
    # The surface map only where asked for (`--surface-map`): no shipped reader draws with it.
    assert ("surface" in sidecar["impostor"]["maps"]) == (surface_map and "surface" in manifest["impostor"]["maps"])
    for kind in ("normal", "detail", "surface"):
        if kind in sidecar["impostor"]["maps"]:
            sources[sidecar["impostor"]["maps"][kind]["ktx2"]] = bundle.textures[manifest["impostor"]["maps"][kind]]
    uv = bundle.textures[manifest["impostor"]["maps"]["uv"]]
    if uv.pixel_format == "uvblock":  # exported as the uv32 words of its decoded texels
        from crowdbake.bake.map_codecs import uvblock_to_uv32

        words = np.stack([uvblock_to_uv32(layer, uv.width, uv.height) for layer in uv.layers])
    else:
        words = np.stack([uv.texels(k) for k in range(len(uv.layers))])
    surface = bundle.textures.get(manifest["impostor"]["maps"].get("surface", ""))
    if surface is not None and surface.pixel_format == "bc2":  # covered where the character covers over half the texel
        alpha = np.stack([compression.decode(layer, "bc2", surface.width, surface.height)[..., 3] for layer in surface.layers])
        assert ((alpha > 0) & (alpha < 255)).any()  # the bake's silhouette is soft
        words = np.where(alpha / 255.0 > 0.5, words, 0)
    expected[sidecar["impostor"]["maps"]["uv"]["ktx2"]] = words
    covered = (words >> 31).astype(bool)
    for path, texture in sources.items():
        # A bc5 normal map (two in-view components) is exported in model space: BC1 blocks of those codes in
        # "bc" mode (decoded here as an engine would), the codes themselves in "rgba8" mode; 0 where the UV map
        # covers no texel (of the 4x4 block, in "bc" mode), as nothing reads a normal there.
        if texture.pixel_format == "bc5":
            codes = model_space_normals(texture, manifest["impostor"])
            if sidecar["ktx2"] == "bc":
                codes = np.stack([compression.decode(compression.encode_bc1(layer), "bc1", texture.width, texture.height) for layer in codes])
                live = covered.reshape(len(codes), texture.height // 4, 4, texture.width // 4, 4).any(axis=(2, 4))
                kept, nothing = np.repeat(np.repeat(live, 4, axis=1), 4, axis=2), [0, 0, 0, 255]  # a zero BC1 block: opaque black
            else:
                kept, nothing = covered, [0, 0, 0, 0]
            assert covered.any() and not kept.all()
            expected[path] = np.where(kept[..., None], codes, np.array(nothing, np.uint8))
        else:
            expected[path] = rgba8_layers(texture)
    ktx_files = sorted(out.rglob("*.ktx2"))
    reports = {Path(r["path"]).relative_to(out).as_posix(): r for r in node_tool("read-ktx2.mjs", *ktx_files)}
    assert len(reports) == len(ktx_files)
    block_files = 0
    for path, report in reports.items():
        assert report["reserialisedIdentical"] and report["levelCount"] == 1 and report["supercompressionScheme"] == 2, path
        image = ktx2.decode_ktx2((out / path).read_bytes())
        assert report["levels"][0]["sha256"] == hashlib.sha256(image.stored_level).hexdigest(), path
        if path not in expected:
            continue
        if image.blocks is not None:
            block_files += 1
            texture = sources[path]
            assert sidecar["ktx2"] == "bc" and texture.pixel_format in ("bc1", "bc2", "bc5"), path
            if texture.pixel_format != "bc5":  # bc5 normals are re-encoded in model space (checked by their texels)
                assert [layer.tobytes() for layer in image.blocks] == list(texture.layers[: len(image.blocks)]), path
            decoded = np.stack([texture2ddecoder_rgba(layer, image.vk_format, image.width, image.height) for layer in image.blocks])
            np.testing.assert_array_equal(decoded, expected[path][: len(decoded)], err_msg=path)
        else:
            np.testing.assert_array_equal(image.texels.reshape(expected[path].shape), expected[path], err_msg=path)
    assert set(expected) <= set(reports)
    compressed_sources = sum(texture.pixel_format in ("bc1", "bc2", "bc5") for texture in sources.values())
    assert block_files == (compressed_sources if sidecar["ktx2"] == "bc" else 0)

    # 4. The sidecar describes the impostor as the bundle does.
    impostor = sidecar["impostor"]
    for key in ("tile_size", "azimuths_deg", "elevations_deg", "frame_indices", "bounds"):
        assert impostor[key] == manifest["impostor"][key]
    switch = impostor["switch_distance"]
    radius, tile = manifest["impostor"]["bounds"]["radius"], manifest["impostor"]["tile_size"]
    assert switch["distance_m"] == pytest.approx(radius * 720 / (tile * np.tan(np.radians(22.5))))
    assert set(sidecar["regions"]["used"]) <= set(range(16))


def morph_played(gltf: pygltflib.GLTF2, blob: bytes, node, primitive, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A morph part's positions (dequantized by its node) and unit normals at morph `weights` (T,), as a glTF
    player sums them: base plus the weighted targets."""
    position = read_accessor(gltf, blob, primitive.attributes.POSITION)
    normal = read_accessor(gltf, blob, primitive.attributes.NORMAL)
    for target, weight in zip(primitive.targets, weights):  # pygltflib loads targets as dicts
        if weight:
            position = position + weight * read_accessor(gltf, blob, target["POSITION"])
            normal = normal + weight * read_accessor(gltf, blob, target["NORMAL"])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return np.array(node.translation) + node.scale[0] * position, normal


def check_morph_frame(gltf: pygltflib.GLTF2, blob: bytes, part: dict, node, primitive, cache) -> None:
    """A part played by morph targets: the targets on the middle frame's path (mesh extras `morph_parents`),
    dequantized by the node, give that frame."""
    from crowdbake.export.glb import path_weights

    mesh = next(m for m in gltf.meshes if m.primitives[0] is primitive)
    parents = np.array(mesh.extras["crowdbake"]["morph_parents"])
    assert parents.shape == (cache.frame_count,) and (parents < 0).sum() >= 1
    frame = cache.frame_count // 2
    assert part["node"]["translation"] == node.translation and part["node"]["scale"] == node.scale[0]
    played, normal = morph_played(gltf, blob, node, primitive, path_weights(parents, [frame])[0])
    assert np.abs(played - cache.positions[frame]).max() < MORPH_TOLERANCE_M
    turned = np.degrees(np.arccos(np.clip((normal * cache.normals[frame]).sum(-1), -1, 1)))
    assert turned.max() < MORPH_NORMAL_DEGREES, turned.max()


def skin_played(gltf: pygltflib.GLTF2, blob: bytes, mesh_index: int, animation: pygltflib.Animation, keys, normals: bool = False):
    """(K, V, 3) positions a glTF player gives for skinned mesh `mesh_index` at `keys` (key indices) of
    `animation`: the rest mesh plus its morph targets at their keyed weights, skinned by the joints' keyed
    translation, rotation and scale (a joint no channel keys keeps its node's) times its inverse bind.
    normals: also the (K, V, 3) unit normals, turned by the blended 3 x 3 blocks (three.js's skinning)."""
    from scipy.spatial.transform import Rotation

    node_index = next(k for k, node in enumerate(gltf.nodes) if node.mesh == mesh_index)
    skin = gltf.skins[gltf.nodes[node_index].skin]
    primitive = gltf.meshes[mesh_index].primitives[0]
    rest = read_accessor(gltf, blob, primitive.attributes.POSITION).astype(np.float64)
    influences = read_accessor(gltf, blob, primitive.attributes.JOINTS_0).astype(np.int64)
    weights = read_accessor(gltf, blob, primitive.attributes.WEIGHTS_0).astype(np.float64)
    targets = np.array([read_accessor(gltf, blob, target["POSITION"]) for target in primitive.targets or []]).reshape(-1, len(rest), 3)
    rest_normals = read_accessor(gltf, blob, primitive.attributes.NORMAL).astype(np.float64)
    normal_targets = np.array([read_accessor(gltf, blob, target["NORMAL"]) for target in primitive.targets or []]).reshape(-1, len(rest), 3)
    inverse_binds = read_accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    tracks = {(c.target.node, c.target.path): read_accessor(gltf, blob, animation.samplers[c.sampler].output) for c in animation.channels}

    def keyed(joint: int, path: str, default: list[float], key: int) -> np.ndarray:
        return np.asarray(tracks[(joint, path)][key] if (joint, path) in tracks else getattr(gltf.nodes[joint], path) or default, np.float64)

    played, turned = [], []
    for key in keys:
        morphed, morphed_normals = rest.copy(), rest_normals.copy()
        if (node_index, "weights") in tracks:
            target_weights = tracks[(node_index, "weights")].reshape(-1, len(targets))[key]
            morphed += np.einsum("c,cvi->vi", target_weights, targets)
            morphed_normals += np.einsum("c,cvi->vi", target_weights, normal_targets)
        matrices = np.tile(np.eye(4), (len(skin.joints), 1, 1))
        for row, joint in enumerate(skin.joints):
            matrices[row, :3, :3] = Rotation.from_quat(keyed(joint, "rotation", [0, 0, 0, 1], key)).as_matrix() * keyed(joint, "scale", [1, 1, 1], key)
            matrices[row, :3, 3] = keyed(joint, "translation", [0, 0, 0], key)
        skinning = matrices @ inverse_binds  # the joints hang from the character's root, at identity
        blended = np.einsum("vk,vkij->vij", weights, skinning[influences])
        played.append(np.einsum("vij,vj->vi", blended[:, :3, :3], morphed) + blended[:, :3, 3])
        normal = np.einsum("vij,vj->vi", blended[:, :3, :3], morphed_normals)
        turned.append(normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12))
    return (np.asarray(played), np.asarray(turned)) if normals else np.asarray(played)


def check_skinned_part(gltf: pygltflib.GLTF2, blob: bytes, part: dict, cache, plans) -> None:
    """A body exported as a glTF skin: JOINTS_0 and unorm16 WEIGHTS_0, morph targets only on its corrective
    frames, every animation playing the bundle's frames at its keys within a millimetre, and its bytes in the
    .glb (mesh, skin, keys) a fraction of what its morph targets took."""
    mesh_index = next(k for k, mesh in enumerate(gltf.meshes) if mesh.name == part["part"])
    primitive = gltf.meshes[mesh_index].primitives[0]
    assert part["playback"] == "skin" and "bones" not in part
    assert (part["node"]["translation"], part["node"]["scale"]) == ([0.0, 0.0, 0.0], 1.0)  # the VATs' space is the skin's
    weights = gltf.accessors[primitive.attributes.WEIGHTS_0]
    assert weights.normalized and weights.componentType == pygltflib.UNSIGNED_SHORT
    corrective = part["skin"]["corrective_frames"]
    assert len(primitive.targets or []) == len(corrective) and len(corrective) < cache.frame_count / 4
    assert gltf.meshes[mesh_index].extras.get("targetNames", []) == [f"frame_{frame}" for frame in corrective]
    for plan, animation in zip(plans, gltf.animations, strict=True):
        played, normals = skin_played(gltf, blob, mesh_index, animation, range(plan.key_count), normals=True)
        assert np.linalg.norm(played - cache.positions[plan.keys], axis=-1).max() < MORPH_TOLERANCE_M, (plan.name, part["part"])
        turned = np.degrees(np.arccos(np.clip((normals * cache.normals[plan.keys]).sum(-1), -1, 1)))
        assert turned.max() < MORPH_NORMAL_DEGREES, (plan.name, part["part"], turned.max())  # float rest normals, int8 corrections
    node_index = next(k for k, node in enumerate(gltf.nodes) if node.mesh == mesh_index)
    skin = gltf.skins[gltf.nodes[node_index].skin]
    accessors = {primitive.attributes.POSITION, primitive.attributes.NORMAL, primitive.attributes.JOINTS_0, primitive.attributes.WEIGHTS_0,
                 skin.inverseBindMatrices}
    accessors |= {index for target in primitive.targets or [] for index in target.values()}
    accessors |= {a.samplers[c.sampler].output for a in gltf.animations for c in a.channels if c.target.node in {*skin.joints, node_index}}
    skin_bytes = sum(gltf.bufferViews[gltf.accessors[index].bufferView].byteLength for index in accessors)
    # export.json's count (40 bytes a vertex, 16 a vertex a corrective frame, 32 a weighted joint a key), under
    # the morph targets' 12 bytes a vertex a pose frame (the export's rule), and a quarter of them on a body of
    # over 2,000 vertices, where the rest mesh outweighs the joints' keys.
    assert skin_bytes == part["skin"]["bytes"], (part["part"], skin_bytes, part["skin"]["bytes"])
    assert skin_bytes < cache.frame_count * cache.vertex_count * 12 / (4 if cache.vertex_count > 2000 else 1), (part["part"], skin_bytes)


def read_accessor(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """An accessor's values; normalized integers as the floats they stand for (glTF's rule: max(c / max, -1))."""
    accessor = gltf.accessors[index]
    view = gltf.bufferViews[accessor.bufferView]
    dtype = np.dtype({pygltflib.FLOAT: "<f4", pygltflib.UNSIGNED_SHORT: "<u2", pygltflib.UNSIGNED_INT: "<u4", pygltflib.SHORT: "<i2",
                      pygltflib.BYTE: "i1", pygltflib.UNSIGNED_BYTE: "u1"}[accessor.componentType])
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[accessor.type]
    stride = view.byteStride or dtype.itemsize * width
    start = view.byteOffset + (accessor.byteOffset or 0)
    rows = np.frombuffer(blob, np.uint8, stride * (accessor.count - 1) + dtype.itemsize * width, start)
    data = np.lib.stride_tricks.as_strided(rows.view(np.uint8), (accessor.count, dtype.itemsize * width), (stride, 1)).copy().view(dtype)
    if accessor.normalized:
        data = np.maximum(data.astype(np.float64) / np.iinfo(dtype).max, -1.0)
    return data.reshape(accessor.count, width) if width > 1 else data.reshape(-1)


def test_sample_export_validates_and_round_trips(sample_bundle, sample_export):
    sidecar = json.loads((sample_export / "export.json").read_text())
    assert sidecar["ktx2"] == "bc" and sidecar["format_version"] == 5
    assert sidecar["impostor"]["maps"]["normal"]["vk_format"] == "BC1_RGB_UNORM_BLOCK"  # the bundle's bc5, in model space
    assert sidecar["impostor"]["maps"]["detail"]["vk_format"] == "BC2_SRGB_BLOCK"
    assert sidecar["impostor"]["maps"]["uv"]["vk_format"] == "R32_UINT"  # words stay exact, never block-compressed
    # The engine setups ship inside the export (docs/export.md "Using it in an engine").
    assert {"shaders/crowdbake_vat.gdshader", "shaders/unity_vat_custom_function.hlsl", "shaders/unreal_vat_custom_node.hlsl"} <= set(sidecar["shaders"])
    assert all((sample_export / path).is_file() for path in sidecar["shaders"])
    # So do the engines' import scripts, beside export.json's folder (tests/test_engine_import.py).
    assert sidecar["engines"] == ["engines/CrowdbakeUnityImport.cs", "engines/crowdbake_godot_import.gd", "engines/crowdbake_unreal_import.py"]
    assert all((sample_export / path).is_file() for path in sidecar["engines"])
    check_export(sample_bundle, sample_export)


def test_rgba8_export_decodes_the_blocks_and_is_larger(sample_bundle, sample_export, sample_export_rgba8):
    sidecar = json.loads((sample_export_rgba8 / "export.json").read_text())
    assert sidecar["ktx2"] == "rgba8" and sidecar["impostor"]["maps"]["detail"]["vk_format"] == "R8G8B8A8_SRGB"
    check_export(sample_bundle, sample_export_rgba8)
    # Same files; the BC ones 4x (BC2) or 8x (BC1) smaller in their level data.
    sizes = {mode: {p.relative_to(root).as_posix(): p.stat().st_size for p in root.rglob("*.ktx2")} for mode, root in (("bc", sample_export), ("rgba8", sample_export_rgba8))}
    assert sizes["bc"].keys() == sizes["rgba8"].keys()
    for kind, ratio in (("normal", 8), ("detail", 4)):
        path = f"impostor/{kind}.ktx2"
        # uncompressedByteLength: the texels' bytes before zstd
        level_bc = int.from_bytes((sample_export / path).read_bytes()[96:104], "little")
        level_rgba8 = int.from_bytes((sample_export_rgba8 / path).read_bytes()[96:104], "little")
        assert level_rgba8 == ratio * level_bc, path


def test_the_impostor_normal_map_is_compressed_harder_than_the_other_textures(sample_export):
    """Its BC1 blocks take zstd at IMPOSTOR_NORMAL_ZSTD_LEVEL (the robot's zip fits 10 MB by it): the stored
    level is that level's frame of the blocks, and smaller than ktx2.ZSTD_LEVEL's."""
    data = (sample_export / "impostor" / "normal.ktx2").read_bytes()
    _, length, _ = ktx2._LEVEL.unpack_from(data, ktx2.HEADER_BYTES)  # the level as stored
    blocks = ktx2.decode_ktx2(data).blocks.tobytes()
    assert length == len(ktx2.zstd_compress(blocks, IMPOSTOR_NORMAL_ZSTD_LEVEL))
    assert length < len(ktx2.zstd_compress(blocks, ktx2.ZSTD_LEVEL))


def test_the_surface_map_is_exported_only_when_asked(sample_bundle, sample_export, tmp_path):
    assert "surface" in json.loads((sample_bundle / "manifest.json").read_text())["impostor"]["maps"]
    assert not (sample_export / "impostor" / "surface.ktx2").exists()
    out = tmp_path / "with_surface"
    assert cli_main(["export", str(sample_bundle), "--out", str(out), "--surface-map"]) == 0
    check_export(sample_bundle, out, surface_map=True)
    assert (out / "impostor" / "surface.ktx2").is_file()


def test_bake_publishes_the_export_beside_the_bundle(sample_bundle, sample_export):
    """`run_bake` (the CLI's bake) with the default export=true writes <out>/../exports/<name>/<version>/,
    the same export `crowdbake export` writes: the same files, byte for byte."""
    from crowdbake.storage.exports import export_home

    home = export_home(sample_bundle.parent.parent, "sample", "1.0")
    index = json.loads((home / "index.json").read_text())
    assert sorted(index["files"]) == sorted(p.relative_to(sample_export).as_posix() for p in sample_export.rglob("*") if p.is_file())
    for path, entry in index["files"].items():
        assert hashlib.sha256((sample_export / path).read_bytes()).hexdigest() == entry["sha256"], path


def test_the_export_zip_is_deflated_as_the_files_are_written(tmp_path):
    """ZipAsWritten: entries in the order the files came, bytes as given, zip's epoch as every date; a zip that
    cannot be written fails at close() without add() ever blocking."""
    import zipfile

    from crowdbake.storage.exports import ZipAsWritten

    files = [("b.bin", np.random.default_rng(0).bytes(5000)), ("a/z.txt", b"z" * 200_000), ("a/empty", b"")]
    zipper = ZipAsWritten(tmp_path / "export.zip", "walker-1.0")
    for path, data in files:
        zipper.add(path, data)
    zipper.close()
    with zipfile.ZipFile(tmp_path / "export.zip") as archive:
        assert archive.namelist() == [f"walker-1.0/{path}" for path, _ in files]
        assert [archive.read(f"walker-1.0/{path}") for path, _ in files] == [data for _, data in files]
        assert {info.date_time for info in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
        assert archive.getinfo("walker-1.0/a/z.txt").compress_size < 2000
    broken = ZipAsWritten(tmp_path / "no such folder" / "export.zip", "walker-1.0")
    for path, data in files * 50:
        broken.add(path, data)
    with pytest.raises(FileNotFoundError):
        broken.close()


def test_the_bake_converts_the_export_layers_while_it_packs(sample_bundle):
    """The pack stage converts every impostor normal and UV layer for the export as it encodes the frame (and the
    poses stage decodes every diffuse layer), keyed
    by the bundle layer's digest, to what the export itself makes of that layer (the byte-for-byte test above
    shows the bake's export, which uses them, is the CLI's, which does not)."""
    from crowdbake.bake.atlas import AtlasLayout
    from crowdbake.bake.map_codecs import uvblock_to_uv32
    from crowdbake.stages.pack import prepared_export_layers

    prepared = prepared_export_layers(sample_bundle.parent.parent.parent / "work")
    bundle = verify_bundle(sample_bundle)
    impostor = bundle.manifest["impostor"]
    normal, uv = (bundle.textures[impostor["maps"][kind]] for kind in ("normal", "uv"))
    assert (normal.pixel_format, uv.pixel_format) == ("bc5", "uvblock")
    assert sorted(prepared.model_normal_bc1) == sorted(layer_digest(layer) for layer in normal.layers)
    assert sorted(prepared.uv32) == sorted(layer_digest(layer) for layer in uv.layers)
    layout = AtlasLayout.from_manifest(impostor)
    for layer in normal.layers:
        decoded = compression.decode(layer, "bc5", normal.width, normal.height)
        assert prepared.model_normal_bc1[layer_digest(layer)] == model_space_normal_bc1(decoded, layout)
    for layer in uv.layers:
        assert np.array_equal(prepared.uv32[layer_digest(layer)], uvblock_to_uv32(layer, uv.width, uv.height))
    # The diffuse layers as the poses stage decoded them: what rgba8_layers decodes without them.
    diffuse = bundle.textures[bundle.manifest["materials"][0]["diffuse"]]
    assert sorted(prepared.rgba8) == sorted(layer_digest(layer) for layer in diffuse.layers)
    assert np.array_equal(rgba8_layers(diffuse, prepared), rgba8_layers(diffuse))


def test_morph_animation_keys_each_frame_once(sample_export):
    gltf = pygltflib.GLTF2.load(sample_export / "character_lod0.glb")
    blob = gltf.binary_blob()
    sampler = gltf.animations[0].samplers[0]
    times = read_accessor(gltf, blob, sampler.input)
    weights = read_accessor(gltf, blob, sampler.output).reshape(len(times), -1)
    frames = len(times) - 1
    np.testing.assert_allclose(times, np.arange(frames + 1) / 24.0, rtol=1e-6)
    # Frame k weighs the targets on its path, its own included; the cycle's end is frame 0 again; a still
    # viewer shows frame 0.
    from crowdbake.export.glb import path_weights

    morphed = [mesh for mesh in gltf.meshes if len(mesh.primitives[0].targets or []) == frames]
    assert morphed
    parents = np.array(morphed[0].extras["crowdbake"]["morph_parents"])
    np.testing.assert_array_equal(weights[:-1], path_weights(parents, np.arange(frames)))
    assert (np.diag(weights[:-1]) == 1).all()
    np.testing.assert_array_equal(weights[-1], weights[0])
    assert all(mesh.weights == path_weights(np.array(mesh.extras["crowdbake"]["morph_parents"]), [0])[0].tolist() for mesh in morphed)
    # Keyed weights (each 0 or 1) are unorm8 and joint rotations snorm16, as glTF allows animation outputs.
    outputs = {channel.target.path: gltf.accessors[animation.samplers[channel.sampler].output]
               for animation in gltf.animations for channel in animation.channels}
    assert outputs["weights"].componentType == pygltflib.UNSIGNED_BYTE and outputs["weights"].normalized
    assert outputs["rotation"].componentType == pygltflib.SHORT and outputs["rotation"].normalized


def test_cli_refuses_a_non_empty_folder_and_a_broken_bundle(sample_bundle, sample_export, tmp_path, capsys):
    assert cli_main(["export", str(sample_bundle), "--out", str(sample_export)]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    broken = tmp_path / "broken"
    shutil.copytree(sample_bundle, broken)
    (broken / "impostor" / "uv.cbtx").write_bytes(b"CBTX")
    assert cli_main(["export", str(broken), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "does not verify" in error and "impostor/uv.cbtx" in error
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- CesiumMan and its skirt


@pytest.mark.slow
def test_cesiumman_export_validates_and_round_trips(tmp_path_factory):
    character = SHARED_ASSETS / "CesiumMan.glb"
    skirt = SHARED_ASSETS / "long_skirt"
    if not (character.is_file() and (skirt / "long_skirt.pc2").is_file()):
        pytest.skip(f"CesiumMan.glb and long_skirt/ not found under {SHARED_ASSETS} (set CROWDBAKE_SHARED_ASSETS)")
    pytest.importorskip("pyrender")
    root = tmp_path_factory.mktemp("cesiumman")
    arguments = [
        "bake", str(character), "--cloth", str(skirt / "long_skirt.pc2"), "--cloth-mesh", str(skirt / "long_skirt.obj"),
        "--name", "cesiumman", "--version", "1.0", "--out", str(root / "bundles"),
        "--frames", "2", "--azimuths", "4", "--elevations", "0", "--tile", "32", "--cycle-views", "3", "--candidates", "2", "--lod-ratio", "0.2",
    ]
    assert cli_main(arguments) == 0
    bundle = root / "bundles" / "cesiumman" / "1.0"
    assert cli_main(["export", str(bundle), "--out", str(root / "export")]) == 0
    check_export(bundle, root / "export")


def test_a_look_is_the_smallest_image_within_the_jpegs_error():
    """look_image: painted colours with blended edges (more than 256 colours) take a 256-colour PNG, smaller
    than the lossless one and the JPEG and no further from the look; a photographic texture takes the JPEG."""
    from PIL import Image

    from crowdbake.export.writer import jpeg_rgb, look_image, rms_levels

    rng = np.random.default_rng(7)
    # Rings of 8 flat colours, their edges blended: several hundred colours, as a painted look's.
    y, x = np.mgrid[0:256, 0:256]
    rings = rng.integers(0, 256, (8, 3)).astype(np.uint8)[(np.hypot(x - 100.0, y - 150.0) // 12).astype(int) % 8]
    painted = cv2.GaussianBlur(rings, (5, 5), 0)
    assert len(np.unique(painted.reshape(-1, 3), axis=0)) > 256
    photo = cv2.GaussianBlur(rng.integers(0, 256, (256, 256, 3)).astype(np.uint8), (3, 3), 0)

    def lossless_png(rgb):
        buffer = io.BytesIO()
        Image.fromarray(rgb).save(buffer, format="PNG")
        return buffer.getvalue()

    for rgb, want_type in ((painted, "image/png"), (photo, "image/jpeg")):
        media_type, data = look_image(rgb)
        seen = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
        jpeg = jpeg_rgb(rgb)
        assert media_type == want_type
        assert rms_levels(seen, rgb) <= rms_levels(np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")), rgb)
        assert len(data) <= min(len(jpeg), len(lossless_png(rgb)))
    media_type, data = look_image(painted)
    assert Image.open(io.BytesIO(data)).mode == "P" and len(data) < len(lossless_png(painted)) / 1.5


def test_looks_are_gltf_variants_with_the_outfit_colours_baked_in(sample_bundle, sample_export):
    """KHR_materials_variants: one variant per diffuse variation, each primitive mapped to a material per
    variant whose base colour is that variation in that outfit (what crowdview draws unlit), variant 0
    also the default; export.json lists them."""
    from PIL import Image

    from crowdbake.export.writer import jpeg_rgb, outfit_look, rms_levels

    bundle = verify_bundle(sample_bundle)
    manifest = bundle.manifest
    sidecar = json.loads((sample_export / "export.json").read_text())
    variations = manifest["materials"][0]["variations"]
    assert [v["variation"] for v in sidecar["variants"]] == list(range(variations))
    assert [v["outfit"] for v in sidecar["variants"]] == [k % manifest["outfits"]["count"] for k in range(variations)]
    diffuse = rgba8_layers(bundle.textures[manifest["materials"][0]["diffuse"]])
    outfit_rows = rgba8_layers(bundle.textures[manifest["outfits"]["file"]])[0]
    for lod in sidecar["lods"]:
        gltf = pygltflib.GLTF2.load(sample_export / lod["glb"])
        assert "KHR_materials_variants" in gltf.extensionsUsed
        names = [v["name"] for v in gltf.extensions["KHR_materials_variants"]["variants"]]
        assert names == [v["name"] for v in sidecar["variants"]]
        for mesh in gltf.meshes:
            primitive = mesh.primitives[0]
            mappings = primitive.extensions["KHR_materials_variants"]["mappings"]
            assert sorted(v for m in mappings for v in m["variants"]) == list(range(variations))
            assert next(m["material"] for m in mappings if m["variants"] == [0]) == primitive.material
            for mapping in mappings[:3]:
                (k,) = mapping["variants"]
                texture = gltf.textures[gltf.materials[mapping["material"]].pbrMetallicRoughness.baseColorTexture.index]
                image = gltf.images[texture.source]
                # One file per look in looks/, shared by the LODs: a PNG (lossless or 256 colours) or a JPEG,
                # never further from the look than the JPEG at LOOK_JPEG_QUALITY.
                assert image.uri.startswith("looks/") and image.uri.endswith((".png", ".jpg")) and image.bufferView is None
                look = np.asarray(Image.open(sample_export / image.uri).convert("RGB"))
                want = outfit_look(diffuse[k], outfit_rows[k % len(outfit_rows)])
                jpeg = np.asarray(Image.open(io.BytesIO(jpeg_rgb(want))).convert("RGB"))
                assert rms_levels(look, want) <= rms_levels(jpeg, want) + 1e-9, (k, rms_levels(look, want), rms_levels(jpeg, want))
    # The looks differ: another variation and another outfit.
    assert not np.array_equal(outfit_look(diffuse[0], outfit_rows[0]), outfit_look(diffuse[1], outfit_rows[1 % len(outfit_rows)]))


def test_blender_imports_the_export_and_plays_the_loop(sample_bundle, sample_export, tmp_path):
    """Blender's own glTF importer (bpy, the crowdbake[alembic] extra) reads every LOD: its `cycle` action
    drives the shape keys to the bundle's frames within 1 mm, and the looks arrive as its variants."""
    import importlib.util
    import sys

    if importlib.util.find_spec("bpy") is None:
        pytest.skip("Blender's bpy module is not installed (pip install 'crowdbake[alembic]')")
    bundle = verify_bundle(sample_bundle)
    sidecar = json.loads((sample_export / "export.json").read_text())
    for lod in sidecar["lods"]:
        out = tmp_path / f"lod{lod['lod']}.npz"
        run = subprocess.run([sys.executable, "-m", "crowdbake.export.blender_round_trip", str(sample_export / lod["glb"]), str(out),
                              "--bundle", str(sample_bundle)],
                             capture_output=True, text=True, timeout=300, cwd=REPO_ROOT, env={**os.environ, "PYTHONPATH": str(REPO_ROOT / "services")})
        assert run.returncode == 0 and out.is_file(), run.stderr[-2000:]
        assert f"Blender plays every animation of LOD {lod['lod']} within 1 mm of the bundle" in run.stdout, run.stdout
        seen = np.load(out)
        info = json.loads(str(seen["info"]))
        assert info["actions"] == ["cycle"]
        assert info["variants"] == [v["name"] for v in sidecar["variants"]]
        for mesh in (m for m in bundle.manifest["meshes"] if m["lod"] == lod["lod"]):
            expected = bundle.pose_caches[mesh["file"]].positions
            played = seen[f"mesh_{mesh['part']}"]
            assert played.shape == expected.shape, (mesh["part"], played.shape, expected.shape)
            assert float(np.abs(played - expected).max()) < 1e-3, mesh["part"]
            assert info["mesh_variants"][mesh["part"]] == list(range(len(sidecar["variants"])))
