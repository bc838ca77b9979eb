"""The web page (GET /ui) and what it shows: the cycle report of a bake, impostor atlas previews and
bundle versions, in headless Chromium against a real service with a finished bake.

The previews are checked against independent decodes of the published CBTX files (BC1 with
texture2ddecoder, the 16-bit UV map from the raw texels), so a PNG that merely looks plausible would
not pass. The browser test reads the DOM after the page's scripts ran (--dump-dom with a virtual time
budget) and writes a screenshot to out/ui/.
"""
from __future__ import annotations

import html
import io
import re
import shutil
import subprocess
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from baked_service import NAME, baked_service
from sample_fixtures import SMALL_SAMPLE
from crowdbake.formats.binary import decode_texture_array
from crowdbake.formats.texel_codecs import unpack_uvblock
from service_fixtures import REPO_ROOT, make_api, publish_vector_bundle

SCREENSHOTS = REPO_ROOT / "out" / "ui"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
# Virtual time the page gets to poll, fetch the report and decode a preview (Chromium pauses virtual
# time while requests are in flight, so this is time the page's timers see, not a wall-clock wait).
VIRTUAL_TIME_BUDGET_MS = 8000
CHROMIUM_TIMEOUT_S = 90


def png(response: httpx.Response) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    return np.asarray(Image.open(io.BytesIO(response.content)).convert("RGBA"))


# ----------------------------------------------------------------------- page and previews, no worker


@pytest.fixture
def api(tmp_path):
    return make_api(tmp_path)


def test_page_and_its_files_are_served_with_a_strict_policy(api):
    page = api.client.get("/ui")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    policy = page.headers["content-security-policy"]
    assert "script-src 'self'" in policy and "connect-src 'self'" in policy and "frame-ancestors 'none'" in policy
    for name in re.findall(r'(?:src|href)="/ui/static/([^"]+)"', page.text):
        assert api.client.get(f"/ui/static/{name}").status_code == 200, name
    assert api.client.get("/", follow_redirects=False).headers["location"] == "/ui"
    for bad in ("..%2Fapp.py", "index.html", "%2e%2e%2froutes%2fweb.py", "app.js.map"):
        response = api.client.get(f"/ui/static/{bad}")
        assert response.status_code == 404 and response.headers["content-type"] == "application/problem+json", bad


def test_uv_preview_is_u_red_v_green_and_transparent_where_uncovered(api):
    name, version = publish_vector_bundle(api)
    folder = Path(api.settings.bundles_dir) / name / version
    uv = decode_texture_array((folder / "impostor" / "uv.cbtx").read_bytes())
    for layer in range(len(uv.layers)):
        picture = png(api.client.get(f"/v1/bundles/{name}/{version}/preview/uv?frame={layer}", headers=api.auth("read")))
        texels = uv.texels(layer)
        assert picture.shape == (uv.height, uv.width, 4)
        covered = texels[..., 3] > 0
        assert covered.any()  # (the vector covers every texel; the baked bundle below has both)
        np.testing.assert_array_equal(picture[..., 0][covered], (texels[..., 0] >> 8)[covered])
        np.testing.assert_array_equal(picture[..., 1][covered], (texels[..., 1] >> 8)[covered])
        assert (picture[..., 3][covered] == 255).all() and (picture[..., 3][~covered] == 0).all()


def test_preview_views_and_errors(api):
    name, version = publish_vector_bundle(api)
    read = api.auth("read")
    base = f"/v1/bundles/{name}/{version}/preview"
    whole = png(api.client.get(f"{base}/normal", headers=read))
    tile = png(api.client.get(f"{base}/normal?azimuth=1&elevation=0", headers=read))
    np.testing.assert_array_equal(tile, whole[0:4, 4:8])  # tile (a=1, e=0) of 4² texels: columns 4..8
    column = png(api.client.get(f"{base}/detail?azimuth=0", headers=read))
    assert column.shape == (4, 4, 4)
    out_of_range = api.client.get(f"{base}/uv?frame=2", headers=read)
    assert out_of_range.status_code == 422 and out_of_range.json()["errors"][0]["field"] == "frame"
    assert api.client.get(f"{base}/uv?azimuth=2", headers=read).status_code == 422
    assert api.client.get(f"{base}/albedo", headers=read).status_code == 422
    assert api.client.get(f"{base}/uv").status_code == 404  # private bundle, no key: as if missing
    assert api.client.get(f"/v1/bundles/{name}/9.9.9/preview/uv", headers=read).status_code == 404
    first = api.client.get(f"{base}/uv", headers=read)
    assert "immutable" in first.headers["cache-control"]
    again = api.client.get(f"{base}/uv", headers={**read, "If-None-Match": first.headers["etag"]})
    assert again.status_code == 304 and again.content == b""


# --------------------------------------------------------------------------- with a finished bake


@pytest.fixture(scope="module")
def service(tmp_path_factory, small_sample):
    with baked_service(tmp_path_factory.mktemp("web"), small_sample) as running:
        yield running


@pytest.mark.slow  # tens of seconds; runs in CI (CROWDBAKE_SLOW_TESTS=1)
def test_cycle_report_of_a_bake_is_served_with_its_plots(service):
    bake_id = service.bake["id"]
    with service.client() as client:
        report = client.get(f"/v1/bakes/{bake_id}/cycle/report.html")
        assert report.status_code == 200 and report.headers["content-type"].startswith("text/html")
        assert "sandbox" in report.headers["content-security-policy"]
        images = re.findall(r'<img src="([^"]+)"', report.text)
        assert "pass1.png" in images
        for image in images:
            picture = client.get(f"/v1/bakes/{bake_id}/cycle/{image}")
            assert picture.status_code == 200 and picture.content.startswith(b"\x89PNG"), image
        cycle = client.get(f"/v1/bakes/{bake_id}/cycle/cycle.json").json()
        assert cycle["cycle_frames"] == SMALL_SAMPLE["cycle_frames"] and cycle["files"]["report"] == "report.html"
        for bad in ("stage.json", "../job.json", "..%2Fjob.json", "edges/../looped.pc2", "looped.pc2"):
            response = client.get(f"/v1/bakes/{bake_id}/cycle/{bad}")
            assert response.status_code == 404, bad
        # The failed bake never reached the cycle stage: a clear 404, not a 500.
        missing = client.get(f"/v1/bakes/{service.failed_bake['id']}/cycle/report.html")
        assert missing.status_code == 404 and "has not finished" in missing.json()["detail"]
    assert httpx.get(f"{service.url}/v1/bakes/{bake_id}/cycle/report.html").status_code == 401


@pytest.mark.slow  # tens of seconds; runs in CI (CROWDBAKE_SLOW_TESTS=1)
def test_previews_of_the_baked_bundle_match_independent_decodes(service):
    texture2ddecoder = pytest.importorskip("texture2ddecoder")
    folder = Path(service.settings.bundles_dir) / NAME / "1.0.0"
    normal = decode_texture_array((folder / "impostor" / "normal.cbtx").read_bytes())
    uv = decode_texture_array((folder / "impostor" / "uv.cbtx").read_bytes())
    assert normal.pixel_format == "bc5" and uv.pixel_format == "uvblock"
    with service.client() as client:
        picture = png(client.get(f"/v1/bundles/{NAME}/1.0.0/preview/normal?frame=1"))
    theirs = np.frombuffer(texture2ddecoder.decode_bc5(normal.layers[1], normal.width, normal.height), np.uint8)
    theirs = theirs.reshape(normal.height, normal.width, 4)[..., [2, 1]].astype(int)  # BGRA -> the normal's in-view x, y
    covered = unpack_uvblock(uv.layers[1], uv.width, uv.height)[3]
    assert 0.05 < covered.mean() < 0.95  # the character shows in the atlas, with background around it
    # BC5's interpolation rounds by a level differently here and there; blue is the rebuilt third component.
    assert np.abs(picture[..., :2][covered].astype(int) - theirs[covered]).max() <= 1
    xy = picture[..., :2][covered] / 255.0 * 2.0 - 1.0  # z is steep near the silhouette: rebuilt from the preview's own x, y
    z = np.rint((np.sqrt(np.maximum(0.0, 1.0 - (xy ** 2).sum(axis=-1))) + 1.0) * 127.5)
    assert np.abs(picture[..., 2][covered].astype(int) - z).max() <= 1
    assert (picture[..., 3] == np.where(covered, 255, 0)).all()
    # The uvblock UV map previews as rgba16 would: u red, v green (top 8 of 16 bits), material blue.
    with service.client() as client:
        uv_picture = png(client.get(f"/v1/bundles/{NAME}/1.0.0/preview/uv?frame=1"))
    u, v, material, _ = unpack_uvblock(uv.layers[1], uv.width, uv.height)
    np.testing.assert_array_equal(uv_picture[..., 0][covered], (np.rint(u * 65535).astype(np.uint16) >> 8)[covered])
    np.testing.assert_array_equal(uv_picture[..., 1][covered], (np.rint(v * 65535).astype(np.uint16) >> 8)[covered])
    assert (uv_picture[..., 2][covered] == 64 * material[covered]).all()
    assert (uv_picture[..., 3] == np.where(covered, 255, 0)).all()


def run_chromium(*arguments: str, profile: Path) -> subprocess.CompletedProcess:
    command = [CHROMIUM, "--headless", "--disable-gpu", "--no-sandbox", "--no-first-run", "--disable-dev-shm-usage",
               f"--user-data-dir={profile}", f"--virtual-time-budget={VIRTUAL_TIME_BUDGET_MS}", *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=CHROMIUM_TIMEOUT_S)


@pytest.mark.slow  # tens of seconds; runs in CI (CROWDBAKE_SLOW_TESTS=1)
def test_page_in_headless_chromium_shows_the_bake_its_report_bundles_and_atlas(service, tmp_path):
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it; apt-get install chromium)")
    bake = service.bake
    # The key and the selection travel in the fragment: never sent to the server, moved to sessionStorage.
    url = f"{service.url}/ui#key={service.key}&bake={bake['id']}&bundle={NAME}/1.0.0"
    result = run_chromium("--dump-dom", url, profile=tmp_path / "profile")
    assert result.returncode == 0, result.stderr[-2000:]
    dom = result.stdout

    # The bakes table: both bakes with their names and states, from the JSON API.
    rows = dict(re.findall(r'<tr[^>]*data-bake="([^"]+)"[^>]*data-state="([^"]+)"', dom))
    assert rows == {bake["id"]: "succeeded", service.failed_bake["id"]: "failed"}
    assert f"{NAME} 1.0.0" in dom and f"{NAME} 0.0.1-broken" in dom
    # The detail of the chosen bake, its stages and its cycle report (plots inlined as data URLs).
    assert re.search(rf'id="bake-detail"[^>]*data-bake="{bake["id"]}"[^>]*data-state="succeeded"', dom)
    frame = re.search(r'<iframe id="report"[^>]*>', dom).group(0)
    assert 'data-loaded="true"' in frame and " hidden" not in re.sub(r'srcdoc="[^"]*"', "", frame)
    srcdoc = html.unescape(re.search(r'srcdoc="([^"]*)"', frame).group(1))
    assert "Cyclical cloth" in srcdoc and srcdoc.count('src="data:image/png;base64,') >= 3
    # Bundle versions with their sizes, as the API records them.
    with service.client() as client:
        record = client.get(f"/v1/bundles/{NAME}/1.0.0").json()
    assert re.search(rf'data-bundle="{NAME}/1.0.0".*?data-bytes="{record["size"]}"', dom)
    # The atlas viewer decoded layer 0 of the UV map: the whole atlas, azimuths x elevations cells (the
    # tiles as stored, cropped: SPEC.md "Impostor maps").
    image = re.search(r'<img id="atlas-image"[^>]*>', dom).group(0)
    assert 'data-loaded="true"' in image and 'data-kind="uv"' in image
    with service.client() as client:
        crop = client.get(f"/v1/bundles/{NAME}/1.0.0/manifest.json").json()["impostor"]["crop"]
    assert crop["width"] < 32 or crop["height"] < 32
    assert f'data-width="{4 * crop["width"]}"' in image and f'data-height="{2 * crop["height"]}"' in image
    # The key left the address bar and no error was shown.
    assert service.key not in dom.replace(f'value="{service.key}"', "")
    assert "Could not load" not in dom and "Enter a key" not in dom

    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    screenshot = SCREENSHOTS / "jobs.png"
    screenshot.unlink(missing_ok=True)
    shot = run_chromium(f"--screenshot={screenshot}", "--window-size=1280,2400", "--hide-scrollbars", url, profile=tmp_path / "profile2")
    assert shot.returncode == 0 and screenshot.is_file(), shot.stderr[-2000:]
    picture = np.asarray(Image.open(screenshot).convert("RGB"))
    assert picture.shape == (2400, 1280, 3) and picture.std() > 10  # not a blank page
