"""crowdview fetching a bundle over real HTTP: dropped connections resume with Range requests,
servers without Range support are downloaded again, tampered and missing files are refused, a
dripping server meets the deadline, a manifest claiming a huge file meets the cache budget, a
private bundle needs the bearer key (never printed), `latest` is resolved to one version, a
redirect loop ends after a few requests, a trickled manifest (alone or three in a crowd) ends by its
deadline, and a crowd description's archetypes (a published bundle by
name and `latest`, a URL, a missing one) share one cache and a refused one stops alone.

    python3 http_fetch_test.py CROWDVIEW MAKE_SYNTHETIC_BUNDLE

Standard library only. The server lays bundles out as the service does:
bundles/{name}/{version}/manifest.json and bundles/{name}/{version}/files/{path}.
"""
from __future__ import annotations

import http.server
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

BUNDLE_DIR = "bundles/synthetic-walker"
BUNDLE = f"{BUNDLE_DIR}/1.0.0"
KEY = "s3cret-test-key-4711"
DRIP_BYTES_PER_S = 2


class Handler(http.server.BaseHTTPRequestHandler):
    root: Path
    cut_once: set[str] = set()  # paths whose next response stops halfway and drops the connection
    ranges = True               # honour Range requests
    log: list[tuple[str, str | None]] = []
    drip_prefix = "drip/"       # paths under it are sent at DRIP_BYTES_PER_S
    private_prefix = "private/"  # paths under it need "Authorization: Bearer " + KEY
    latest: str = "1.0.0"        # what bundles/<name>/latest/ means; see on_latest_manifest
    on_latest_manifest = None    # called after a latest manifest is sent (a publish in between)

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        path = self.path.lstrip("/")
        Handler.log.append((path, self.headers.get("Range")))
        if path.startswith("v1/"):  # the service's API prefix: /v1/bundles/{name}/{version}/...
            path = path[3:]
        if path.startswith("loop/"):  # redirects to itself, for ever
            self.redirect(path)
            return
        if path.startswith("hops/"):  # hops/N/<rest>: N redirects before <rest> is served
            _, hops, rest = path.split("/", 2)
            if int(hops) > 0:
                self.redirect(f"hops/{int(hops) - 1}/{rest}")
                return
            path = rest
        if path.startswith(self.private_prefix):
            if self.headers.get("Authorization") != f"Bearer {KEY}":
                self.send_error(401)
                return
            path = path[len(self.private_prefix):]
        drip = path.startswith(self.drip_prefix)
        if drip:
            path = path[len(self.drip_prefix):]
        trickle = path.startswith("trickle/")  # trickle/<any>/<rest>: <rest>, manifest included, at DRIP_BYTES_PER_S
        if trickle:
            path = path.split("/", 2)[2]
        latest_manifest = f"{BUNDLE_DIR}/latest/manifest.json"
        is_latest_manifest = path == latest_manifest
        path = path.replace(f"{BUNDLE_DIR}/latest/", f"{BUNDLE_DIR}/{Handler.latest}/")
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
        if is_latest_manifest and Handler.on_latest_manifest:
            Handler.on_latest_manifest()
        if trickle or (drip and not path.endswith("manifest.json")):
            try:
                for i in range(0, len(body), DRIP_BYTES_PER_S):
                    self.wfile.write(body[i:i + DRIP_BYTES_PER_S])
                    self.wfile.flush()
                    time.sleep(1)
            except OSError:  # the client gave up: what the test wants
                pass
            return
        if path in Handler.cut_once:
            Handler.cut_once.discard(path)
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            self.close_connection = True
            self.connection.shutdown(2)  # the client sees a short body: an interrupted download
            return
        self.wfile.write(body)

    def redirect(self, path: str) -> None:
        self.send_response(302)
        self.send_header("Location", "/" + path)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *args) -> None:  # keep test output to the checks
        pass


def run(crowdview: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([crowdview, *args], capture_output=True, text=True, timeout=120)


def check_limits(run, check, crowdview, served: Path, base: str, work: Path) -> None:
    # 6. A server dripping 2 bytes/s: under the stall rule's 1 byte/s floor it would be waited
    #    for for ever; the total deadline ends the fetch, and nothing partial is kept.
    started = time.monotonic()
    result = run(crowdview, "--verify", f"{base}/drip/{BUNDLE}", "--cache", str(work / "cache-drip"), "--timeout", "3")
    elapsed = time.monotonic() - started
    check(result.returncode == 1 and result.stdout.startswith("fetch_failed "), "drip: fetch_failed", result)
    check("deadline" in result.stderr, "drip: the deadline is named", result)
    check(elapsed < 15, f"drip: gave up after {elapsed:.1f} s")
    check(not list((work / "cache-drip" / "partial").glob("*")), "drip: no partial file kept")

    # 7. A manifest claiming a 10^12-byte file is refused before any file is requested, and
    #    nothing is written; with a budget that admits it, no more than the real bytes are
    #    written and the short file is deleted.
    huge = served.parent / "9.9.9"
    shutil.copytree(served, huge)
    manifest = json.loads((huge / "manifest.json").read_text())
    entry = next(f for f in manifest["files"] if f["path"] == "impostor/uv.cbtx")
    entry["size"] = 10**12
    manifest["version"] = "9.9.9"
    (huge / "manifest.json").write_text(json.dumps(manifest))
    Handler.log.clear()
    result = run(crowdview, "--verify", f"{base}/{BUNDLE_DIR}/9.9.9", "--cache", str(work / "cache-huge"))
    check(result.returncode == 1 and result.stdout.strip() == "over_budget manifest.json", "huge manifest: over_budget", result)
    check([p for p, _ in Handler.log] == [f"{BUNDLE_DIR}/9.9.9/manifest.json"], f"huge manifest: nothing else requested: {Handler.log}")
    check(not (work / "cache-huge").exists() or not any(p.is_file() for p in (work / "cache-huge").rglob("*")), "huge manifest: nothing written")
    result = run(crowdview, "--verify", f"{base}/{BUNDLE_DIR}/9.9.9", "--cache", str(work / "cache-huge2"),
                 "--cache-budget-mib", str(2 * 10**6))
    check(result.returncode == 1 and result.stdout.strip() == "size_mismatch impostor/uv.cbtx", "huge file admitted: size_mismatch", result)
    check(not list((work / "cache-huge2" / "partial").glob("*")), "huge file admitted: partial file deleted")
    shutil.rmtree(huge)


def check_manifest_deadlines(run, check, crowdview, base: str, work: Path) -> None:
    # 12. A manifest trickled at 2 bytes/s: it kept a fetch waiting 183 s without --timeout, a crowd of
    #     three such URLs over 600 s. Each ends by its deadline with one line naming it: --timeout for
    #     the whole fetch, --manifest-timeout (default 60 s) for the manifest alone, and one --timeout
    #     for all of a crowd's fetches together (they share one deadline, fetched one after another).
    def timed(*args: str) -> tuple[subprocess.CompletedProcess, float]:
        started = time.monotonic()
        result = run(crowdview, *args, "--cache", str(work / "cache-trickle"), "--headless")
        return result, time.monotonic() - started

    def one_refusal_line(result, what: str, words: str) -> None:
        lines = result.stderr.strip().splitlines()
        check(result.returncode == 1 and len(lines) == 1 and "bundle refused" in lines[0] and words in lines[0], what, result)

    result, elapsed = timed("--url", f"{base}/trickle/0/{BUNDLE}", "--timeout", "3")
    one_refusal_line(result, "trickled manifest, --timeout 3: one line", "total fetch deadline passed (--timeout 3 s")
    check(elapsed < 6, f"trickled manifest, --timeout 3: gave up after {elapsed:.1f} s")
    result, elapsed = timed("--url", f"{base}/trickle/0/{BUNDLE}", "--manifest-timeout", "2")
    one_refusal_line(result, "trickled manifest, no --timeout: one line", "the manifest's deadline of 2 s")
    check(elapsed < 5, f"trickled manifest, no --timeout: gave up after {elapsed:.1f} s")
    crowd = {"crowd_format_version": 1, "archetypes": [
        {"name": f"trickle-{k}", "url": f"{base}/trickle/{k}/{BUNDLE}", "count": 1} for k in range(3)]}
    (work / "trickle-crowd.json").write_text(json.dumps(crowd))
    result, elapsed = timed("--crowd", str(work / "trickle-crowd.json"), "--timeout", "4")
    lines = result.stderr.strip().splitlines()
    check(result.returncode == 1 and all(sum(f"'trickle-{k}'" in line for line in lines) == 1 for k in range(3)),
          "trickled crowd: one line per archetype", result)
    check(all("deadline" in line for line in lines if "bundle refused" in line), "trickled crowd: the deadline is named", result)
    check(elapsed < 7, f"trickled crowd of 3, --timeout 4: gave up after {elapsed:.1f} s (one deadline, not one each)")


def check_redirects(run, check, crowdview, base: str, work: Path) -> None:
    # 10. A redirect loop: before the limit, 2,008 requests in 0.4 s, stopped only by libcurl's cap
    #     on header bytes. Now it ends after kMaxRedirects (5) with a message that says so; a chain
    #     of 3 (more than the service makes) still works, for the manifest and every file.
    Handler.log.clear()
    result = run(crowdview, "--verify", f"{base}/loop/{BUNDLE}", "--cache", str(work / "cache-loop"))
    requests = len(Handler.log)
    check(result.returncode == 1 and result.stdout.strip() == "fetch_failed manifest.json", "redirect loop: fetch_failed", result)
    check("more than 5 redirects" in result.stderr and "/loop/" in result.stderr, "redirect loop: named, with the URL", result)
    check(requests == 6, f"redirect loop: {requests} requests, 1 + 5 redirects")
    result = run(crowdview, "--verify", f"{base}/hops/3/{BUNDLE}", "--cache", str(work / "cache-hops"))
    check(result.returncode == 0 and result.stdout.startswith("OK synthetic-walker"), "3 redirects: fetched", result)
    result = run(crowdview, "--verify", f"{base}/hops/6/{BUNDLE}", "--cache", str(work / "cache-hops6"))
    check(result.returncode == 1 and "more than 5 redirects" in result.stderr, "6 redirects: refused", result)


def check_key(run, check, crowdview, base: str, work: Path) -> None:
    # 8. A private bundle: no key is unauthorized, a wrong key too, the right one (from the
    #    environment or --key) fetches it. The key never appears in anything printed.
    url = f"{base}/private/{BUNDLE}"
    result = run(crowdview, "--verify", url, "--cache", str(work / "cache-key"))
    check(result.returncode == 1 and result.stdout.strip() == "unauthorized manifest.json", "no key: unauthorized", result)
    check("CROWDVIEW_API_KEY" in result.stderr, "no key: says how to give one", result)
    result = run(crowdview, "--verify", url, "--cache", str(work / "cache-key"), "--key", "wrong-" + KEY)
    check(result.returncode == 1 and result.stdout.strip() == "unauthorized manifest.json", "wrong key: unauthorized", result)
    check(KEY not in result.stdout + result.stderr, "wrong key: not printed", result)
    os.environ["CROWDVIEW_API_KEY"] = KEY
    try:
        result = run(crowdview, "--verify", url, "--cache", str(work / "cache-key"))
    finally:
        del os.environ["CROWDVIEW_API_KEY"]
    check(result.returncode == 0 and result.stdout.startswith("OK synthetic-walker"), "key from the environment", result)
    check(KEY not in result.stdout + result.stderr, "key not printed", result)
    result = run(crowdview, "--verify", url, "--cache", str(work / "cache-key2"), "--key", KEY)
    check(result.returncode == 0, "key from --key", result)
    check(KEY not in result.stdout + result.stderr, "--key not printed", result)


def check_latest(run, check, crowdview, served: Path, base: str, work: Path) -> None:
    # 9. `latest` is resolved once: 2.0.0 (other bytes) is published right after the manifest
    #    of 1.0.0 went out; every file still comes from 1.0.0.
    newer = served.parent / "2.0.0"
    shutil.copytree(served, newer)
    manifest = json.loads((newer / "manifest.json").read_text())
    manifest["version"] = "2.0.0"
    (newer / "manifest.json").write_text(json.dumps(manifest))
    victim = newer / "files" / "poses" / "body_lod0.cbpc"
    data = bytearray(victim.read_bytes())
    data[200] ^= 0xFF
    victim.write_bytes(bytes(data))  # what a mixed fetch would get: bytes 1.0.0's manifest refuses
    Handler.latest = "1.0.0"
    Handler.on_latest_manifest = lambda: setattr(Handler, "latest", "2.0.0")
    Handler.log.clear()
    result = run(crowdview, "--verify", f"{base}/{BUNDLE_DIR}/latest", "--cache", str(work / "cache-latest"))
    Handler.on_latest_manifest = None
    check(result.returncode == 0 and result.stdout.startswith("OK synthetic-walker 1.0.0"), "latest: one version", result)
    files = [p for p, _ in Handler.log if "/files/" in p]
    check(files and all(p.startswith(f"{BUNDLE}/files/") for p in files), f"latest: files by the concrete version: {files[:3]}")
    check("latest is 1.0.0" in result.stderr, "latest: the resolution is logged", result)
    Handler.latest = "1.0.0"
    shutil.rmtree(newer)


def check_crowd(run, check, crowdview, base: str, work: Path) -> None:
    # 11. A crowd of three archetypes: one published bundle by name (latest), the same bundle by URL,
    # one missing. The two share the cache (each file fetched once); with --allow-missing the missing one stops alone.
    crowd = {"crowd_format_version": 1, "seed": 3, "archetypes": [
        {"name": "published", "published": {"server": base, "name": "synthetic-walker"}, "count": 3},
        {"name": "by-url", "url": f"{base}/{BUNDLE}", "count": 2},
        {"name": "gone", "published": {"server": base, "name": "no-such-bundle", "version": "1.0.0"}, "count": 2}]}
    (work / "crowd.json").write_text(json.dumps(crowd))
    Handler.log.clear()
    report = work / "crowd-report.json"
    result = run(crowdview, "--crowd", str(work / "crowd.json"), "--allow-missing", "--cache", str(work / "cache-crowd"), "--headless",
                 "--frames", "1", "--width", "64", "--height", "48", "--impostor-blend", "off", "--report", str(report))
    check("archetype 'gone': bundle refused: " in result.stderr and "not_found" in result.stderr, "crowd: the missing archetype is named", result)
    files = [p for p, _ in Handler.log if "/files/" in p]
    check(files and len(files) == len(set(files)), f"crowd: each file fetched once for both archetypes: {len(files)} requests", result)
    check(any(p.startswith("v1/bundles/synthetic-walker/latest/manifest.json") for p, _ in Handler.log), "crowd: latest asked for")
    if result.returncode == 3:  # no OpenGL here: loading was still checked
        return
    check(result.returncode == 0, "crowd: drawn without the missing archetype", result)
    names = [a["name"] for a in json.loads(report.read_text())["archetypes"]] if report.exists() else []
    check(names == ["published", "by-url"], f"crowd: archetypes drawn: {names}", result)


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
        check(result.returncode == 1 and result.stdout.strip() == "not_found manifest.json", "missing bundle is not_found", result)
        check("no bundle at" in result.stderr, "not found says so", result)
        shutil.copy(work / "bundle" / "poses" / "body_lod0.cbpc", victim)  # whole again

        base = f"http://127.0.0.1:{server.server_address[1]}"
        check_limits(run, check, crowdview, served, base, work)
        check_key(run, check, crowdview, base, work)
        check_latest(run, check, crowdview, served, base, work)
        check_redirects(run, check, crowdview, base, work)
        check_manifest_deadlines(run, check, crowdview, base, work)
        check_crowd(run, check, crowdview, base, work)
        server.shutdown()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print("http fetch: all checks passed" if failures == 0 else f"http fetch: {failures} failed")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
