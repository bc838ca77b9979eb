"""Headless Chromium driven through the DevTools protocol (websockets; no browser download): evaluate
script, wait for a condition, set a file input's files, drop files from disk on an element, allow
downloads into a folder, take a screenshot. crowdbake.export.preview_shot takes the preview page's
pictures with it; the web page's tests click through the page with it.

    with Browser(profile_dir) as browser:
        page = browser.open("http://127.0.0.1:8000/ui")
        page.wait_for("document.querySelector('#jobs-table tbody tr') !== null")
"""
from __future__ import annotations

import base64
import contextlib
import itertools
import json
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import httpx
from websockets.sync.client import connect

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
START_TIMEOUT_S = 30


class DevToolsError(RuntimeError):
    pass


class Session:
    """One websocket to a DevTools target; `call` sends a command and returns its result."""

    def __init__(self, url: str):
        self.stack = contextlib.ExitStack()
        self.socket = self.stack.enter_context(connect(url, max_size=None, open_timeout=START_TIMEOUT_S))
        self.ids = itertools.count(1)

    def call(self, method: str, timeout: float = 60, **params: Any) -> dict[str, Any]:
        message_id = next(self.ids)
        self.socket.send(json.dumps({"id": message_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            message = json.loads(self.socket.recv(timeout=max(deadline - time.monotonic(), 0.01)))
            if message.get("id") == message_id:  # events (no id) and older answers are skipped
                if "error" in message:
                    raise DevToolsError(f"{method}: {message['error']}")
                return message.get("result", {})

    def close(self) -> None:
        self.stack.close()


class Page(Session):
    def evaluate(self, expression: str, timeout: float = 60) -> Any:
        """The value of a JavaScript expression (promises awaited), or DevToolsError with its exception."""
        result = self.call("Runtime.evaluate", timeout=timeout, expression=expression, awaitPromise=True, returnByValue=True)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise DevToolsError(f"{expression[:80]}: {details.get('exception', {}).get('description', details.get('text'))}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 60, interval: float = 0.2) -> Any:
        """Evaluate until the expression is truthy; its value. AssertionError with the last value on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.evaluate(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"not true within {timeout} s: {expression} (last value {value!r})")
            time.sleep(interval)

    def set_files(self, selector: str, paths: list[Path]) -> None:
        """Choose files in an <input type=file> as a user would (its change event fires)."""
        root = self.call("DOM.getDocument", depth=0)["root"]["nodeId"]
        node = self.call("DOM.querySelector", nodeId=root, selector=selector)["nodeId"]
        if not node:
            raise DevToolsError(f"no element {selector}")
        self.call("DOM.setFileInputFiles", nodeId=node, files=[str(path) for path in paths])

    def drop_files(self, selector: str, paths: list[Path]) -> None:
        """Drag files from disk onto the middle of an element and drop them, as from a desktop (real File
        objects with their bytes; the page's drop handler runs)."""
        box = self.evaluate(f"(() => {{ const node = document.querySelector({json.dumps(selector)}); node.scrollIntoView({{block: 'center'}}); "
                            "const r = node.getBoundingClientRect(); return {x: r.left + r.width / 2, y: r.top + r.height / 2}; })()")
        data = {"items": [], "files": [str(path) for path in paths], "dragOperationsMask": 1}  # 1: copy
        for kind in ("dragEnter", "dragOver", "drop"):
            self.call("Input.dispatchDragEvent", type=kind, x=box["x"], y=box["y"], data=data)

    def screenshot(self, path: Path, selector: str | None = None, width: int = 1280, height: int = 1500) -> None:
        """A PNG of the page's top (width x height), or of the element `selector` (at most `height` tall)."""
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        params: dict[str, Any] = {"format": "png"}
        if selector is not None:
            box = self.evaluate(f"(() => {{ const r = document.querySelector({json.dumps(selector)}).getBoundingClientRect(); "
                                "return {x: r.left + scrollX, y: r.top + scrollY, width: r.width, height: r.height}; })()")
            params.update(captureBeyondViewport=True, clip={"x": box["x"], "y": box["y"], "width": min(box["width"], width),
                                                            "height": min(box["height"], height), "scale": 1})
        data = self.call("Page.captureScreenshot", **params)["data"]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(base64.b64decode(data))


class Browser:
    def __init__(self, profile: Path, window: tuple[int, int] = (1280, 1600), arguments: tuple[str, ...] = ()):
        if CHROMIUM is None:
            raise FileNotFoundError("chromium is not installed (scripts/apt-packages.txt lists it)")
        self.profile = profile
        self.window = window
        self.arguments = tuple(arguments)  # extra Chromium switches (e.g. WebGL on SwiftShader)
        self.process: subprocess.Popen | None = None
        self.port = 0

    def __enter__(self) -> "Browser":
        self.profile.mkdir(parents=True, exist_ok=True)
        command = [CHROMIUM, "--headless", "--disable-gpu", "--no-sandbox", "--no-first-run", "--disable-dev-shm-usage",
                   f"--user-data-dir={self.profile}", "--remote-debugging-port=0", "--remote-allow-origins=*",
                   f"--window-size={self.window[0]},{self.window[1]}", *self.arguments, "about:blank"]
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = self.profile / "DevToolsActivePort"  # Chromium writes the port it chose here
        deadline = time.monotonic() + START_TIMEOUT_S
        while not (port_file.is_file() and port_file.read_text().strip()):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise DevToolsError("chromium did not start its DevTools endpoint")
            time.sleep(0.1)
        self.port = int(port_file.read_text().splitlines()[0])
        self.browser = Session(httpx.get(f"http://127.0.0.1:{self.port}/json/version", timeout=10).json()["webSocketDebuggerUrl"])
        return self

    def allow_downloads(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.browser.call("Browser.setDownloadBehavior", behavior="allow", downloadPath=str(folder))

    def open(self, url: str) -> Page:
        target = httpx.put(f"http://127.0.0.1:{self.port}/json/new?about:blank", timeout=10).json()
        page = Page(target["webSocketDebuggerUrl"])
        page.call("Page.enable")
        page.call("Page.navigate", url=url)
        page.wait_for(f"location.href.startsWith({json.dumps(url.split('#')[0])}) && document.readyState === 'complete'")
        return page

    def __exit__(self, *exc) -> None:
        try:
            self.browser.close()
        finally:
            if self.process is not None and self.process.poll() is None:
                self.process.terminate()
                try:
                    self.process.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
