"""The export's three.js crowd preview (services/crowdbake/api/static/preview/) in headless Chromium.

A small bake is exported, served from a local HTTP server beside the preview page, and drawn with
WebGL on SwiftShader. The page mirrors crowdview's crowd (same seed: positions, headings, phases,
variations, outfits), camera and LOD rule, so its screenshot is compared with crowdview's picture of
the same bundle: silhouette coverage (intersection over union) and a colour histogram. Screenshots go
to out/export/.
"""
from __future__ import annotations

import functools
import html
import json
import os
import re
import shutil
import subprocess
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from repo_paths import REPO_ROOT
from crowdbake.export import ktx2
from test_export import PREVIEW_DIR, sample_bundle, sample_export, sample_export_rgba8  # noqa: F401 (module fixtures)

# slow: a real server and worker (or browser) for tens of seconds; scripts/test.sh runs it with CROWDBAKE_SLOW_TESTS=1, as CI does
pytestmark = pytest.mark.slow

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CROWDVIEW = Path(os.environ.get("CROWDVIEW", REPO_ROOT / "build" / "runtime" / "crowdview"))
SCREENSHOTS = REPO_ROOT / "out" / "export"
# Virtual time the page may use; Chromium pauses it while requests are in flight, and an idle page
# spends it at once, so a generous budget costs no wall-clock time once the crowd is drawn.
VIRTUAL_TIME_BUDGET_MS = 300_000
CHROMIUM_TIMEOUT_S = 240
# Loose agreement with crowdview: the same characters stand in the same places (measured on the
# sample: coverage IoU 0.97, histogram intersection 0.98), but filtering and rasterisers differ.
MIN_COVERAGE_IOU = 0.85
MIN_HISTOGRAM_INTERSECTION = 0.75
SKY_DIFFERENCE = 12  # summed RGB difference from the corner (sky) pixel that counts as "a character"


@pytest.fixture(scope="module")
def server(sample_export, sample_export_rgba8, tmp_path_factory):  # noqa: F811
    if not (PREVIEW_DIR / "node_modules" / "three").is_dir():
        pytest.skip(f"npm packages missing: run `npm ci` in {PREVIEW_DIR} (scripts/setup.sh does)")
    root = tmp_path_factory.mktemp("www")
    (root / "preview").symlink_to(PREVIEW_DIR, target_is_directory=True)
    (root / "export").symlink_to(sample_export, target_is_directory=True)
    (root / "export_rgba8").symlink_to(sample_export_rgba8, target_is_directory=True)

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(root)))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/preview/index.html?export=../export/"
    httpd.shutdown()


def run_chromium(*arguments: str, profile: Path) -> subprocess.CompletedProcess:
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    command = [
        CHROMIUM, "--headless", "--no-sandbox", "--no-first-run", "--disable-dev-shm-usage",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader",  # WebGL2 on the CPU
        f"--user-data-dir={profile}", f"--virtual-time-budget={VIRTUAL_TIME_BUDGET_MS}", *arguments,
    ]
    return subprocess.run(command, capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S)


def page_status(url: str, profile: Path, attempts: int = 3) -> dict:
    """The page's status JSON once it has loaded. Work that holds no request open (shader compiles, texture
    uploads) does not pause Chromium's virtual time, so on a busy machine the DOM can be dumped while the
    page still says "loading": then it is asked again, with a fresh profile."""
    for attempt in range(attempts):
        result = run_chromium("--dump-dom", url, profile=profile.with_name(f"{profile.name}-{attempt}"))
        match = re.search(r'<pre id="status" data-ready="(\w+)"[^>]*>(.*?)</pre>', result.stdout, re.S)
        assert match, result.stderr[-2000:]
        state, text = match.group(1), html.unescape(match.group(2))
        if state in ("error", "empty"):
            return {"ready": False, "error": text}
        if state == "true":
            return json.loads(text)
    pytest.fail(f"the preview still said 'loading' after {attempts} tries: {url}")


def screenshot(url: str, path: Path, profile: Path) -> np.ndarray:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)
    result = run_chromium(f"--screenshot={path}", "--window-size=1280,720", "--hide-scrollbars", url, profile=profile)
    assert result.returncode == 0 and path.is_file(), result.stderr[-2000:]
    return np.asarray(Image.open(path).convert("RGB")).astype(np.int32)


def crowdview_picture(bundle: Path, path: Path, *extra: str) -> np.ndarray:
    if not CROWDVIEW.is_file():
        pytest.skip(f"crowdview is not built at {CROWDVIEW} (scripts/setup.sh builds it; or set CROWDVIEW)")
    result = subprocess.run(
        [str(CROWDVIEW), "--bundle", str(bundle), "--headless", "--count", "100", "--seed", "1", "--screenshot", str(path),
         "--shaders", str(REPO_ROOT / "runtime" / "src" / "shaders"), *extra],
        capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S,
    )
    if result.returncode != 0:
        pytest.skip(f"crowdview could not draw here: {result.stderr.strip()[-300:]}")
    return np.asarray(Image.open(path).convert("RGB")).astype(np.int32)


def characters(picture: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that differ from the sky (the corner pixel)."""
    return np.abs(picture - picture[0, 0]).sum(axis=-1) > SKY_DIFFERENCE


def colour_histogram(picture: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Normalised 8x8x8 RGB histogram of the masked pixels."""
    bins = picture[mask] // 32
    counts = np.bincount(bins[:, 0] * 64 + bins[:, 1] * 8 + bins[:, 2], minlength=512).astype(np.float64)
    return counts / max(counts.sum(), 1.0)


def compare(preview: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    a, b = characters(preview), characters(reference)
    iou = float((a & b).sum() / max((a | b).sum(), 1))
    intersection = float(np.minimum(colour_histogram(preview, a), colour_histogram(reference, b)).sum())
    return iou, intersection


def test_preview_draws_the_crowd_with_crowdviews_lod_rule(server, sample_export, tmp_path):  # noqa: F811
    status = page_status(f"{server}&time=0&count=100", tmp_path / "profile")
    assert status["ready"] is True, status
    assert sum(status["lod"].values()) == 100 and status["bundle"]["name"] == "sample"
    # The page's switch distance is the sidecar's for the same 720-pixel-high view.
    sidecar = json.loads((sample_export / "export.json").read_text())
    assert status["switch_distance_m"] == pytest.approx(sidecar["impostor"]["switch_distance"]["distance_m"], rel=1e-6)
    forced = page_status(f"{server}&time=0&count=100&lod=impostor", tmp_path / "profile2")
    assert forced["lod"] == {"high": 0, "low": 0, "impostor": 100}
    # The BC1/BC2 KTX2 files went up as S3TC blocks (SwiftShader has WEBGL_compressed_texture_s3tc).
    assert {ktx2.VK_FORMAT_BC1_RGB_UNORM_BLOCK, ktx2.VK_FORMAT_BC2_SRGB_BLOCK} <= set(status["texture_formats"]), status


def test_bc_and_rgba8_exports_draw_the_same_picture(server, tmp_path):
    """The blocks the GPU decodes and the texels the exporter decoded are the same texels, so the two
    KTX2 modes give the same screenshot (a few pixels may differ where filtering rounds differently)."""
    rgba8_url = server.replace("export=../export/", "export=../export_rgba8/")
    assert page_status(f"{rgba8_url}&time=0&count=16", tmp_path / "profile")["texture_formats"][0] == ktx2.VK_FORMAT_R8G8B8A8_UNORM
    bc = screenshot(f"{server}&time=0&count=100", SCREENSHOTS / "preview_bc.png", tmp_path / "profile_bc")
    rgba8 = screenshot(f"{rgba8_url}&time=0&count=100", SCREENSHOTS / "preview_rgba8.png", tmp_path / "profile_rgba8")
    differing = (np.abs(bc - rgba8).sum(axis=-1) > 3).mean()
    (SCREENSHOTS / "compare_bc_rgba8.json").write_text(json.dumps({"differing_pixel_fraction": float(differing), "max_difference": int(np.abs(bc - rgba8).max())}) + "\n")
    assert differing < 0.001, differing


# The preview draws impostors as the paper does, nearest view and frame: crowdview with blending off.
@pytest.mark.parametrize("mode, crowdview_args", [("auto", ()), ("impostor", ("--lod", "impostor", "--impostor-blend", "off"))])
def test_preview_screenshot_matches_crowdview(server, sample_bundle, tmp_path, mode, crowdview_args):  # noqa: F811
    preview = screenshot(f"{server}&time=0&count=100&lod={mode}", SCREENSHOTS / f"preview_{mode}.png", tmp_path / "profile")
    covered = characters(preview)
    assert 0.02 < covered.mean() < 0.6, "the crowd should cover part of the picture, not none or all of it"
    reference = crowdview_picture(sample_bundle, SCREENSHOTS / f"crowdview_{mode}.png", *crowdview_args)
    iou, intersection = compare(preview, reference)
    (SCREENSHOTS / f"compare_{mode}.json").write_text(json.dumps({"coverage_iou": iou, "histogram_intersection": intersection}) + "\n")
    assert iou >= MIN_COVERAGE_IOU, iou
    assert intersection >= MIN_HISTOGRAM_INTERSECTION, intersection
