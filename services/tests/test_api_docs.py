"""The API's own documentation: clean operation ids, and /docs and /redoc served from packaged files,
so they work with no internet (checked in the HTML, and in headless Chromium with every host but the
service unresolvable)."""
from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from service_fixtures import free_port, make_api, service_env, start_api

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
OPERATION_ID = re.compile(r"^[a-z]+-[a-z][a-z_]*$")


@pytest.fixture
def api(tmp_path):
    return make_api(tmp_path)


def operations(document: dict) -> list[tuple[str, str, dict]]:
    return [(method, path, operation) for path, item in document["paths"].items() for method, operation in item.items()]


def test_operation_ids_are_tag_and_function_and_unique(api):
    document = api.client.get("/openapi.json").json()
    ids = [operation["operationId"] for _, _, operation in operations(document)]
    assert len(ids) == len(set(ids)) and len(ids) >= 20
    for method, path, operation in operations(document):
        assert OPERATION_ID.match(operation["operationId"]), (method, path, operation["operationId"])
        assert operation["operationId"].split("-")[0] == operation["tags"][0]
        assert "_v1_" not in operation["operationId"] and not operation["operationId"].endswith(f"_{method}")
    assert "assets-upload_character" in ids and "bakes-create_bake" in ids and "bundles-get_file" in ids


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_reference_no_other_host(api, page):
    response = api.client.get(page)
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/html")
    html = response.text
    assert not re.search(r"(https?:)?//[A-Za-z0-9]", html), re.findall(r"(?:https?:)?//[^\s'\"<>]+", html)
    references = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert references, html
    for reference in references:
        assert reference.startswith("/") and not reference.startswith("//"), reference
        asset = api.client.get(reference)
        assert asset.status_code == 200 and len(asset.content) > 1000, reference


def test_docs_render_in_chromium_with_no_network(tmp_path):
    """Every host name but the service's address fails to resolve: a page that needed a CDN stays blank."""
    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    port = free_port()
    api = start_api(service_env(tmp_path / "data", "filesystem://"), port, tmp_path / "api.log")
    try:
        command = [CHROMIUM, "--headless", "--disable-gpu", "--no-sandbox", "--no-first-run", "--disable-dev-shm-usage",
                   f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000",
                   "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1", "--dump-dom", f"http://127.0.0.1:{port}/docs"]
        result = subprocess.run(command, capture_output=True, text=True, timeout=90)
    finally:
        api.stop()
    assert result.returncode == 0, result.stderr[-2000:]
    dom = result.stdout
    # Swagger UI rendered the operations (each gets an element id from its tag and operation id).
    assert 'id="operations-assets-assets-upload_character"' in dom, dom[:2000]
    assert 'id="operations-bakes-bakes-create_bake"' in dom
