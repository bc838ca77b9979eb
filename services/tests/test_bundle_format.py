"""The Python reader against shared_formats/vectors/v1, v1-uv32, v1-uvblock, v1-hostile, v1-crop, v1-surface and
v2-hostile-fps, which the C++ tests read too."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from crowdbake.formats.binary import (
    decode_pose_cache,
    decode_texture_array,
    encode_pose_cache,
    encode_texture_array,
    layer_size,
)
from crowdbake.formats.texel_codecs import (
    check_uvblock,
    pack_uv32,
    pack_uvblock,
    region_alpha,
    region_codes,
    unpack_uv32,
    unpack_uvblock,
)
from crowdbake.formats.bundle import BundleFile, build_manifest, check_path, verify_bundle, write_bundle
from crowdbake.formats.errors import FormatError
from repo_paths import vector_expectation

REPO_ROOT = Path(__file__).resolve().parents[2]
VECTORS = REPO_ROOT / "shared_formats" / "vectors"

V1 = VECTORS / "v1"
GOOD = V1 / "good" / "bundle"
BAD_CASES = sorted(p.name for p in (V1 / "bad").iterdir())
V1_UV32 = VECTORS / "v1-uv32"
GOOD_UV32 = V1_UV32 / "good" / "bundle"
BAD_CASES_UV32 = sorted(p.name for p in (V1_UV32 / "bad").iterdir())
V1_UVBLOCK = VECTORS / "v1-uvblock"
GOOD_UVBLOCK = V1_UVBLOCK / "good" / "bundle"
BAD_CASES_UVBLOCK = sorted(p.name for p in (V1_UVBLOCK / "bad").iterdir())
V1_CROP = VECTORS / "v1-crop"
BAD_CASES_CROP = sorted(p.name for p in (V1_CROP / "bad").iterdir())
V1_SURFACE = VECTORS / "v1-surface"
BAD_CASES_SURFACE = sorted(p.name for p in (V1_SURFACE / "bad").iterdir())
V1_HOSTILE = VECTORS / "v1-hostile"
BAD_CASES_HOSTILE = sorted(p.name for p in (V1_HOSTILE / "bad").iterdir())
V2_HOSTILE_FPS = VECTORS / "v2-hostile-fps"
BAD_CASES_HOSTILE_FPS = sorted(p.name for p in (V2_HOSTILE_FPS / "bad").iterdir())


def test_good_vector_decodes_to_the_expected_values():
    expected = json.loads((V1 / "good" / "expected.json").read_text())
    bundle = verify_bundle(GOOD)
    assert bundle.manifest["name"] == expected["name"]
    assert set(bundle.pose_caches) == set(expected["pose_caches"])
    for path, want in expected["pose_caches"].items():
        cache = bundle.pose_caches[path]
        assert (cache.vertex_count, cache.triangle_count, cache.frame_count) == (
            want["vertex_count"], want["triangle_count"], want["frame_count"])
        np.testing.assert_array_equal(cache.indices.reshape(-1), want["indices"])
        np.testing.assert_array_equal(cache.positions.reshape(-1), np.float32(want["positions"]))
        np.testing.assert_array_equal(cache.normals.reshape(-1), np.float32(want["normals"]))
        np.testing.assert_array_equal(cache.uvs.reshape(-1), np.float32(want["uvs"]))
    for path, want in expected["textures"].items():
        texture = bundle.textures[path]
        assert (texture.width, texture.height, texture.pixel_format, len(texture.layers)) == (
            want["width"], want["height"], want["pixel_format"], want["layer_count"])
        assert texture.layers[0][:8].hex() == want["first_bytes_hex"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_vector_is_refused_with_its_code_and_file(case):
    expect = vector_expectation(V1 / "bad" / case)
    with pytest.raises(FormatError) as raised:
        verify_bundle(V1 / "bad" / case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"])


@pytest.mark.parametrize("path", sorted(p.relative_to(GOOD).as_posix() for p in GOOD.rglob("*.cb*")))
def test_every_strict_prefix_of_a_binary_is_truncated(path):
    """meshoptimizer-style: no prefix of a valid file may parse or crash."""
    data = (GOOD / path).read_bytes()
    decode = decode_pose_cache if path.endswith(".cbpc") else decode_texture_array
    decode(data, path)
    for length in range(len(data)):
        with pytest.raises(FormatError) as raised:
            decode(data[:length], path)
        assert raised.value.code == "truncated", (length, raised.value)


def test_writer_still_produces_the_committed_vectors(tmp_path):
    """Old vectors are never edited, so the writer must keep producing their exact bytes."""
    spec = importlib.util.spec_from_file_location("gen", REPO_ROOT / "shared_formats" / "generate_vectors_v1.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v1")
    for committed in sorted(V1.rglob("*")):
        if committed.is_file():
            assert (tmp_path / "v1" / committed.relative_to(V1)).read_bytes() == committed.read_bytes(), committed


@pytest.mark.parametrize("path", ["../x", "/abs", "a/../b", "a//b", "a\\b", "./a", "manifest.json", "", "x" * 201, "a b"])
def test_unsafe_paths_are_refused(path):
    with pytest.raises(FormatError) as raised:
        check_path(path)
    assert raised.value.code == "unsafe_path"


def test_region_codes_survive_dxt3_alpha_quantisation():
    codes = np.arange(16)
    alpha = region_alpha(codes)
    four_bit = (alpha >> 4) * 17  # what a DXT3 decoder returns for explicit 4-bit alpha
    np.testing.assert_array_equal(region_codes(four_bit), codes)


def test_write_bundle_refuses_to_overwrite_and_leaves_no_staging(tmp_path):
    files = [BundleFile("cycle/cycle.json", b"{}", "cycle")]
    manifest = {"files": [f.entry() for f in files]}
    write_bundle(tmp_path / "b", manifest, files)
    with pytest.raises(FileExistsError):
        write_bundle(tmp_path / "b", manifest, files)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]


def test_write_bundle_failure_leaves_nothing(tmp_path):
    files = [BundleFile("a.json", b"{}", "cycle")]
    manifest = {"files": [BundleFile("a.json", b"other", "cycle").entry()]}
    with pytest.raises(ValueError):
        write_bundle(tmp_path / "b", manifest, files)
    assert list(tmp_path.iterdir()) == []


def test_encoder_rejects_nan_and_bad_indices():
    indices = np.array([[0, 1, 2]])
    uvs = np.zeros((3, 2))
    positions = np.zeros((1, 3, 3))
    normals = np.tile([0.0, 0.0, 1.0], (1, 3, 1))
    with pytest.raises(ValueError, match="out of range"):
        encode_pose_cache(np.array([[0, 1, 3]]), uvs, positions, normals, 24)
    positions[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        encode_pose_cache(indices, uvs, positions, normals, 24)


def test_build_manifest_refuses_duplicate_and_unsafe_paths():
    with pytest.raises(ValueError):
        build_manifest("n", "1", {}, [BundleFile("a.json", b"", "cycle"), BundleFile("a.json", b"", "cycle")], format_version=1)
    with pytest.raises(FormatError):
        build_manifest("n", "1", {}, [BundleFile("../a.json", b"", "cycle")], format_version=1)


# --- pixel format 5, uv32 (vectors/v1-uv32) ---------------------------------------------------------


def test_uv32_good_vector_decodes_to_the_expected_values():
    expected = json.loads((V1_UV32 / "good" / "expected.json").read_text())
    bundle = verify_bundle(GOOD_UV32)
    assert bundle.manifest["name"] == expected["name"] == "vector-good-uv32"
    for path, want in expected["textures"].items():
        texture = bundle.textures[path]
        assert (texture.width, texture.height, texture.pixel_format, len(texture.layers)) == (
            want["width"], want["height"], want["pixel_format"], want["layer_count"])
        assert texture.layers[0][:8].hex() == want["first_bytes_hex"]
    uv_map = bundle.textures[expected["uv32_texels"]["file"]]
    assert uv_map.pixel_format == "uv32" and len(uv_map.layers[0]) == 4 * uv_map.width * uv_map.height
    texels = expected["uv32_texels"]["texels"]
    assert any(not t["coverage"] for t in texels) and len({t["material"] for t in texels}) >= 4
    for want in texels:
        words = uv_map.texels(want["layer"])
        assert words.shape == (uv_map.height, uv_map.width) and words.dtype == np.uint32
        word = words[want["row"], want["column"]]
        assert int(word) == want["word"]
        u, v, material, coverage = unpack_uv32(word)
        assert (float(u), float(v), int(material), bool(coverage)) == (want["u"], want["v"], want["material"], want["coverage"])
        assert (float(u), float(v)) == (want["u14"] / 16383, want["v14"] / 16383)


@pytest.mark.parametrize("case", BAD_CASES_UV32)
def test_uv32_bad_vector_is_refused_with_its_code_and_file(case):
    expect = json.loads((V1_UV32 / "bad" / case / "expect.json").read_text())
    with pytest.raises(FormatError) as raised:
        verify_bundle(V1_UV32 / "bad" / case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"])


def test_every_strict_prefix_of_a_uv32_texture_is_truncated():
    data = (GOOD_UV32 / "impostor" / "uv.cbtx").read_bytes()
    assert decode_texture_array(data).pixel_format == "uv32"
    for length in range(len(data)):
        with pytest.raises(FormatError) as raised:
            decode_texture_array(data[:length])
        assert raised.value.code == "truncated", (length, raised.value)


def test_writer_still_produces_the_committed_uv32_vectors(tmp_path):
    spec = importlib.util.spec_from_file_location("gen_uv32", REPO_ROOT / "shared_formats" / "generate_vectors_v1_uv32.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v1-uv32")
    committed_files = [p for p in sorted(V1_UV32.rglob("*")) if p.is_file()]
    assert committed_files
    for committed in committed_files:
        assert (tmp_path / "v1-uv32" / committed.relative_to(V1_UV32)).read_bytes() == committed.read_bytes(), committed


def test_uv32_bit_layout_and_round_trip():
    # u in bits 0..13, v in 14..27, material in 28..30, coverage in bit 31 (SPEC.md).
    assert int(pack_uv32(1.0, 0.0, 0, True)) == 0x3FFF | 1 << 31
    assert int(pack_uv32(0.0, 1.0, 0, True)) == 0x3FFF << 14 | 1 << 31
    assert int(pack_uv32(0.0, 0.0, 7, True)) == 7 << 28 | 1 << 31
    assert int(pack_uv32(0.7, 0.2, 5, False)) == 0  # uncovered texels have one encoding
    rng = np.random.default_rng(4)
    u, v = rng.random((2, 16, 8))
    material = rng.integers(0, 8, (16, 8))
    covered = rng.random((16, 8)) < 0.8
    words = pack_uv32(u, v, material, covered)
    assert words.shape == (16, 8) and words.dtype == np.uint32
    du, dv, dm, dc = unpack_uv32(words)
    np.testing.assert_array_equal(dc, covered)
    np.testing.assert_array_equal(dm[covered], material[covered])
    # Half a 14-bit step: 1/32 texel of a 1024² texture.
    assert np.abs(du - u)[covered].max() <= 0.5 / 16383 + 1e-12 and np.abs(dv - v)[covered].max() <= 0.5 / 16383 + 1e-12
    data = encode_texture_array(8, 16, "uv32", words[None])
    assert len(data) == 32 + layer_size("uv32", 8, 16) == 32 + 4 * 8 * 16
    np.testing.assert_array_equal(decode_texture_array(data).texels(0), words)
    with pytest.raises(ValueError):
        pack_uv32(0.5, 0.5, 8, True)
    with pytest.raises(ValueError):
        pack_uv32(np.nan, 0.5, 0, True)


# --- pixel format 6, uvblock (vectors/v1-uvblock) ---------------------------------------------------


def test_uvblock_good_vector_decodes_to_the_expected_values():
    expected = json.loads((V1_UVBLOCK / "good" / "expected.json").read_text())
    bundle = verify_bundle(GOOD_UVBLOCK)
    assert bundle.manifest["name"] == expected["name"] == "vector-good-uvblock"
    uv_map = bundle.textures[expected["uvblock_texels"]["file"]]
    assert uv_map.pixel_format == "uvblock" and len(uv_map.layers[0]) == 24 * (uv_map.width // 4) * (uv_map.height // 4)
    texels = expected["uvblock_texels"]["texels"]
    assert any(not t["coverage"] for t in texels) and {t["material"] for t in texels if t["coverage"]} == {0, 1, 2, 3}
    decoded = [unpack_uvblock(layer, uv_map.width, uv_map.height) for layer in uv_map.layers]
    for want in texels:
        u, v, material, coverage = (array[want["row"], want["column"]] for array in decoded[want["layer"]])
        assert (bool(coverage), int(material)) == (want["coverage"], want["material"])
        assert (float(u), float(v)) == (want["qu"] / 4095, want["qv"] / 4095)


@pytest.mark.parametrize("case", BAD_CASES_UVBLOCK)
def test_uvblock_bad_vector_is_refused_with_its_code_and_file(case):
    expect = json.loads((V1_UVBLOCK / "bad" / case / "expect.json").read_text())
    with pytest.raises(FormatError) as raised:
        verify_bundle(V1_UVBLOCK / "bad" / case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"])


def test_every_strict_prefix_of_a_uvblock_texture_is_truncated():
    data = (GOOD_UVBLOCK / "impostor" / "uv.cbtx").read_bytes()
    assert decode_texture_array(data).pixel_format == "uvblock"
    for length in range(len(data)):
        with pytest.raises(FormatError) as raised:
            decode_texture_array(data[:length])
        assert raised.value.code == "truncated", (length, raised.value)


def test_writer_still_produces_the_committed_uvblock_vectors(tmp_path):
    spec = importlib.util.spec_from_file_location("gen_uvblock", REPO_ROOT / "shared_formats" / "generate_vectors_v1_uvblock.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v1-uvblock")
    committed_files = [p for p in sorted(V1_UVBLOCK.rglob("*")) if p.is_file()]
    assert committed_files
    for committed in committed_files:
        assert (tmp_path / "v1-uvblock" / committed.relative_to(V1_UVBLOCK)).read_bytes() == committed.read_bytes(), committed


def test_uvblock_keeps_coverage_and_material_and_rounds_within_half_a_step():
    """A smooth chart with a seam through it and a second material: coverage and material come back exactly,
    and each coordinate within half a step of the smallest shift that spans its subset (SPEC.md)."""
    rng = np.random.default_rng(5)
    row, column = np.meshgrid(np.arange(16), np.arange(24), indexing="ij")
    u = 0.3 + 0.0021 * column + 0.0007 * row + rng.normal(0, 1e-4, row.shape)
    v = 0.6 - 0.0015 * row + 0.0004 * column
    seam = column > row + 3  # a second UV chart, far away in the texture
    u, v = np.where(seam, u + 0.4, u), np.where(seam, v - 0.5, v)
    material = np.where((row % 7 == 3) & ~seam, 2, 0)  # so a block holds at most three (chart, material) pairs
    covered = rng.random(row.shape) < 0.85
    data = pack_uvblock(u, v, material, covered)
    assert len(data) == layer_size("uvblock", 24, 16) == 24 * 6 * 4
    du, dv, dm, dc = unpack_uvblock(data, 24, 16)
    np.testing.assert_array_equal(dc, covered)
    np.testing.assert_array_equal(dm[covered], material[covered])
    assert (du[~covered] == 0).all() and (dv[~covered] == 0).all()
    # Inside one 4x4 block of one chart the coordinates span under 0.012 (49 steps of 1/4095): a
    # shift of 3 at most, so the error is at most 4/4095, plus the 12-bit grid's half step.
    error = np.maximum(np.abs(du - u), np.abs(dv - v))[covered]
    assert error.max() <= 4.5 / 4095
    with pytest.raises(ValueError):
        pack_uvblock(u, v, np.full(u.shape, 4), covered)  # two bits of material
    four = (column % 4) + 0 * row  # four materials in every block: three subsets cannot keep them
    with pytest.raises(ValueError, match="more than 3 materials"):
        pack_uvblock(u, v, np.clip(four, 0, 3), np.ones_like(covered))


def test_check_uvblock_refuses_exactly_what_unpack_uvblock_refuses():
    """The verifier's uvblock check decodes only blocks whose header bound could pass 4095: on random words
    (most blocks out of range) and on a packed map it refuses a layer exactly when the full decode does."""
    rng = np.random.default_rng(11)
    outcomes = []
    for _ in range(400):
        words = rng.integers(0, 2**32, (4, 6), dtype=np.uint64)
        words[rng.random(4) < 0.3, 0] = 0  # some blocks outside the character
        data = words.astype("<u4").tobytes()
        try:
            unpack_uvblock(data, 8, 8)
            refused = False
        except ValueError:
            refused = True
        if refused:
            with pytest.raises(ValueError, match="above 4095"):
                check_uvblock(data, 8, 8)
        else:
            check_uvblock(data, 8, 8)
        outcomes.append(refused)
    assert any(outcomes) and not all(outcomes)
    row, column = np.meshgrid(np.arange(16), np.arange(24), indexing="ij")
    check_uvblock(pack_uvblock(0.99 + 0.0004 * column, 1.0 - 0.0004 * row, 0 * row, row >= 0), 24, 16)  # near u = v = 1


def test_the_bakes_uvblock_paths_match_their_definitions_on_a_mostly_empty_atlas():
    """map_codecs.uv_map_to_uvblock gathers only the blocks the character touches, and uvblock_to_uv32
    decodes only those: the same bytes as pack_uvblock of decode_uv_map's planes, and the same words as
    pack_uv32 of unpack_uvblock, on a 16-bit atlas with empty blocks, partly covered blocks, two charts,
    three materials and uncovered texels holding stray values (which neither path may read)."""
    from crowdbake.bake.map_codecs import decode_uv_map, uv_map_to_uvblock, uvblock_to_uv32

    rng = np.random.default_rng(17)
    height, width = 32, 48
    row, column = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    covered = ((row - 14) ** 2 / 100 + (column - 20) ** 2 / 150 < 1) & (rng.random(row.shape) < 0.9)
    seam = column > row + 12
    u = np.where(seam, 0.7, 0.2) + 0.002 * column + rng.normal(0, 2e-4, row.shape)
    v = np.where(seam, 0.1, 0.5) + 0.0017 * row
    material = np.where(seam, 0, np.where(row % 9 == 4, 2, 1))
    uv_map = np.zeros((height, width, 4), np.uint16)
    uv_map[..., 0], uv_map[..., 1] = np.rint(np.clip(u, 0, 1) * 65535), np.rint(np.clip(v, 0, 1) * 65535)
    uv_map[..., 2] = np.where(covered, material, rng.integers(0, 65536, row.shape))  # stray material outside
    uv_map[..., 3] = np.where(covered, 65535, rng.integers(0, 32768, row.shape))  # below half: uncovered
    blocks_touched = covered.reshape(height // 4, 4, width // 4, 4).any(axis=(1, 3))
    assert blocks_touched.any() and not blocks_touched.all()

    uv, decoded_material, decoded_covered = decode_uv_map(uv_map)
    np.testing.assert_array_equal(decoded_covered, covered)
    data = uv_map_to_uvblock(uv_map)
    assert data == pack_uvblock(uv[..., 0], uv[..., 1], np.where(covered, decoded_material, 0), covered)
    np.testing.assert_array_equal(uvblock_to_uv32(data, width, height), pack_uv32(*unpack_uvblock(data, width, height)))
    empty = np.zeros_like(uv_map)
    assert uv_map_to_uvblock(empty) == bytes(layer_size("uvblock", width, height))
    assert not uvblock_to_uv32(uv_map_to_uvblock(empty), width, height).any()
    with pytest.raises(ValueError, match="0..3"):
        uv_map_to_uvblock(np.where(covered[..., None], np.array([0, 0, 4, 65535], np.uint16), uv_map))
    with pytest.raises(ValueError, match="multiples of 4"):
        uv_map_to_uvblock(uv_map[:30])


@pytest.mark.parametrize("case", BAD_CASES_HOSTILE)
def test_hostile_manifest_is_refused_like_crowdview_refuses_it(case):
    """Regression (read by crowdview's test_vectors too): a file size of 2^64 - 1 passed the schema here
    and read as 0 in crowdview; a path holding NUL cut crowdview's message short. Both readers now give
    the same code and file, the bad characters escaped."""
    expect = json.loads((V1_HOSTILE / "bad" / case / "expect.json").read_text())
    with pytest.raises(FormatError) as raised:
        verify_bundle(V1_HOSTILE / "bad" / case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"])
    assert "\x00" not in str(raised.value) and "\x1b" not in str(raised.value)
    if expect["error"] == "manifest_invalid":
        assert "at files/0/size" in str(raised.value)


def test_a_path_with_a_trailing_newline_breaks_the_path_rule():
    """`$` matched before a final newline, so "a.cbpc\\n" passed the path rule (fullmatch now)."""
    with pytest.raises(FormatError) as raised:
        check_path("poses/a.cbpc\n")
    assert raised.value.file == "poses/a.cbpc\\x0a"


# --- the impostor crop (vectors/v1-crop) ------------------------------------------------------------


def test_crop_good_vector_reads_as_its_crop():
    from crowdbake.bake.atlas import AtlasLayout

    expected = json.loads((V1_CROP / "good" / "expected.json").read_text())
    bundle = verify_bundle(V1_CROP / "good" / "bundle")
    layout = AtlasLayout.from_manifest(bundle.manifest["impostor"])
    want = expected["crop"]
    assert (layout.tile_size, layout.crop) == (want["tile_size"], (want["x"], want["y"], want["width"], want["height"]))
    uv = bundle.textures[bundle.manifest["impostor"]["maps"]["uv"]]
    assert (uv.width, uv.height) == (layout.width, layout.height)


@pytest.mark.parametrize("case", BAD_CASES_CROP)
def test_crop_bad_vector_is_refused_with_its_code_and_file(case):
    expect = json.loads((V1_CROP / "bad" / case / "expect.json").read_text())
    with pytest.raises(FormatError) as raised:
        verify_bundle(V1_CROP / "bad" / case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"])


def test_writer_still_produces_the_committed_crop_vectors(tmp_path):
    spec = importlib.util.spec_from_file_location("gen_crop", REPO_ROOT / "shared_formats" / "generate_vectors_v1_crop.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v1-crop")
    committed_files = [p for p in sorted(V1_CROP.rglob("*")) if p.is_file()]
    assert committed_files
    for committed in committed_files:
        assert (tmp_path / "v1-crop" / committed.relative_to(V1_CROP)).read_bytes() == committed.read_bytes(), committed


# --- the surface map, bc2 with coverage in alpha (vectors/v1-surface) ------------------------------


def test_surface_good_vector_decodes_to_the_expected_texels():
    """Every texel of the bc2 surface map after BC2 decoding: depth and motion codes from all four palette
    entries, alpha 255 (covered), 17..136 (a share of the texel) and 0 (outside)."""
    from crowdbake.bake.compression import decode

    expected = json.loads((V1_SURFACE / "good" / "expected.json").read_text())
    bundle = verify_bundle(V1_SURFACE / "good" / "bundle")
    want = expected["surface_texels"]
    assert bundle.manifest["impostor"]["maps"]["surface"] == want["file"]
    assert {f["path"]: f["role"] for f in bundle.manifest["files"]}[want["file"]] == "impostor-surface"
    surface = bundle.textures[want["file"]]
    assert surface.pixel_format == want["pixel_format"] == "bc2"
    decoded = np.stack([decode(layer, surface.pixel_format, surface.width, surface.height) for layer in surface.layers])
    assert len(want["texels"]) == decoded.shape[0] * decoded.shape[1] * decoded.shape[2]
    for texel in want["texels"]:
        assert decoded[texel["layer"], texel["y"], texel["x"]].tolist() == [texel[c] for c in "rgba"], texel
    assert {0, 17, 68, 136, 255} == set(decoded[..., 3].reshape(-1).tolist())


@pytest.mark.parametrize("case", BAD_CASES_SURFACE)
def test_surface_bad_vector_is_refused_with_its_code_and_file(case):
    expect = json.loads((V1_SURFACE / "bad" / case / "expect.json").read_text())
    with pytest.raises(FormatError) as raised:
        verify_bundle(V1_SURFACE / "bad" / case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"])


def test_every_strict_prefix_of_the_surface_map_is_truncated():
    path = "impostor/surface.cbtx"
    data = (V1_SURFACE / "good" / "bundle" / path).read_bytes()
    for length in range(len(data)):
        with pytest.raises(FormatError) as raised:
            decode_texture_array(data[:length], path)
        assert raised.value.code == "truncated", length


def test_writer_still_produces_the_committed_surface_vectors(tmp_path):
    spec = importlib.util.spec_from_file_location("gen_surface", REPO_ROOT / "shared_formats" / "generate_vectors_v1_surface.py")
    generator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generator)
    generator.generate(tmp_path / "v1-surface")
    committed_files = [p for p in sorted(V1_SURFACE.rglob("*")) if p.is_file()]
    written_files = [p for p in sorted((tmp_path / "v1-surface").rglob("*")) if p.is_file()]
    assert [p.relative_to(V1_SURFACE) for p in committed_files] == [p.relative_to(tmp_path / "v1-surface") for p in written_files]
    for committed in committed_files:
        assert (tmp_path / "v1-surface" / committed.relative_to(V1_SURFACE)).read_bytes() == committed.read_bytes(), committed


def test_the_largest_frame_rate_allowed_verifies():
    expected = json.loads((V2_HOSTILE_FPS / "good" / "expected.json").read_text())
    bundle = verify_bundle(V2_HOSTILE_FPS / "good" / "bundle")
    assert bundle.manifest["frames_per_second"] == expected["frames_per_second"] == 1000
    assert all(cache.frames_per_second == 1000 for cache in bundle.pose_caches.values())


@pytest.mark.parametrize("case", BAD_CASES_HOSTILE_FPS)
def test_hostile_frame_rate_is_refused_like_crowdview_refuses_it(case):
    """Regression (read by crowdview's test_vectors too): a manifest frames_per_second of 1e300 over pose
    caches at 24 verified in both readers, and every clip then lasted no time at all (a crowd of 20,000
    drew 30 frames in 559 s). The rate must lie in [1, 1000] and match every pose cache's."""
    expect = json.loads((V2_HOSTILE_FPS / "bad" / case / "expect.json").read_text())
    with pytest.raises(FormatError) as raised:
        verify_bundle(V2_HOSTILE_FPS / "bad" / case / "bundle")
    assert (raised.value.code, raised.value.file) == (expect["error"], expect["file"])
    if expect["error"] == "manifest_invalid":
        assert "frames_per_second" in str(raised.value)


def test_generator_still_produces_the_committed_frame_rate_vectors(tmp_path):
    spec = importlib.util.spec_from_file_location("gen_fps", REPO_ROOT / "shared_formats" / "generate_vectors_v2_hostile_fps.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(tmp_path)
    written = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    assert written == sorted(p.relative_to(V2_HOSTILE_FPS) for p in V2_HOSTILE_FPS.rglob("*") if p.is_file())
    assert all((tmp_path / p).read_bytes() == (V2_HOSTILE_FPS / p).read_bytes() for p in written)
