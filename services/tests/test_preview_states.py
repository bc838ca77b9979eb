"""The preview page's loading, empty and error states, in headless Chromium (services/tests/browser.py).

The page once stayed plain blue with no word: its status line sat at left -10000 px, so "loading" and
any error were drawn off-screen. These tests need no bake: a local server holds export.json back (the
page is loading), answers 404 (a missing export) or serves a sidecar with no frames (no animation), and
each time the status line must be inside the viewport, with a size, saying so.
"""
from __future__ import annotations

import functools
import json
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

import pytest

from crowdbake.export.devtools import CHROMIUM, Browser
from repo_paths import REPO_ROOT

PREVIEW_DIR = REPO_ROOT / "services" / "crowdbake" / "api" / "static" / "preview"
HOLD_S = 30  # how long the server keeps the "slow" export.json back; released when the test is done

# The status line's box and text, and whether the box lies wholly inside the window with a non-zero size.
STATUS_JS = """(() => { const s = document.getElementById('status'); const r = s.getBoundingClientRect();
  return {state: s.dataset.ready, text: s.textContent, width: r.width, height: r.height,
          inside: r.width > 0 && r.height > 0 && r.left >= 0 && r.top >= 0 && r.right <= innerWidth && r.bottom <= innerHeight}; })()"""


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    if not (PREVIEW_DIR / "node_modules" / "three").is_dir():
        pytest.skip(f"npm packages missing: run `npm ci` in {PREVIEW_DIR} (scripts/setup.sh does)")
    root = tmp_path_factory.mktemp("www")
    (root / "preview").symlink_to(PREVIEW_DIR, target_is_directory=True)
    (root / "version_4").mkdir()  # an export written before VATs became one file a part
    (root / "version_4" / "export.json").write_text(json.dumps(
        {"format_version": 4, "frame_count": 24, "frames_per_second": 24, "lods": [{"lod": 0}], "impostor": {}, "bundle": {"name": "old"}}))
    (root / "no_animation").mkdir()
    (root / "no_animation" / "export.json").write_text(json.dumps(
        {"frame_count": 0, "frames_per_second": 30, "lods": [], "impostor": None, "bundle": {"name": "still"}}))
    release = threading.Event()

    class Handler(SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            if self.path.startswith("/slow/"):
                release.wait(HOLD_S)
                self.send_error(503)
                return
            super().do_GET()

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(root)))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/preview/index.html"
    release.set()
    httpd.shutdown()


@pytest.fixture(scope="module")
def browser(site, tmp_path_factory):
    with Browser(tmp_path_factory.mktemp("profile"), window=(800, 600)) as b:
        yield b


def status_once(browser, url: str, until: str) -> dict:
    page = browser.open(url)
    try:
        page.wait_for(f"document.getElementById('status').dataset.ready === {json.dumps(until)}", timeout=60)
        return page.evaluate(STATUS_JS)
    finally:
        page.close()


def test_status_line_is_on_screen_while_the_export_loads(site, browser):
    status = status_once(browser, f"{site}?export=../slow/", until="false")
    assert status["inside"], status
    assert "Loading" in status["text"] and "/slow/export.json" in status["text"], status


def test_missing_export_shows_an_error_on_screen(site, browser):
    status = status_once(browser, f"{site}?export=../nowhere/", until="error")
    assert status["inside"], status
    assert "Could not show the export" in status["text"] and "HTTP 404" in status["text"], status


def test_export_without_animation_is_refused_in_words(site, browser):
    status = status_once(browser, f"{site}?export=../no_animation/", until="error")
    assert status["inside"], status
    assert "no animation" in status["text"] and "frame_count 0" in status["text"], status


def test_no_export_parameter_says_how_to_give_one(site, browser):
    """The default used to be ../export/, which under /ui/preview/ is a 404: now the page says what to add."""
    status = status_once(browser, site, until="empty")
    assert status["inside"], status
    assert "?export=" in status["text"], status


def test_an_export_older_than_the_page_reads_is_refused_in_words(site, browser):
    """An export.json of format version 4 names its VATs as position and normal files; the page says to
    export again rather than fail on a missing file."""
    status = status_once(browser, f"{site}?export=../version_4/", until="error")
    assert status["inside"], status
    assert "format version 4" in status["text"] and "export the bundle again" in status["text"], status
