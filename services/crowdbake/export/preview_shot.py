"""A picture of an export's crowd as the preview page draws it, taken once the page says it is ready.

    python -m crowdbake.export.preview_shot EXPORT_DIR OUT.png [--count 100] [--time 0] [--lod auto]

Serves the preview page (`crowdbake/api/static/preview`) and the export folder on a private loopback
port, opens the page in headless Chromium (WebGL2 on the CPU, SwiftShader) with a fresh profile, and
waits for the page's own ready state (its status line's `data-ready`), never for a fixed time: a cold
first run (Chromium's first start, shaders compiled, textures decoded on the CPU) takes what it takes.
While it waits it prints each status line the page shows. Then two more frames are drawn and the
picture is written.

Exit 0 with the picture; 1 when the page reports an error or is not ready within `--timeout`
(one line naming the page's last status); 2 for a usage error (a folder that is not an export).
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import json
import shutil
import sys
import tempfile
import threading
import time
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlencode

PREVIEW_DIR = Path(__file__).resolve().parents[1] / "api" / "static" / "preview"
# The page's status element (preview.js showStatus): data-ready "false" while loading, then "true" once
# drawn (its text: the figures, as JSON), "empty" or "error" (its text says why).
SETTLED = "document.getElementById('status').dataset.ready !== 'false'"
READY = "document.getElementById('status').dataset.ready"
STATUS_TEXT = "document.getElementById('status').textContent"
TWO_FRAMES = "new Promise(done => requestAnimationFrame(() => requestAnimationFrame(() => done(true))))"
# Chromium's WebGL2 on the CPU: the page needs WebGL2 and a headless machine has no GPU.
CHROMIUM_ARGUMENTS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars")
STATUS_POLL_S = 0.5


class _QuietHandler(SimpleHTTPRequestHandler):
    def log_message(self, *_args) -> None:  # one line per file would bury the status lines
        pass


@contextlib.contextmanager
def serve_export(export_dir: Path):
    """A loopback HTTP server holding `preview/` (the page) and `export/` (the export); yields its base URL."""
    with tempfile.TemporaryDirectory(prefix="crowdbake-preview-") as root:
        (Path(root) / "preview").symlink_to(PREVIEW_DIR, target_is_directory=True)
        (Path(root) / "export").symlink_to(export_dir.resolve(), target_is_directory=True)
        httpd = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=root))
        thread = threading.Thread(target=httpd.serve_forever, daemon=True)
        thread.start()
        try:
            yield f"http://127.0.0.1:{httpd.server_address[1]}"
        finally:
            httpd.shutdown()
            httpd.server_close()


def page_query(count: int, time_s: float | None, lod: str, seed: int, size: tuple[int, int]) -> str:
    """The preview page's query string (docs/export.md lists the parameters)."""
    query = {"export": "../export/", "count": count, "seed": seed, "lod": lod, "width": size[0], "height": size[1]}
    if time_s is not None:
        query["time"] = time_s
    return urlencode(query)


def wait_until_settled(page, timeout_s: float, say=print) -> tuple[bool, str]:
    """Poll the page's status until it is ready or failed; (ready, last status text). `say` gets each
    new status text. TimeoutError with the last text when it does neither within `timeout_s`."""
    deadline, shown = time.monotonic() + timeout_s, None
    while True:
        text = page.evaluate(STATUS_TEXT) or ""
        settled = page.evaluate(SETTLED)
        if text != shown and not settled:
            say(text)
            shown = text
        if settled:
            return page.evaluate(READY) == "true", page.evaluate(STATUS_TEXT) or ""
        if time.monotonic() > deadline:
            raise TimeoutError(text)
        time.sleep(STATUS_POLL_S)


@contextlib.contextmanager
def chromium_profile(settle_s: float = 5.0):
    """A fresh Chromium profile folder, removed afterwards; the removal retries for up to `settle_s` while
    Chromium's helper processes finish writing into it, then leaves what is left (a temporary folder)."""
    folder = tempfile.mkdtemp(prefix="crowdbake-chromium-")
    try:
        yield folder
    finally:
        deadline = time.monotonic() + settle_s
        while True:
            try:
                shutil.rmtree(folder)
                break
            except FileNotFoundError:
                break
            except OSError:
                if time.monotonic() > deadline:
                    shutil.rmtree(folder, ignore_errors=True)
                    break
                time.sleep(0.2)


def take(export_dir: Path, out: Path, count: int, time_s: float | None, lod: str, seed: int, size: tuple[int, int], timeout_s: float,
         say=print) -> None:
    """Serve, open, wait, and write the picture to `out` (PNG). RuntimeError with one line when the page
    fails or does not settle in time."""
    from crowdbake.export.devtools import Browser

    # Chromium's helpers outlive its main process by a moment and still write into the profile: its removal
    # retries (chromium_profile) rather than failing a picture that was taken.
    with serve_export(export_dir) as base, chromium_profile() as profile:
        with Browser(Path(profile), window=size, arguments=CHROMIUM_ARGUMENTS) as browser:
            page = browser.open(f"{base}/preview/index.html?{page_query(count, time_s, lod, seed, size)}")
            try:
                ready, status = wait_until_settled(page, timeout_s, say)
            except TimeoutError as stuck:
                raise RuntimeError(f"the preview was not ready within {timeout_s:g} s; its status said: {stuck}") from None
            if not ready:
                raise RuntimeError(f"the preview could not draw the export: {status}")
            page.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1, mobile=False)
            page.evaluate(TWO_FRAMES)
            page.screenshot(out, width=size[0], height=size[1])
            page.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m crowdbake.export.preview_shot", description=__doc__.splitlines()[0])
    parser.add_argument("export", type=Path, help="an export folder (holds export.json)")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--count", type=int, default=100, help="characters (default 100)")
    parser.add_argument("--time", type=float, default=0.0, help="seconds into the animation, one still frame (default 0)")
    parser.add_argument("--lod", choices=("auto", "high", "low", "impostor"), default="auto")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT (default 1280x720)")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds to wait for the page to be ready (default 600)")
    arguments = parser.parse_args(argv)
    try:
        width, height = (int(value) for value in arguments.size.lower().split("x"))
    except ValueError:
        parser.error(f"--size {arguments.size!r}: expected WIDTHxHEIGHT, e.g. 1280x720")
    if not (arguments.export / "export.json").is_file():
        parser.error(f"{arguments.export} is not an export folder (no export.json); `crowdbake export BUNDLE --out DIR` makes one")
    if arguments.count < 1:
        parser.error("--count must be at least 1")
    arguments.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        take(arguments.export, arguments.out, arguments.count, arguments.time, arguments.lod, arguments.seed, (width, height),
             arguments.timeout, say=lambda text: print(f"preview: {text}", file=sys.stderr, flush=True))
    except (RuntimeError, FileNotFoundError) as error:
        print(f"preview_shot: {error}", file=sys.stderr)
        return 1
    print(json.dumps({"picture": str(arguments.out), "export": str(arguments.export), "count": arguments.count}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
