"""Impostor fidelity (crowdbake.bake.fidelity): the impostor a runtime reconstructs from the baked maps
must reproduce the mesh rendered at 1:1 texel-to-pixel."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import compression, fidelity, shading
from crowdbake.reference import mesh_reference
from crowdbake.bake import impostor_views
from crowdbake.reference import impostor_maps as maps
from crowdbake.formats.texel_codecs import region_alpha

pytest.importorskip("pyrender")
from crowdbake.reference.triangle_ids import TriangleIdRenderer  # noqa: E402
from shapes import uv_sphere  # noqa: E402

# Thresholds for a textured sphere at 64² (measured: SSIM 0.979 / PSNR 33.5 dB with exact normals,
# 0.973 / 33.2 dB with the normal map through DXT1); the silhouette's anti-aliasing is most of what remains.
SSIM_EXACT = 0.95
PSNR_EXACT_DB = 30.0
SSIM_DXT1 = 0.93
SIZE = 64


def patterned_texture(size: int = 128) -> np.ndarray:
    """Stripes and regions: detail the impostor must carry through its UV map."""
    v, u = (np.mgrid[0:size, 0:size] + 0.5) / size
    texture = np.zeros((size, size, 4), dtype=np.uint8)
    texture[..., 0] = np.rint(140 + 90 * np.sin(12 * np.pi * u))
    texture[..., 1] = np.rint(120 + 100 * (np.floor(8 * v) % 2))
    texture[..., 2] = np.rint(100 + 60 * np.cos(2 * np.pi * u))
    texture[..., 3] = region_alpha(np.where(v > 0.6, 3, 0))
    return texture


OUTFIT = np.full((16, 4), 255, dtype=np.uint8)
OUTFIT[3] = (60, 200, 90, 255)


@pytest.fixture(scope="module")
def sphere():
    positions, normals, uvs, faces = uv_sphere()
    return positions, normals, uvs, faces, np.zeros(len(faces), int), [patterned_texture()]


def bake_view(scene, azimuth: float, elevation: float):
    positions, normals, uvs, faces, material, diffuse = scene
    view = impostor_views.ortho_view((0, 0, 0), 0.6, azimuth, elevation, SIZE)
    with TriangleIdRenderer(SIZE) as renderer:
        renderer.set_mesh(positions, faces)
        coverage = renderer.coverage(view, positions, faces)
    return maps.view_maps(view, coverage, positions, normals, uvs, faces, material, diffuse)


def reference(scene, azimuth: float, elevation: float, supersample: int = mesh_reference.DEFAULT_SUPERSAMPLE):
    positions, normals, uvs, faces, material, diffuse = scene
    view = impostor_views.ortho_view((0, 0, 0), 0.6, azimuth, elevation, SIZE * supersample)
    with TriangleIdRenderer(view.size) as renderer:
        renderer.set_mesh(positions, faces)
        coverage = renderer.coverage(view, positions, faces)
    light = shading.camera_light(view)
    return mesh_reference.mesh_reference(view, coverage, supersample, positions, normals, uvs, faces, material, diffuse, OUTFIT, light), light


def test_impostor_reproduces_the_mesh_render(sphere):
    baked = bake_view(sphere, 40.0, 15.0)
    mesh, light = reference(sphere, 40.0, 15.0)
    exact = fidelity.impostor_image(baked.uv, baked.normal, sphere[5], OUTFIT, light)
    score = fidelity.compare(mesh, exact)
    assert score["ssim"] >= SSIM_EXACT and score["psnr_db"] >= PSNR_EXACT_DB
    decoded = compression.decode_bc1(compression.encode_bc1(baked.normal), SIZE, SIZE)
    compressed = fidelity.compare(mesh, fidelity.impostor_image(baked.uv, decoded, sphere[5], OUTFIT, light))
    assert compressed["ssim"] >= SSIM_DXT1
    assert compressed["ssim"] <= score["ssim"] + 1e-9  # compression cannot make it more faithful


def test_impostor_images_of_one_tile_equal_the_picture_of_each_normal_map(sphere):
    """impostor_images samples the diffuse once and decodes only the covered texels' normals: each picture is
    the whole-tile picture (decode_normal_map of the whole map, lit where covered) to the bit."""
    from crowdbake.bake import map_codecs

    baked = bake_view(sphere, 40.0, 15.0)
    _, light = reference(sphere, 40.0, 15.0)
    decoded = compression.decode_bc1(compression.encode_bc1(baked.normal), SIZE, SIZE)
    pictures = fidelity.impostor_images(baked.uv, [baked.normal, decoded], sphere[5], OUTFIT, light)
    uv, material, covered = map_codecs.decode_uv_map(baked.uv)
    albedo = shading.apply_outfit(shading.texels_at(uv[covered], np.clip(material[covered], 0, len(sphere[5]) - 1), sphere[5]), OUTFIT)
    for picture, normal_map in zip(pictures, (baked.normal, decoded)):
        whole = np.zeros_like(picture)
        whole[covered] = shading.lambert(albedo, map_codecs.decode_normal_map(normal_map)[covered], light)
        assert np.array_equal(picture, whole)
    assert not np.array_equal(*pictures)  # the two normal maps light it differently
    assert np.array_equal(pictures[0], fidelity.impostor_image(baked.uv, baked.normal, sphere[5], OUTFIT, light))


def test_a_wrong_impostor_is_caught(sphere):
    """The metric must notice a broken UV map (v flipped) and a view from the wrong angle."""
    baked = bake_view(sphere, 40.0, 15.0)
    mesh, light = reference(sphere, 40.0, 15.0)
    good = fidelity.compare(mesh, fidelity.impostor_image(baked.uv, baked.normal, sphere[5], OUTFIT, light))
    flipped = baked.uv.copy()
    covered = flipped[..., 3] > 0
    flipped[..., 1][covered] = 65535 - flipped[..., 1][covered]
    broken = fidelity.compare(mesh, fidelity.impostor_image(flipped, baked.normal, sphere[5], OUTFIT, light))
    assert broken["ssim"] < good["ssim"] - 0.1
    # The nearest-view error: the mesh 11.25° away from the baked view (half a 16-view step).
    between, light_between = reference(sphere, 51.25, 15.0)
    shifted = fidelity.compare(between, fidelity.impostor_image(baked.uv, baked.normal, sphere[5], OUTFIT, light_between))
    assert shifted["ssim"] < good["ssim"]


def test_compare_and_summary():
    image = np.zeros((16, 16, 3))
    image[4:12, 4:12] = 0.5
    same = fidelity.compare(image, image)
    assert same["ssim"] == pytest.approx(1.0) and same["psnr_db"] == float("inf")
    other = image.copy()
    other[6:8, 6:8] = 1.0
    worse = fidelity.compare(image, other)
    assert worse["ssim"] < 1.0 and np.isfinite(worse["psnr_db"])
    summary = fidelity.summarize([same, worse])
    assert summary["ssim_worst"] == worse["ssim"] and summary["psnr_db_mean"] == worse["psnr_db"]
    # The box: lit pixels plus the margin, not the empty frame.
    rows, columns = fidelity.measure_box(image)
    assert (rows.start, rows.stop) == (4 - fidelity.MEASURE_MARGIN_PX, 12 + fidelity.MEASURE_MARGIN_PX)


def test_outfit_colours_follow_the_region_codes():
    texels = np.array([[200, 100, 50, 0], [200, 100, 50, 51], [255, 255, 255, 17 * 15]], dtype=np.float64)
    outfit = np.zeros((16, 4), dtype=np.uint8)
    outfit[3] = (255, 0, 128, 255)
    outfit[15] = (10, 20, 30, 255)
    rgb = shading.apply_outfit(texels, outfit)
    np.testing.assert_allclose(rgb[0], [200 / 255, 100 / 255, 50 / 255])  # region 0 keeps its colour
    np.testing.assert_allclose(rgb[1], [200 / 255, 0, 50 / 255 * 128 / 255])
    np.testing.assert_allclose(rgb[2], [10 / 255, 20 / 255, 30 / 255])
    lit = shading.lambert(np.ones((2, 3)), np.array([[0, 0, 1.0], [0, 0, -1.0]]), np.array([0, 0, 1.0]))
    np.testing.assert_allclose(lit[:, 0], [shading.AMBIENT + shading.DIFFUSE, shading.AMBIENT])


def test_uv_precision_shows_why_the_uv_map_keeps_14_bits(sphere):
    baked = bake_view(sphere, 0.0, 0.0)
    precision = fidelity.uv_precision(baked.uv, 1024)
    assert precision["rgba16"]["max_texels"] < 0.01
    # uv32: 14 bits a coordinate re-rounded from 16, within 1/16 texel of a 1024² texture.
    assert precision["rgba16"]["max_texels"] < precision["uv32"]["max_texels"] <= 1024 * (0.5 / 16383 + 0.5 / 65535) + 1e-9
    assert precision["uv32"]["max_texels"] < 1.0 / 16
    # 8 bits per coordinate: half a step of 1/255 is two texels of a 1024² texture.
    assert 1.0 < precision["rgba8"]["max_texels"] <= 0.5 / 255 * 1024 + 1e-6
    assert precision["bc1"]["max_texels"] >= precision["rgba8"]["max_texels"]


def test_uv_precision_measures_uvblock_against_the_lookup_footprint(sphere):
    """The lookup's footprint at 1:1 is several diffuse texels (a 1024² texture over a small sphere), and
    uvblock's rounding stays well within one footprint on a smooth chart."""
    baked = bake_view(sphere, 0.0, 0.0)
    size = baked.uv.shape[0]
    precision = fidelity.uv_precision(baked.uv, 1024, size)
    assert precision["lookup_footprint_texels"]["median"] > 1.0
    assert precision["uvblock"]["max_texels"] > precision["uv32"]["max_texels"]
    assert precision["uvblock_error_footprints"]["p99"] < 0.5


def test_ssim_and_psnr_are_scikit_images():
    """compare's SSIM (OpenCV box filter) and PSNR are scikit-image's structural_similarity (defaults,
    data range 1) and peak_signal_noise_ratio, on images of the measured sizes, and they move with the error."""
    metrics = pytest.importorskip("skimage.metrics")
    rng = np.random.default_rng(4)
    scores = []
    for shape, window in (((100, 90, 3), 7), ((40, 33, 3), 7), ((7, 9, 3), 7), ((5, 6, 3), 5)):
        a = rng.random(shape)
        for noise in (0.02, 0.2):
            b = np.clip(a + rng.normal(0, noise, shape), 0, 1)
            want = metrics.structural_similarity(a, b, channel_axis=2, data_range=1.0, win_size=window)
            assert fidelity.ssim(a, b, window) == pytest.approx(want, abs=1e-12)
            scores.append(want)
    a = rng.random((64, 64, 3))
    a[:2] = 0  # measure_box keeps the whole image where both have content
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    got = fidelity.compare(a, b)
    rows, columns = fidelity.measure_box(a, b)
    assert got["psnr_db"] == pytest.approx(metrics.peak_signal_noise_ratio(a[rows, columns], b[rows, columns], data_range=1.0), rel=1e-12)
    assert got["ssim"] == pytest.approx(metrics.structural_similarity(a[rows, columns], b[rows, columns], channel_axis=2, data_range=1.0, win_size=7), abs=1e-12)
    assert fidelity.compare(a, a)["psnr_db"] == float("inf") and fidelity.compare(a, a)["ssim"] == pytest.approx(1.0)
    assert min(scores[1::2]) < max(scores[0::2])  # more noise, lower SSIM
