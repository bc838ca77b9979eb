"""The export's three.js crowd preview (services/crowdbake/api/static/preview/) in headless Chromium.

A small bake is exported, served from a local HTTP server beside the preview page, and drawn with
WebGL on SwiftShader. The page mirrors crowdview's crowd (same seed: positions, headings, phases,
variations, outfits), camera and LOD rule, so its screenshot is compared with crowdview's picture of
the same bundle: silhouette coverage (intersection over union) and a colour histogram. Screenshots go
to out/export/.
"""
from __future__ import annotations

import functools
import json
import os
import subprocess
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from websockets.exceptions import ConnectionClosed

from repo_paths import REPO_ROOT
from crowdbake.export import ktx2
from crowdbake.export.devtools import CHROMIUM, Browser
from test_export import PREVIEW_DIR, sample_bundle, sample_export, sample_export_rgba8  # noqa: F401 (module fixtures)

# slow: a real server and worker (or browser) for tens of seconds; scripts/test.sh runs it with CROWDBAKE_SLOW_TESTS=1, as CI does
pytestmark = pytest.mark.slow

CROWDVIEW = Path(os.environ.get("CROWDVIEW", REPO_ROOT / "build" / "runtime" / "crowdview"))
SCREENSHOTS = REPO_ROOT / "out" / "export"
WINDOW = (1280, 720)
CROWDVIEW_TIMEOUT_S = 240
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


# The page's own ready state (#status data-ready), never a fixed wait: software WebGL on a busy machine can
# take minutes to compile shaders and upload textures, and a picture taken before "true" shows "Loading".
READY_TIMEOUT_S = 240
SETTLED = "document.getElementById('status').dataset.ready !== 'false' && document.getElementById('status').dataset.ready"
TWO_FRAMES = "new Promise(done => requestAnimationFrame(() => requestAnimationFrame(() => done(true))))"


def preview_browser(profile: Path) -> Browser:
    """Headless Chromium with WebGL2 on the CPU (SwiftShader), a WINDOW-sized view; skips without Chromium."""
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    return Browser(profile, window=WINDOW, arguments=("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars"))


@pytest.fixture(scope="module")
def chromium(tmp_path_factory):
    with preview_browser(tmp_path_factory.mktemp("profile")) as browser:
        yield browser


def settled_page(browser: Browser, url: str):
    """The page once its status says it is ready (or failed); fails naming the status it was stuck at."""
    page = browser.open(url)
    try:
        page.wait_for(SETTLED, timeout=READY_TIMEOUT_S)
    except AssertionError:
        stuck = page.evaluate("document.getElementById('status').textContent")
        close_tab(page)
        pytest.fail(f"the preview was not ready within {READY_TIMEOUT_S} s; its status said: {stuck!r} ({url})")
    return page


def close_tab(page) -> None:
    """Closes the tab, not only its socket: an open WebGL tab keeps drawing on the CPU."""
    try:
        page.call("Page.close", timeout=10)
    except (ConnectionClosed, TimeoutError):
        pass  # the tab may close its socket before it answers
    finally:
        page.close()


def page_status(browser: Browser, url: str) -> dict:
    """The page's status JSON once it has settled: {"ready": True, ...}, or {"ready": False, "error": text}."""
    page = settled_page(browser, url)
    try:
        state = page.evaluate("document.getElementById('status').dataset.ready")
        text = page.evaluate("document.getElementById('status').textContent")
    finally:
        close_tab(page)
    return json.loads(text) if state == "true" else {"ready": False, "error": text}


def screenshot(browser: Browser, url: str, path: Path) -> np.ndarray:
    """A WINDOW-sized picture of the page, taken after it is ready and has drawn two more frames."""
    page = settled_page(browser, url)
    try:
        assert page.evaluate("document.getElementById('status').dataset.ready") == "true", page.evaluate(
            "document.getElementById('status').textContent")
        # The capture's viewport first, then two frames drawn at that size.
        page.call("Emulation.setDeviceMetricsOverride", width=WINDOW[0], height=WINDOW[1], deviceScaleFactor=1, mobile=False)
        page.evaluate(TWO_FRAMES)
        path.unlink(missing_ok=True)
        page.screenshot(path, width=WINDOW[0], height=WINDOW[1])
    finally:
        close_tab(page)
    return np.asarray(Image.open(path).convert("RGB")).astype(np.int32)


def crowdview_picture(bundle: Path, path: Path, *extra: str) -> np.ndarray:
    if not CROWDVIEW.is_file():
        pytest.skip(f"crowdview is not built at {CROWDVIEW} (scripts/setup.sh builds it; or set CROWDVIEW)")
    result = subprocess.run(
        [str(CROWDVIEW), "--bundle", str(bundle), "--headless", "--count", "100", "--seed", "1", "--screenshot", str(path),
         "--shaders", str(REPO_ROOT / "runtime" / "src" / "shaders"), *extra],
        capture_output=True, text=True, timeout=CROWDVIEW_TIMEOUT_S,
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


def test_preview_draws_the_crowd_with_crowdviews_lod_rule(server, chromium, sample_export):  # noqa: F811
    status = page_status(chromium, f"{server}&time=0&count=100")
    assert status["ready"] is True, status
    assert sum(status["lod"].values()) == 100 and status["bundle"]["name"] == "sample"
    # The page's switch distance is the sidecar's for the same 720-pixel-high view.
    sidecar = json.loads((sample_export / "export.json").read_text())
    assert status["switch_distance_m"] == pytest.approx(sidecar["impostor"]["switch_distance"]["distance_m"], rel=1e-6)
    forced = page_status(chromium, f"{server}&time=0&count=100&lod=impostor")
    assert forced["lod"] == {"high": 0, "low": 0, "impostor": 100}
    # The BC1/BC2 KTX2 files went up as S3TC blocks (SwiftShader has WEBGL_compressed_texture_s3tc).
    assert {ktx2.VK_FORMAT_BC1_RGB_UNORM_BLOCK, ktx2.VK_FORMAT_BC2_SRGB_BLOCK} <= set(status["texture_formats"]), status


def test_bc_and_rgba8_exports_draw_the_same_picture(server, chromium):
    """The blocks the GPU decodes and the texels the exporter decoded are the same texels, so the two
    KTX2 modes give the same screenshot (a few pixels may differ where filtering rounds differently)."""
    rgba8_url = server.replace("export=../export/", "export=../export_rgba8/")
    assert page_status(chromium, f"{rgba8_url}&time=0&count=16")["texture_formats"][0] == ktx2.VK_FORMAT_R8G8B8A8_UNORM
    bc = screenshot(chromium, f"{server}&time=0&count=100", SCREENSHOTS / "preview_bc.png")
    rgba8 = screenshot(chromium, f"{rgba8_url}&time=0&count=100", SCREENSHOTS / "preview_rgba8.png")
    differing = (np.abs(bc - rgba8).sum(axis=-1) > 3).mean()
    (SCREENSHOTS / "compare_bc_rgba8.json").write_text(json.dumps({"differing_pixel_fraction": float(differing), "max_difference": int(np.abs(bc - rgba8).max())}) + "\n")
    assert differing < 0.001, differing


def test_the_docs_picture_command_waits_for_the_page_on_a_cold_first_run(server, chromium, sample_export, tmp_path):  # noqa: F811
    """docs/export.md's picture command starts its own Chromium with a fresh profile (a cold first run)
    and its own server, waits for the page's ready state, and draws what the page draws for a user."""
    import sys

    out = tmp_path / "crowd.png"
    run = subprocess.run([sys.executable, "-m", "crowdbake.export.preview_shot", str(sample_export), str(out), "--count", "100", "--time", "0"],
                         capture_output=True, text=True, timeout=900, cwd=REPO_ROOT, env={**os.environ, "PYTHONPATH": str(REPO_ROOT / "services")})
    assert run.returncode == 0, run.stderr[-2000:]
    assert "preview: Loading" in run.stderr  # the status lines it waited through
    assert json.loads(run.stdout)["picture"] == str(out)
    shot = np.asarray(Image.open(out).convert("RGB")).astype(np.int32)
    reference = screenshot(chromium, f"{server}&time=0&count=100", tmp_path / "reference.png")
    assert shot.shape == reference.shape
    assert (np.abs(shot - reference).sum(axis=-1) > 3).mean() < 0.001
    # Not an export: one line, exit 2, nothing drawn.
    refused = subprocess.run([sys.executable, "-m", "crowdbake.export.preview_shot", str(tmp_path), str(tmp_path / "none.png")],
                             capture_output=True, text=True, timeout=60, cwd=REPO_ROOT, env={**os.environ, "PYTHONPATH": str(REPO_ROOT / "services")})
    assert refused.returncode == 2 and "no export.json" in refused.stderr and not (tmp_path / "none.png").exists()


# The preview draws impostors as the paper does, nearest view and frame: crowdview with blending off.
@pytest.mark.parametrize("mode, crowdview_args", [("auto", ()), ("impostor", ("--lod", "impostor", "--impostor-blend", "off"))])
def test_preview_screenshot_matches_crowdview(server, chromium, sample_bundle, mode, crowdview_args):  # noqa: F811
    preview = screenshot(chromium, f"{server}&time=0&count=100&lod={mode}", SCREENSHOTS / f"preview_{mode}.png")
    covered = characters(preview)
    assert 0.02 < covered.mean() < 0.6, "the crowd should cover part of the picture, not none or all of it"
    reference = crowdview_picture(sample_bundle, SCREENSHOTS / f"crowdview_{mode}.png", *crowdview_args)
    iou, intersection = compare(preview, reference)
    (SCREENSHOTS / f"compare_{mode}.json").write_text(json.dumps({"coverage_iou": iou, "histogram_intersection": intersection}) + "\n")
    assert iou >= MIN_COVERAGE_IOU, iou
    assert intersection >= MIN_HISTOGRAM_INTERSECTION, intersection
