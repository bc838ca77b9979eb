"""crowdview fetching a bundle over real HTTP: dropped connections resume with Range requests,
servers without Range support are downloaded again, tampered and missing files are refused.

    python3 http_fetch_test.py CROWDVIEW MAKE_SYNTHETIC_BUNDLE

Standard library only. The server lays bundles out as the service does:
bundles/{name}/{version}/manifest.json and bundles/{name}/{version}/files/{path}.
"""
from __future__ import annotations

import http.server
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

BUNDLE = "bundles/synthetic-walker/1.0.0"


class Handler(http.server.BaseHTTPRequestHandler):
    root: Path
    cut_once: set[str] = set()  # paths whose next response stops halfway and drops the connection
    ranges = True               # honour Range requests
    log: list[tuple[str, str | None]] = []

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        path = self.path.lstrip("/")
        Handler.log.append((path, self.headers.get("Range")))
        file = self.root / path
        if not file.is_file():
            self.send_error(404)
            return
        data = file.read_bytes()
        start = 0
        header = self.headers.get("Range")
        if header and self.ranges and header.startswith("bytes=") and header.endswith("-"):
            start = int(header[6:-1])
            if start >= len(data):
                self.send_error(416)
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            self.send_response(200)
        body = data[start:]
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if path in Handler.cut_once:
            Handler.cut_once.discard(path)
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            self.close_connection = True
            self.connection.shutdown(2)  # the client sees a short body: an interrupted download
            return
        self.wfile.write(body)

    def log_message(self, *args) -> None:  # keep test output to the checks
        pass


def run(crowdview: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([crowdview, *args], capture_output=True, text=True, timeout=120)


def main() -> int:
    crowdview, make_bundle = sys.argv[1], sys.argv[2]
    work = Path(tempfile.mkdtemp(prefix="crowdview-http-"))
    failures = 0

    def check(condition: bool, what: str, result: subprocess.CompletedProcess | None = None) -> None:
        nonlocal failures
        if not condition:
            failures += 1
            detail = f"\n  stdout: {result.stdout.strip()}\n  stderr: {result.stderr.strip()}" if result else ""
            print(f"FAILED: {what}{detail}")

    try:
        subprocess.run([make_bundle, str(work / "bundle")], check=True, capture_output=True)
        served = work / "srv" / BUNDLE
        (served / "files").mkdir(parents=True)
        shutil.copy(work / "bundle" / "manifest.json", served / "manifest.json")
        for file in (work / "bundle").rglob("*"):
            if file.is_file() and file.name != "manifest.json":
                target = served / "files" / file.relative_to(work / "bundle")
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy(file, target)
        Handler.root = work / "srv"
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        url = f"http://127.0.0.1:{server.server_address[1]}/{BUNDLE}"
        big = f"{BUNDLE}/files/impostor/uv.cbtx"

        # 1. The connection drops halfway through the biggest file: resumed with a Range request.
        Handler.cut_once = {big}
        result = run(crowdview, "--verify", url, "--cache", str(work / "cache"))
        check(result.returncode == 0 and result.stdout.startswith("OK synthetic-walker"), "fetch with a dropped connection", result)
        requests = [r for p, r in Handler.log if p == big]
        check(len(requests) == 2 and requests[0] is None and (requests[1] or "").startswith("bytes="),
              f"resumed with Range: {requests}")
        check("resuming impostor/uv.cbtx" in result.stderr, "resume is logged", result)

        # 2. Everything now comes from the cache: only the manifest is requested.
        Handler.log.clear()
        result = run(crowdview, "--verify", url, "--cache", str(work / "cache"))
        check(result.returncode == 0 and [p for p, _ in Handler.log] == [f"{BUNDLE}/manifest.json"], f"cache hit: {Handler.log}", result)

        # 3. A server without Range support: the resume is refused, the file downloaded again.
        Handler.ranges = False
        Handler.cut_once = {big}
        result = run(crowdview, "--verify", url, "--cache", str(work / "cache-norange"))
        check(result.returncode == 0 and result.stdout.startswith("OK"), "fetch without Range support", result)
        Handler.ranges = True

        # 4. A tampered file is refused by name and kept out of the cache.
        victim = served / "files" / "poses" / "body_lod0.cbpc"
        data = bytearray(victim.read_bytes())
        data[200] ^= 0xFF
        victim.write_bytes(bytes(data))
        result = run(crowdview, "--verify", url, "--cache", str(work / "cache-tampered"))
        check(result.returncode == 1 and result.stdout.strip() == "sha256_mismatch poses/body_lod0.cbpc", "tampered file", result)
        check("poses/body_lod0.cbpc" in result.stderr, "error names the file", result)
        check(not list((work / "cache-tampered" / "partial").glob("*")), "no bad partial kept")

        # 5. A missing file, and a missing bundle.
        victim.unlink()
        result = run(crowdview, "--verify", url, "--cache", str(work / "cache-missing"))
        check(result.returncode == 1 and result.stdout.strip() == "missing_file poses/body_lod0.cbpc", "missing file", result)
        result = run(crowdview, "--verify", url + "-nope", "--cache", str(work / "cache-missing"))
        check(result.returncode == 1 and result.stdout.strip() == "manifest_invalid manifest.json", "missing bundle", result)
        server.shutdown()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print("http fetch: all checks passed" if failures == 0 else f"http fetch: {failures} failed")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
