"""The two sides of the bundle format agree: crowdview (C++) reads what crowdbake (Python) bakes,
crowdbake verifies what crowdview's test writer makes, and both name the same error for every
broken vector."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from crowdbake.params import BakeParams
from crowdbake.stages.runner import run_bake
from crowdbake.stages.validate import BakeInputs
from crowdbake.formats.binary import decode_texture_array
from crowdbake.formats.bundle import verify_bundle
from crowdbake.formats.errors import FormatError
from repo_paths import vector_expectation

ROOT = Path(__file__).resolve().parents[1]
CROWDVIEW = ROOT / "build" / "runtime" / "crowdview"
SYNTHETIC_WRITER = ROOT / "build" / "runtime" / "tests" / "make_synthetic_bundle"
VECTORS = ROOT / "shared_formats" / "vectors" / "v1"

pytestmark = pytest.mark.skipif(
    not CROWDVIEW.exists(), reason="build/runtime/crowdview is not built (scripts/setup.sh builds it)"
)


def crowdview(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([str(CROWDVIEW), *args], capture_output=True, text=True, timeout=timeout)


def bake_sample(tmp_path_factory, small_sample: Path, folder: str, **params) -> Path:
    """The procedural sample (the session's, generated once) baked by crowdbake with `params` over the small
    defaults below; returns the bundle folder."""
    root = tmp_path_factory.mktemp(folder)
    settings = dict(impostor_frames=2, azimuths=4, elevations_deg=(0.0, 30.0), tile_size=32, lod_triangles=1200, cycle_views=3, candidates=3)
    inputs = BakeInputs(character=small_sample / "character.glb", cloth=small_sample / "cloth.pc2",
                        cloth_mesh=small_sample / "cloth.obj", textures=small_sample / "textures",
                        cycle=None, name="cross", version="1", params=BakeParams(**{**settings, **params}))
    run_bake(inputs, root / "bundles", work=root / "work")
    return root / "bundles" / "cross" / "1"


@pytest.fixture(scope="module")
def python_bundle(tmp_path_factory, small_sample) -> Path:
    """A small bundle baked by crowdbake from the procedural sample."""
    return bake_sample(tmp_path_factory, small_sample, "cross")


@pytest.mark.parametrize("case", sorted(p.name for p in (VECTORS / "bad").iterdir()))
def test_both_readers_name_the_same_error_for_each_broken_vector(case):
    expect = vector_expectation(VECTORS / "bad" / case)
    with pytest.raises(FormatError) as raised:
        verify_bundle(VECTORS / "bad" / case / "bundle")
    result = crowdview("--verify", str(VECTORS / "bad" / case / "bundle"))
    assert result.returncode != 0
    assert raised.value.code == expect["error"]
    assert expect["error"] in result.stdout + result.stderr, result.stdout + result.stderr


def test_crowdview_verifies_and_renders_a_python_baked_bundle(python_bundle, tmp_path):
    verify_bundle(python_bundle)
    assert crowdview("--verify", str(python_bundle)).returncode == 0
    shot = tmp_path / "crowd.png"
    result = crowdview("--bundle", str(python_bundle), "--count", "24", "--headless", "--frames", "3",
                       "--camera", "street", "--width", "320", "--height", "180", "--screenshot", str(shot))
    assert result.returncode == 0, result.stderr
    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=np.int16)
    background = pixels[0, 0]
    covered = np.abs(pixels - background).sum(axis=-1) > 30
    # Two dozen characters at eye level cover a visible share of the frame, not a stray pixel or all of it.
    assert 0.02 < covered.mean() < 0.9, covered.mean()


def test_crowdview_refuses_a_tampered_python_bundle(python_bundle, tmp_path):
    import shutil

    tampered = tmp_path / "tampered"
    shutil.copytree(python_bundle, tampered)
    target = next(p for p in sorted(tampered.rglob("*.cbpc")))
    data = bytearray(target.read_bytes())
    data[-1] ^= 0x55
    target.write_bytes(bytes(data))
    result = crowdview("--verify", str(tampered))
    assert result.returncode != 0
    assert "sha256_mismatch" in result.stdout + result.stderr
    assert target.name in result.stdout + result.stderr


@pytest.mark.skipif(not SYNTHETIC_WRITER.exists(), reason="the runtime's test bundle writer is not built")
def test_python_verifies_the_runtime_test_writers_bundle(tmp_path):
    subprocess.run([str(SYNTHETIC_WRITER), str(tmp_path / "synthetic")], check=True, capture_output=True, timeout=120)
    bundle = verify_bundle(tmp_path / "synthetic")
    assert bundle.pose_caches and bundle.textures


def test_crowdview_renders_a_private_bundle_from_the_service_by_url(python_bundle, tmp_path):
    """A bundle published privately on a real crowdbake server: crowdview fetches it by URL with a key
    (`--key`, sent as a bearer token), verifies and renders it; without the key it gets `unauthorized`
    and exits with a message, and an unknown version is `not_found`, not a manifest error."""
    from crowdbake.storage.bundles import register_bundle
    from crowdbake.storage.db import session_scope
    from service_fixtures import free_port, make_api, service_env, start_api

    api = make_api(tmp_path / "api")
    store = api.client.app.state.services.bundles
    store.publish(python_bundle, "cross", "1")
    with session_scope(api.sessions) as session:
        register_bundle(session, store, "cross", "1", False, None)
    settings = api.client.app.state.services.settings
    port = free_port()
    env = service_env(settings.data_dir, "filesystem://", CROWDBAKE_DATABASE_URL=settings.database_url, CROWDBAKE_SHARED_WORKSPACE="true")
    server = start_api(env, port, tmp_path / "api.log")
    try:
        url = f"http://127.0.0.1:{port}/v1/bundles/cross/1"
        denied = crowdview("--verify", url, "--cache", str(tmp_path / "cache0"))
        # Without a key a private bundle answers exactly as a missing one: nothing says it exists.
        assert denied.returncode != 0 and "not_found" in denied.stderr, denied.stderr
        missing = crowdview("--verify", f"http://127.0.0.1:{port}/v1/bundles/cross/9", "--key", api.keys["read"],
                            "--cache", str(tmp_path / "cache1"))
        assert missing.returncode != 0 and "not_found" in missing.stderr, missing.stderr
        picture = tmp_path / "private.png"
        rendered = crowdview("--url", url, "--key", api.keys["read"], "--cache", str(tmp_path / "cache2"), "--count", "12",
                             "--headless", "--frames", "2", "--width", "320", "--height", "200", "--screenshot", str(picture))
        assert rendered.returncode == 0, rendered.stderr
        assert api.keys["read"] not in rendered.stdout + rendered.stderr + denied.stderr
        pixels = np.asarray(Image.open(picture).convert("RGB"), dtype=np.int16)
        assert pixels.std() > 5, "the picture of the crowd is blank"
    finally:
        server.stop()


def _shot(bundle: Path, out: Path, *extra: str) -> np.ndarray:
    """crowdview's picture of `bundle`: 24 characters seen from above, deterministic placement."""
    result = crowdview("--bundle", str(bundle), "--count", "24", "--headless", "--frames", "1", "--seed", "7",
                       "--camera", "overview", "--width", "480", "--height", "270", "--screenshot", str(out), *extra)
    assert result.returncode == 0, result.stderr
    return np.asarray(Image.open(out).convert("RGB"), dtype=np.int16)


@pytest.fixture(scope="module")
def uv32_bundle(tmp_path_factory, small_sample) -> Path:
    """The python_bundle's bake with the 4-byte uv32 UV map instead of the default uvblock."""
    return bake_sample(tmp_path_factory, small_sample, "cross-uv32", uv_format="uv32")


def test_crowdview_draws_uvblock_impostors_as_uv32_ones_and_near_the_mesh(python_bundle, uv32_bundle, tmp_path):
    """On the GPU path (the shaders' uvblock decode, not the CPU reader): the default 1.5-byte UV map
    draws the same impostors as the 4-byte one, and both stand where the mesh stands."""
    for bundle, expected in ((python_bundle, "uvblock"), (uv32_bundle, "uv32")):
        uv_file = next(f["path"] for f in json.loads((bundle / "manifest.json").read_text())["files"] if f["role"] == "impostor-uv")
        assert decode_texture_array((bundle / uv_file).read_bytes(), "uv map").pixel_format == expected
    block = _shot(python_bundle, tmp_path / "uvblock.png", "--lod", "impostor")
    wide = _shot(uv32_bundle, tmp_path / "uv32.png", "--lod", "impostor")
    mesh = _shot(python_bundle, tmp_path / "mesh.png", "--lod", "low")
    background = mesh[0, 0]

    def covered(picture):
        return np.abs(picture - background).sum(axis=-1) > 30

    assert covered(block).mean() > 0.005, "the impostors are on screen"
    both = covered(block) | covered(wide)
    difference = np.abs(block - wide).sum(axis=-1)[both] / 3
    print(f"\nuvblock vs uv32 impostors: mean |diff| {difference.mean():.2f} over {both.sum()} pixels, "
          f"IoU with the mesh {(covered(block) & covered(mesh)).sum() / (covered(block) | covered(mesh)).sum():.3f}")
    assert difference.mean() < 3.0 and (covered(block) == covered(wide)).mean() > 0.995
    overlap = (covered(block) & covered(mesh)).sum() / (covered(block) | covered(mesh)).sum()
    assert overlap > 0.6, overlap



@pytest.fixture(scope="module")
def views16_bundle(tmp_path_factory, small_sample) -> Path:
    """The sample baked with views 22.5° apart in 3 rings and 4 frames: the spacing reprojection is for
    (the defaults are 32 x 3; with 4 azimuths, 90° apart, halfway is too far for a few fixed-point steps)."""
    return bake_sample(tmp_path_factory, small_sample, "cross-views16", impostor_frames=4, azimuths=16,
                       elevations_deg=(0.0, 20.0, 40.0), tile_size=64)


@pytest.mark.parametrize("camera", ["street", "overview"])
def test_crowdview_reprojected_impostors_stand_nearer_the_mesh_than_plain_blending(views16_bundle, camera, tmp_path):
    """On the GPU path (shaders/impostor_warp.glsl): every character of the crowd is seen between baked
    views and frames; reprojecting each sample with the bundle's surface map puts the impostors'
    silhouettes and colours nearer the mesh's than blending the same samples unmoved."""
    manifest = json.loads((views16_bundle / "manifest.json").read_text())
    assert "surface" in manifest["impostor"]["maps"]

    def shot(name: str, *extra: str) -> np.ndarray:
        out = tmp_path / f"{name}.png"
        result = crowdview("--bundle", str(views16_bundle), "--count", "24", "--headless", "--frames", "1", "--seed", "7",
                           "--camera", camera, "--width", "960", "--height", "540", "--screenshot", str(out), *extra)
        assert result.returncode == 0, result.stderr
        return np.asarray(Image.open(out).convert("RGB"), dtype=np.int16)

    mesh = shot("mesh", "--lod", "high")
    full = shot("full", "--lod", "impostor", "--impostor-blend", "full")
    warped = shot("warp", "--lod", "impostor", "--impostor-blend", "warp")
    background = mesh[0, 0]

    def covered(picture):
        return np.abs(picture - background).sum(axis=-1) > 30

    def iou(picture):
        return (covered(picture) & covered(mesh)).sum() / (covered(picture) | covered(mesh)).sum()

    def difference(picture):
        either = covered(picture) | covered(mesh)
        return float((np.abs(picture - mesh).sum(axis=-1)[either] / 3).mean())

    print(f"\n{camera}, against the mesh: full blend IoU {iou(full):.3f}, mean |diff| {difference(full):.1f}; "
          f"reprojected IoU {iou(warped):.3f}, mean |diff| {difference(warped):.1f}")
    assert iou(warped) > iou(full) + 0.005
    assert difference(warped) < difference(full) - 0.5


def test_crowdview_decodes_bc5_normal_maps_on_the_cpu_as_the_gpu_does(python_bundle, tmp_path):
    """The default bundle's normal map is BC5 (SPEC.md pixel format 7): crowdview's own decoder
    (--cpu-decode, bundle.cpp decode_bc4_block) and the driver's RGTC2 decode light the impostors alike."""
    normal = next(f["path"] for f in json.loads((python_bundle / "manifest.json").read_text())["files"] if f["role"] == "impostor-normal")
    assert decode_texture_array((python_bundle / normal).read_bytes(), "normal map").pixel_format == "bc5"
    gpu = _shot(python_bundle, tmp_path / "gpu.png", "--lod", "impostor")
    cpu = _shot(python_bundle, tmp_path / "cpu.png", "--lod", "impostor", "--cpu-decode")
    difference = np.abs(gpu - cpu).sum(axis=-1) / 3
    print(f"\nbc5 normals, GPU against CPU decode: mean |diff| {difference.mean():.3f}, over 8 levels {(difference > 8).mean():.4f}")
    assert (np.abs(gpu - _shot(python_bundle, tmp_path / "mesh.png", "--lod", "high")).sum(axis=-1) > 30).mean() > 0.005
    assert difference.mean() < 0.5 and (difference > 8).mean() < 0.005


def test_crowdview_draws_the_reprojected_silhouette_the_bake_scores(views16_bundle, tmp_path):
    """One character at the impostor switch distance, halfway between baked azimuths, rings and frames
    (`crowdview --switch-view`): the impostor's silhouette on the GPU is the one crowdbake's numpy copy of
    the shader draws for the same camera and frame (crowdbake.reference.runtime_picture.sample_tile, the
    twin of the shader whose pictures fidelity.json's `runtime` scores), and plainly not the unreprojected
    blend's."""
    from crowdbake.bake import impostor_views, view_blend
    from crowdbake.reference import impostor_blend
    from crowdbake.reference.runtime_picture import AtlasTiles, sample_tile
    from crowdbake.stages.impostors import load_poses
    from crowdbake.stages.runtime_fidelity import halfway_frame

    poses = load_poses(views16_bundle.parents[2] / "work")
    layout = poses.atlas_layout()
    maps = {kind: (views16_bundle / path).read_bytes() for kind, path in json.loads((views16_bundle / "manifest.json").read_text())["impostor"]["maps"].items()}
    size = layout.tile_size
    frame, frames = halfway_frame(poses)
    results = []
    for azimuth, elevation in ((11.25, 10.0), (191.25, 30.0), (303.75, 10.0)):
        view = impostor_views.ortho_view(poses.center, poses.radius, azimuth, elevation, size)
        weights = view_blend.blend_view_weights(azimuth, elevation, layout.azimuths_deg, layout.elevations_deg)

        def drawn(tiles: AtlasTiles) -> np.ndarray:
            samples = [(w, sample_tile(tiles, tile, k, view, frames)) for w, tile, k in impostor_blend.samples_for(weights, frames)]
            # Each sample counts with the part of the pixel its silhouette covers (the surface map's alpha).
            coverage = sum(w * sample.covered * (1.0 if sample.share is None else sample.share) for w, sample in samples)
            # Reprojected edges are soft: opacity over 2 %, which shows at least 2 levels off the sky below
            # (the character's colours differ from the sky's by more than a third).
            return impostor_blend.edge_alpha(coverage, reprojected=tiles.surface_map is not None) > 0.02

        warped = drawn(AtlasTiles(layout, maps["uv"], maps["normal"], maps["surface"], poses.radius))
        plain = drawn(AtlasTiles(layout, maps["uv"], maps["normal"]))
        out = tmp_path / f"switch_{azimuth}.png"
        result = crowdview("--bundle", str(views16_bundle), "--headless", "--frames", "1", "--lod", "impostor", "--width", "256",
                           "--height", "256", "--switch-view", f"{azimuth},{elevation},{frame}", "--screenshot", str(out))
        assert result.returncode == 0, result.stderr
        picture = np.asarray(Image.open(out).convert("RGB"), dtype=np.int16)
        shown = (np.abs(picture - picture[0, 0]) >= 2).any(axis=-1)
        gpu = shown[128 - size // 2:128 + size // 2, 128 - size // 2:128 + size // 2]
        assert gpu.sum() == shown.sum(), "the impostor reaches outside its 1:1 quad"

        def iou(mask: np.ndarray) -> float:
            return float((gpu & mask).sum() / (gpu | mask).sum())

        results.append((azimuth, elevation, iou(warped), iou(plain)))
    print("\nazimuth, elevation, silhouette IoU of crowdview's against numpy's reprojected / plain: " +
          "; ".join(f"{a}, {e}: {w:.3f} / {p:.3f}" for a, e, w, p in results))
    for _, _, warped_iou, plain_iou in results:
        assert warped_iou > 0.95 and warped_iou > plain_iou + 0.05
