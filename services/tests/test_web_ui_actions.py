"""The web page as people work in it, in headless Chromium (DevTools protocol) against a real API and
worker: choose the character and cloth with the file inputs, drop the textures on the drop zone, start
a bake with parameters, publish it, download the bundle as a zip (every file checked against the
manifest), look at the atlas at full size and zoomed; start a second bake, cancel it, retry it.

Screenshots go to out/ui/ (docs/img/ holds copies)."""
from __future__ import annotations

import base64
import hashlib
import json
import zipfile

import pytest

from baked_service import PARAMS
from live_service import live_service
from service_fixtures import REPO_ROOT

# slow: a real server and worker (or browser) for tens of seconds; scripts/test.sh runs it with CROWDBAKE_SLOW_TESTS=1, as CI does
pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCREENSHOTS = REPO_ROOT / "out" / "ui"
BAKE_TIMEOUT_S = 240
NAME = "page-walker"


@pytest.fixture(scope="module")
def service(tmp_path_factory, small_sample):
    with live_service(tmp_path_factory.mktemp("page"), small_sample) as running:
        yield running


@pytest.fixture
def browser(tmp_path):
    from crowdbake.export.devtools import CHROMIUM, Browser

    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    with Browser(tmp_path / "profile") as running:
        yield running


def drop_files(page, selector: str, files: dict[str, bytes]) -> None:
    """Dispatch a drop event carrying `files` on the element, as a drag from the desktop would."""
    payload = json.dumps({name: base64.b64encode(data).decode() for name, data in files.items()})
    page.evaluate(f"""(() => {{
        const transfer = new DataTransfer();
        for (const [name, data] of Object.entries({payload})) {{
            const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
            transfer.items.add(new File([bytes], name, {{ type: "image/png" }}));
        }}
        const zone = document.querySelector({json.dumps(selector)});
        zone.dispatchEvent(new DragEvent("dragover", {{ dataTransfer: transfer, bubbles: true, cancelable: true }}));
        zone.dispatchEvent(new DragEvent("drop", {{ dataTransfer: transfer, bubbles: true, cancelable: true }}));
    }})()""")


def fill_form(page, version: str, publish: bool) -> None:
    values = {"bake-name": NAME, "bake-version": version, "param-impostor_frames": PARAMS["impostor_frames"], "param-azimuths": PARAMS["azimuths"],
              "param-elevations_deg": ",".join(str(value) for value in PARAMS["elevations_deg"]), "param-tile_size": PARAMS["tile_size"],
              "param-candidates": PARAMS["candidates"], "param-cycle_views": PARAMS["cycle_views"]}
    page.wait_for("document.getElementById('param-azimuths') !== null")  # the fields are built from GET /v1/params
    page.evaluate(f"""(() => {{
        for (const [id, value] of Object.entries({json.dumps(values)})) document.getElementById(id).value = String(value);
        document.getElementById("bake-publish").checked = {json.dumps(publish)};
    }})()""")


def click(page, element_id: str) -> None:
    page.wait_for(f"!document.getElementById('{element_id}').hidden && !document.getElementById('{element_id}').disabled")
    page.evaluate(f"document.getElementById('{element_id}').click()")


def start_bake_from_page(page, version: str, publish: bool) -> str:
    fill_form(page, version, publish)
    page.evaluate("delete document.getElementById('bake-form-status').dataset.bake")
    click(page, "start-bake")
    return page.wait_for("document.getElementById('bake-form-status').dataset.bake || "
                         "(document.getElementById('bake-form-status').textContent.includes(':') && 'error: ' + document.getElementById('bake-form-status').textContent)",
                         timeout=60)


def detail_state(page, bake_id: str) -> str:
    return page.evaluate(f"(() => {{ const d = document.getElementById('bake-detail'); return d.dataset.bake === '{bake_id}' ? d.dataset.state : ''; }})()")


def test_upload_bake_publish_download_zoom_cancel_retry(service, browser, tmp_path):
    sample = service.sample
    downloads = tmp_path / "downloads"
    browser.allow_downloads(downloads)
    page = browser.open(f"{service.url}/ui#key={service.keys['all']}")
    # The key went to sessionStorage (not localStorage) and left the address bar.
    assert page.evaluate("sessionStorage.getItem('crowdbake.key')") == service.keys["all"]
    assert page.evaluate("localStorage.getItem('crowdbake.key')") is None and service.keys["all"] not in page.evaluate("location.href")

    # Inputs: file inputs for the character and the cloth, the drop zone for the textures.
    page.set_files("#file-character", [sample / "character.glb"])
    page.set_files("#file-cloth", [sample / "cloth.pc2"])
    page.set_files("#file-cloth-mesh", [sample / "cloth.obj"])
    textures = {path.name: path.read_bytes() for path in sorted((sample / "textures").glob("*.png"))}
    drop_files(page, "#drop-zone", textures)
    chosen = page.evaluate("document.getElementById('chosen-files').textContent")
    assert "character.glb" in chosen and "cloth.pc2" in chosen and "cloth.obj" in chosen and all(name in chosen for name in textures)

    # A bad name is refused by the server with the field named, and nothing starts.
    page.evaluate("document.getElementById('bake-name').removeAttribute('pattern')")  # past the browser's own check
    fill_form(page, "1.0.0", publish=False)
    page.evaluate("document.getElementById('bake-name').value = 'Bad Name'")
    click(page, "start-bake")
    before = service.asset_count()
    refused = page.wait_for("(() => { const t = document.getElementById('bake-form-status').textContent; return t.includes('Invalid') && t; })()")
    assert "[name" in refused and service.asset_count() == before  # refused before any upload

    # Bake without publishing, from the page; then publish and download from the bake's detail.
    bake_id = start_bake_from_page(page, "1.0.0", publish=False)
    assert bake_id.startswith("bk_"), bake_id
    page.wait_for(f"document.getElementById('bake-detail').dataset.state === 'succeeded' && document.getElementById('bake-detail').dataset.bake === '{bake_id}'",
                  timeout=BAKE_TIMEOUT_S)
    assert page.evaluate("document.getElementById('action-download').hidden") is True
    click(page, "action-publish")
    click(page, "action-download")
    page.wait_for(f"document.getElementById('action-status').dataset.downloaded === '{NAME}/1.0.0'", timeout=BAKE_TIMEOUT_S)
    archive = downloads / f"{NAME}-1.0.0.zip"
    for _ in range(100):
        if archive.is_file() and not (downloads / f"{archive.name}.crdownload").exists():
            break
        page.wait_for("new Promise((done) => setTimeout(() => done(true), 100))")
    with zipfile.ZipFile(archive) as bundle:
        manifest = json.loads(bundle.read(f"{NAME}/1.0.0/manifest.json"))
        assert manifest["name"] == NAME and manifest["version"] == "1.0.0" and manifest["impostor"]["tile_size"] == PARAMS["tile_size"]
        for entry in manifest["files"]:
            data = bundle.read(f"{NAME}/1.0.0/{entry['path']}")
            assert len(data) == entry["size"] and hashlib.sha256(data).hexdigest() == entry["sha256"], entry["path"]
    with service.client() as client:
        assert client.get(f"/v1/bundles/{NAME}/1.0.0/manifest.json").json() == manifest

    # The atlas: full size (1x: one texel per pixel), then 4x; its viewport scrolls instead of shrinking it.
    page.evaluate(f"selectBundle('{NAME}', '1.0.0')")
    page.wait_for("document.getElementById('atlas-image').dataset.loaded === 'true'")
    width = int(page.evaluate("document.getElementById('atlas-image').naturalWidth"))
    # One cell of the crop (SPEC.md "Impostor maps") per azimuth.
    assert width == PARAMS["azimuths"] * manifest["impostor"]["crop"]["width"] < PARAMS["azimuths"] * PARAMS["tile_size"]
    assert page.evaluate("document.getElementById('atlas-image').getBoundingClientRect().width") == width
    page.evaluate("(() => { const z = document.getElementById('atlas-zoom'); z.value = '4'; z.dispatchEvent(new Event('change')); })()")
    assert page.evaluate("document.getElementById('atlas-image').getBoundingClientRect().width") == 4 * width
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(SCREENSHOTS / "jobs-page.png", height=1000)
    page.screenshot(SCREENSHOTS / "atlas-zoom.png", selector="#atlas", height=900)

    # A second bake: cancel it from the page, then retry it (a new attempt), then cancel again.
    second = start_bake_from_page(page, "2.0.0", publish=True)
    assert second.startswith("bk_") and second != bake_id, second
    click(page, "action-cancel")
    page.wait_for(f"document.getElementById('bake-detail').dataset.state === 'cancelled' && document.getElementById('bake-detail').dataset.bake === '{second}'")
    click(page, "action-retry")
    page.wait_for(f"['queued', 'running'].includes(document.getElementById('bake-detail').dataset.state) && document.getElementById('bake-detail').dataset.bake === '{second}'")
    with service.client() as client:
        assert client.get(f"/v1/bakes/{second}").json()["attempt"] == 1
    click(page, "action-cancel")
    page.wait_for("document.getElementById('bake-detail').dataset.state === 'cancelled'")
    assert page.evaluate("document.getElementById('detail-summary').textContent").startswith("cancelled")
