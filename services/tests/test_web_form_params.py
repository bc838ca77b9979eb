"""The web page's bake form is built from the parameter table the server serves (GET /v1/params, from
crowdbake.params.PARAMS). It used to be hand-written beside the table and disagreed with the server: its
azimuths placeholder said 16 while the server baked 32, and its loop-closing list said "default (hermite)"
and lacked crossfade, the server's default. Read here as a user sees it: the page in headless Chromium."""
from __future__ import annotations

import json

import httpx
import pytest

from crowdbake.params import PARAMS, default_text
from service_fixtures import free_port, service_env, start_api


@pytest.fixture(scope="module")
def server_url(tmp_path_factory):
    """uvicorn with the real app (no worker: the form needs none)."""
    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, migrate

    root = tmp_path_factory.mktemp("form")
    data = root / "data"
    migrate(make_engine(Settings(data_dir=data, broker_url="filesystem://").database_url))
    port = free_port()
    api = start_api(service_env(data, "filesystem://"), port, root / "api.log")
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        api.stop()


def test_the_served_table_is_the_parameter_table(server_url):
    served = httpx.get(f"{server_url}/v1/params", timeout=10).json()
    assert [item["name"] for item in served] == [spec.name for spec in PARAMS]
    for item, spec in zip(served, PARAMS):
        assert item["default"] == (list(spec.default) if isinstance(spec.default, tuple) else spec.default), spec.name
        assert item["choices"] == (list(spec.choices) if spec.choices else None), spec.name
        assert item["default_text"] == default_text(spec), spec.name


def test_every_parameter_is_in_the_form_with_the_tables_default_and_choices(server_url, tmp_path):
    from crowdbake.export.devtools import CHROMIUM, Browser

    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    with Browser(tmp_path / "profile") as browser:
        page = browser.open(f"{server_url}/ui")
        page.wait_for(f"document.querySelectorAll('#bake-form [data-param]').length === {len(PARAMS)}", timeout=30)
        fields = page.evaluate("""(() => Object.fromEntries([...document.querySelectorAll('#bake-form [data-param]')].map((input) => [
            input.dataset.param, { id: input.id, tag: input.tagName, type: input.type, placeholder: input.placeholder, checked: input.checked,
                                   options: input.tagName === 'SELECT' ? [...input.options].map((o) => [o.value, o.textContent]) : null }])))()""")
        for spec in PARAMS:
            field = fields[spec.name]
            assert field["id"] == f"param-{spec.name}"
            if spec.kind == "bool":
                assert field["type"] == "checkbox" and field["checked"] is spec.default, (spec.name, field)
            elif spec.kind == "str":
                values = [value for value, _ in field["options"]]
                assert values == ["", *spec.choices], (spec.name, field)  # "" leaves the server's default
                assert field["options"][0][1] == f"default ({default_text(spec)})", (spec.name, field)
            else:
                assert field["placeholder"] == default_text(spec), (spec.name, field)
        # What an untouched form sends: nothing, so the server applies the table's defaults.
        assert page.evaluate("JSON.stringify(bakeParams())") == json.dumps({})
        assert fields["azimuths"]["placeholder"] == "32" and fields["close"]["options"][0][1] == "default (crossfade)"
        # And what a filled one sends, in the API's types.
        page.evaluate("""(() => { document.getElementById('param-azimuths').value = '8'; document.getElementById('param-close').value = 'linear';
            document.getElementById('param-elevations_deg').value = '0, 30'; document.getElementById('param-compress').checked = false;
            document.getElementById('param-animation').value = 'walk'; })()""")
        assert json.loads(page.evaluate("JSON.stringify(bakeParams())")) == {
            "azimuths": 8, "close": "linear", "elevations_deg": [0, 30], "compress": False, "animation": "walk"}
