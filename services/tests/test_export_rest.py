"""A bundle's engine export as a published artefact: written beside the bundle once
(crowdbake.storage.exports), served by the REST API with the bundle's rules (api/routes/exports.py),
and drawn by the three.js preview the jobs page links to (/ui/preview/).

The REST tests run the real app in process on the good bundle vector; the browser test serves the app
with uvicorn, opens the jobs page in headless Chromium (WebGL on SwiftShader), follows its "Preview
crowd" link and waits for the crowd to be drawn.
"""
from __future__ import annotations

import hashlib
import io
import json
import posixpath
import re
import shutil
import threading
import time
import zipfile
import zlib
from pathlib import Path

import pytest

from service_fixtures import GOOD_BUNDLE, STORES, free_port, make_api, publish_vector_bundle
from crowdbake.errors import ExportConflict
from crowdbake.export import ktx2
from crowdbake.storage.exports import INDEX_NAME, export_home, exports_root, publish_export

UV32_BUNDLE = GOOD_BUNDLE.parents[2] / "v1-uv32" / "good" / "bundle"
PREVIEW_DIR = Path(__file__).resolve().parents[1] / "crowdbake" / "api" / "static" / "preview"


def publish_with_export(api, public=False) -> tuple[str, str]:
    """The good vector published (under its own name and version) with its export, through the app's stores."""
    name, version = publish_vector_bundle(api, public=public)
    api.client.app.state.services.exports.publish(GOOD_BUNDLE)
    return name, version


def export_index(api, name: str, version: str) -> dict:
    return api.client.app.state.services.exports.index(name, version)


@pytest.fixture(params=STORES)
def api(tmp_path, request):
    api = make_api(tmp_path, request.param)
    yield api
    api.client.close()


def test_publish_writes_the_export_beside_the_bundle_once(tmp_path):
    api = make_api(tmp_path)
    name, version = publish_with_export(api)
    home = export_home(api.settings.bundles_dir, name, version)
    assert home == Path(api.settings.bundles_dir).parent / "exports" / name / version
    index = json.loads((home / INDEX_NAME).read_text())
    assert index["bundle"]["name"] == name and index["ktx2"] == "bc"
    for path, entry in index["files"].items():
        data = (home / "export" / path).read_bytes()
        assert entry["size"] == len(data) and entry["sha256"] == hashlib.sha256(data).hexdigest(), path
    # A second publish keeps the first export (same bytes, same mtime) and leaves no staging folder.
    stamp = (home / INDEX_NAME).stat().st_mtime_ns
    assert publish_export(Path(api.settings.bundles_dir) / name / version, Path(api.settings.bundles_dir)) == home
    assert (home / INDEX_NAME).stat().st_mtime_ns == stamp
    assert sorted(p.name for p in exports_root(api.settings.bundles_dir).joinpath(name).iterdir()) == [version]


def test_export_files_are_served_like_bundle_files(api):
    name, version = publish_with_export(api)
    index = export_index(api, name, version)
    base = f"/v1/bundles/{name}/{version}"
    assert api.client.get(base, headers=api.auth("read")).json()["export_url"] == f"{base}/export/"
    for path, entry in index["files"].items():
        response = api.client.get(f"{base}/export/{path}", headers=api.auth("read"))
        assert response.status_code == 200, (path, response.text)
        assert hashlib.sha256(response.content).hexdigest() == entry["sha256"]
        assert response.headers["etag"] == f'"{entry["sha256"]}"'
        assert response.headers["content-type"].startswith(entry["media_type"].split(";")[0])
        assert response.headers["cache-control"] == "private, max-age=31536000, immutable"
    sidecar = api.client.get(f"{base}/export/export.json", headers=api.auth("read"))
    assert sidecar.json()["bundle"] == {"name": name, "version": version}
    # Conditional, range and HEAD requests, as for bundle files.
    etag = sidecar.headers["etag"]
    assert api.client.get(f"{base}/export/export.json", headers={**api.auth("read"), "If-None-Match": etag}).status_code == 304
    partial = api.client.get(f"{base}/export/export.json", headers={**api.auth("read"), "Range": "bytes=0-9"})
    assert partial.status_code == 206 and partial.content == sidecar.content[:10]
    head = api.client.head(f"{base}/export/character_lod0.glb", headers=api.auth("read"))
    assert head.status_code == 200 and head.headers["content-type"] == "model/gltf-binary"
    # 'latest' is resolved once: 307 to the concrete version, as for bundle files.
    latest = api.client.get(f"/v1/bundles/{name}/latest/export/export.json", headers=api.auth("read"), follow_redirects=False)
    assert latest.status_code == 307 and latest.headers["location"] == f"{base}/export/export.json"


def test_export_zip_holds_every_file(api):
    name, version = publish_with_export(api)
    index = export_index(api, name, version)
    response = api.client.get(f"/v1/bundles/{name}/{version}/export.zip", headers=api.auth("read"))
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    assert response.headers["etag"] == f'"{index["zip"]["sha256"]}"' == f'"{hashlib.sha256(response.content).hexdigest()}"'
    assert "attachment" in response.headers["content-disposition"]
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        contents = {info.filename.split("/", 1)[1]: hashlib.sha256(archive.read(info)).hexdigest() for info in archive.infolist()}
        assert {info.filename.split("/", 1)[0] for info in archive.infolist()} == {f"{name}-{version}"}
    assert contents == {path: entry["sha256"] for path, entry in index["files"].items()}


def test_export_builds_are_reproducible_and_a_failed_one_reports_its_own_error(tmp_path):
    """Two builds of one bundle are the same bytes, export.zip and index.json included, and a bundle that
    does not verify fails with its FormatError."""
    from crowdbake.formats.bundle import FormatError
    from crowdbake.storage.exports import build_export, zip_level

    builds = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        build_export(GOOD_BUNDLE, tmp_path / name)
        builds.append({p.relative_to(tmp_path / name).as_posix(): p.read_bytes() for p in sorted((tmp_path / name).rglob("*")) if p.is_file()})
    assert builds[0] == builds[1] and "export.zip" in builds[0]
    # Each entry deflated at its level: the .glb files and text at 6, the already compressed KTX2 files at 1.
    with zipfile.ZipFile(tmp_path / "a" / "export.zip") as archive:
        for info in archive.infolist():
            path = info.filename.split("/", 1)[1]
            deflate = zlib.compressobj(zip_level(path), zlib.DEFLATED, -15)
            data = builds[0][f"export/{path}"]
            assert info.compress_size == len(deflate.compress(data) + deflate.flush()), path
    assert zip_level("character_lod0.glb") == zip_level("export.json") == 6 and zip_level("vat/body.joints.ktx2") == 1
    broken = tmp_path / "broken"
    shutil.copytree(GOOD_BUNDLE, broken)
    victim = next(p for p in sorted(broken.rglob("*")) if p.is_file() and p.name != "manifest.json")
    victim.write_bytes(b"not the listed bytes")
    (tmp_path / "c").mkdir()
    with pytest.raises(FormatError):
        build_export(broken, tmp_path / "c")


def test_export_follows_the_bundles_access_rules_and_says_what_is_missing(api):
    name, version = publish_with_export(api)
    base = f"/v1/bundles/{name}/{version}"
    anonymous = api.client.get(f"{base}/export/export.json")
    assert anonymous.status_code == 404 and anonymous.headers["content-type"] == "application/problem+json"  # private: as if missing
    assert api.client.get(f"{base}/export.zip", headers=api.auth("upload")).status_code == 404  # no read scope: nothing revealed
    missing = api.client.get(f"{base}/export/nope.ktx2", headers=api.auth("read"))
    assert missing.status_code == 404 and "nope.ktx2" in missing.json()["detail"]
    assert api.client.get(f"{base}/export/%2e%2e/manifest.json", headers=api.auth("read")).status_code == 404
    assert api.client.patch(base, json={"public": True}, headers=api.auth("publish")).status_code == 200
    public = api.client.get(f"{base}/export/export.json")
    assert public.status_code == 200 and public.headers["cache-control"].startswith("public, ")
    # A bundle published without an export (bake parameter export=false).
    other, other_version = publish_vector_bundle(api, "no-export", "1.0.0", public=True)
    assert api.client.get(f"/v1/bundles/{other}/{other_version}").json()["export_url"] is None
    none = api.client.get(f"/v1/bundles/{other}/{other_version}/export/export.json")
    assert none.status_code == 404 and "export=false" in none.json()["detail"]
    assert api.client.get(f"/v1/bundles/{other}/{other_version}/export.zip").status_code == 404


def test_bake_parameter_export_reaches_cli_and_rest_alike():
    from crowdbake.api.schemas import BakeParamsIn
    from crowdbake.cli import build_parser
    from crowdbake.params import BakeParams

    assert BakeParams().export is True and BakeParamsIn().export is True
    assert BakeParamsIn(export=False).export is False
    bake = build_parser().parse_args(["bake", "c.glb", "--cloth", "c.pc2", "--cloth-mesh", "c.obj", "--name", "a", "--version", "1", "--out", "o", "--no-export"])
    assert bake.export is False


# ------------------------------------------------------------------------------------ preview page


def import_closure(entry: str) -> set[str]:
    """Every file the preview page loads, starting at `entry` (relative to the preview folder): relative
    imports and bare ones through the page's import map, followed through each file."""
    html = (PREVIEW_DIR / "index.html").read_text()
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1))["imports"]
    seen, todo = set(), [entry]
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        text = (PREVIEW_DIR / path).read_text()
        for specifier in re.findall(r"""^\s*(?:import|export)\b[^'";]*?from\s*['"]([^'"]+)['"]|^\s*import\s*['"]([^'"]+)['"]""", text, re.M):
            specifier = next(s for s in specifier if s)
            if specifier.startswith("."):
                resolved = posixpath.join(posixpath.dirname(path), specifier)
            else:
                prefix = max((k for k in imports if specifier == k or (k.endswith("/") and specifier.startswith(k))), key=len)
                resolved = imports[prefix] + specifier[len(prefix):]
            todo.append(posixpath.normpath(resolved))
    return seen


def test_preview_page_serves_exactly_what_it_imports(local_api):
    api = local_api
    if not (PREVIEW_DIR / "node_modules" / "three").is_dir():
        pytest.skip(f"npm packages missing: run `npm ci` in {PREVIEW_DIR} (scripts/setup.sh does)")
    from crowdbake.api.routes.exports import PREVIEW_FILES

    needed = import_closure("preview.js") | {"index.html"}
    assert needed == set(PREVIEW_FILES), needed ^ set(PREVIEW_FILES)
    for path in sorted(needed):
        response = api.client.get(f"/ui/preview/{path}")
        assert response.status_code == 200, path
        assert response.content == (PREVIEW_DIR / path).read_bytes()
    page = api.client.get("/ui/preview/")
    policy = page.headers["content-security-policy"]
    import_map = re.search(r'<script type="importmap">(.*?)</script>', page.text, re.S).group(1)
    import base64
    assert f"'sha256-{base64.b64encode(hashlib.sha256(import_map.encode()).digest()).decode()}'" in policy
    for path in ("package.json", "node_modules/three/package.json", "tools/read-ktx2.mjs", "../app.js", "node_modules/three/src/Three.js"):
        assert api.client.get(f"/ui/preview/{path}").status_code == 404, path


@pytest.fixture
def local_api(tmp_path):
    api = make_api(tmp_path)
    yield api
    api.client.close()


def test_jobs_page_links_the_preview_and_the_preview_draws_the_crowd(local_api, tmp_path):
    """Headless Chromium: the jobs page lists the bundle with a "Preview crowd" link; following it (same
    tab, so the key stays in sessionStorage) the preview fetches the private export with that key and
    draws the crowd, its BC textures uploaded as S3TC blocks."""
    if not (PREVIEW_DIR / "node_modules" / "three").is_dir():
        pytest.skip(f"npm packages missing: run `npm ci` in {PREVIEW_DIR} (scripts/setup.sh does)")
    from crowdbake.export import devtools as browser_module
    if browser_module.CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    import uvicorn

    from crowdbake.storage.bundles import register_bundle
    from crowdbake.storage.db import session_scope

    api = local_api
    manifest = json.loads((UV32_BUNDLE / "manifest.json").read_text())  # the preview draws uv32 impostors
    name, version = manifest["name"], manifest["version"]
    folder = Path(api.settings.bundles_dir) / name / version
    shutil.copytree(UV32_BUNDLE, folder)
    with session_scope(api.sessions) as session:
        register_bundle(session, api.settings.bundles_dir, name, version, False, None)
    publish_export(folder, Path(api.settings.bundles_dir))

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(api.client.app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        webgl = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader")
        with browser_module.Browser(tmp_path / "profile", arguments=webgl) as browser:
            page = browser.open(f"http://127.0.0.1:{port}/ui#key={api.keys['read']}")
            link = page.wait_for(f"document.querySelector('tr[data-bundle=\"{name}/{version}\"] a.preview-link')?.getAttribute('href')")
            assert link == f"/ui/preview/index.html?export={'%2F'.join(['', 'v1', 'bundles', name, version, 'export', ''])}"
            page.evaluate("document.querySelector('a.preview-link').click()")
            # The status element may not be parsed yet right after the navigation: wait for it and its result.
            state = page.wait_for("location.pathname === '/ui/preview/index.html' && "
                                  "((s) => s && s.dataset.ready !== 'false' ? s.textContent : null)(document.getElementById('status'))", timeout=120)
            status = json.loads(state)
            assert status.get("ready") is True, status
            assert sum(status["lod"].values()) == status["characters"] > 0
            assert status["bundle"] == {"name": name, "version": version}
            assert {ktx2.VK_FORMAT_BC1_RGB_UNORM_BLOCK, ktx2.VK_FORMAT_BC2_SRGB_BLOCK} <= set(status["texture_formats"]), status
    finally:
        server.should_exit = True
        thread.join(timeout=10)


@pytest.mark.parametrize("store", [store for store in STORES if "s3" in str(store)])
def test_an_object_store_export_is_written_once_under_its_index_and_can_redirect(tmp_path, store):
    """On the S3 store as in folders: the index is written last, once (a second publish keeps it), the
    files sit under the index's digest, and with presigned downloads a file answers 307 to the bucket."""
    api = make_api(tmp_path, "s3", s3_redirect_downloads=True)
    name, version = publish_with_export(api)
    exports = api.client.app.state.services.exports
    client, bucket, home = exports.client, exports.bucket, exports.home(name, version)
    stored = client.get_object(Bucket=bucket, Key=home + INDEX_NAME)
    data = stored["Body"].read()
    digest = hashlib.sha256(data).hexdigest()
    keys = {item["Key"] for item in client.list_objects_v2(Bucket=bucket, Prefix=home)["Contents"]}
    index = json.loads(data)
    assert keys == {home + INDEX_NAME, f"{home}{digest}/export.zip"} | {f"{home}{digest}/export/{path}" for path in index["files"]}
    exports.publish(GOOD_BUNDLE)  # kept: the same object, not rewritten
    assert client.head_object(Bucket=bucket, Key=home + INDEX_NAME)["ETag"] == stored["ETag"]
    other = tmp_path / "other-bytes"  # another bundle's bytes under the same name and version: refused
    shutil.copytree(GOOD_BUNDLE, other)
    manifest = json.loads((other / "manifest.json").read_text())
    manifest["created"] = "2001-01-01T00:00:00Z"
    (other / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ExportConflict, match="other bytes"):
        exports.publish(other)
    assert client.head_object(Bucket=bucket, Key=home + INDEX_NAME)["ETag"] == stored["ETag"]
    base = f"/v1/bundles/{name}/{version}"
    redirect = api.client.get(f"{base}/export/export.json", headers=api.auth("read"), follow_redirects=False)
    assert redirect.status_code == 307 and digest in redirect.headers["location"]
    assert redirect.headers["etag"] == f'"{index["files"]["export.json"]["sha256"]}"'
