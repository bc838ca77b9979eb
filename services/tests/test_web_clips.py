"""Baking several clips from the web page, in headless Chromium against the real API with no worker (the
stored bake request is what is checked): a timeline.json dropped with its cloth cache and the character
makes a bake naming it (REST `timeline`), and rows of clip, cache and mesh make one naming a cloth asset
per clip (REST `clip_cloth`, as `crowdbake submit --clip-cloth NAME=CACHE,MESH`).

The page used to ignore a dropped timeline.json ("Not an input of a bake (ignored)"), wrote "queued"
over that note at once, and the bake, of the cache alone, failed at validate with the garment off the
character. A note on files the page did not use, and a refusal, now stay on show until the user acts,
and no bake starts while such a note is up."""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest

from service_fixtures import REPO_ROOT, free_port, local_api_key, service_env, start_api

# Longer than the page's bake-list poll (JOBS_POLL_MS in app.js), so a poll that wrote over a note would show.
PAST_ONE_POLL_S = 2.5
SCREENSHOTS = REPO_ROOT / "out" / "ui"
ROBOT_FILES = ("robot.glb", "garment.pc2", "garment.obj", "timeline.json")


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """uvicorn with the real app on the filesystem broker; a key with every scope."""
    root = tmp_path_factory.mktemp("web_clips")
    data = root / "data"
    key = local_api_key(data, "upload,bake,publish,read", "page")
    port = free_port()
    api = start_api(service_env(data, "filesystem://"), port, root / "api.log")
    try:
        yield SimpleNamespace(url=f"http://127.0.0.1:{port}", key=key)
    finally:
        api.stop()


@pytest.fixture(scope="module")
def clip_samples(tmp_path_factory) -> dict[str, Path]:
    """{clip: folder} of two one-clip simulations of the same sample character (character.glb, cloth.pc2,
    cloth.obj), as test_clip_cloth bakes them."""
    from crowdbake.sample.generate import generate_sample

    root = tmp_path_factory.mktemp("clip_samples")
    for clip in ("Walking", "Running"):
        generate_sample(root / clip, clips=((clip, 3),), seed=1, cycle_frames=24, texture_size=64, cloth_rows=8, cloth_columns=24)
    return {clip: root / clip for clip in ("Walking", "Running")}


@pytest.fixture
def page(service, tmp_path):
    from crowdbake.export.devtools import CHROMIUM, Browser

    if CHROMIUM is None:
        pytest.skip("chromium is not installed (scripts/apt-packages.txt lists it)")
    with Browser(tmp_path / "profile") as browser:
        opened = browser.open(f"{service.url}/ui#key={service.key}")
        opened.wait_for("document.getElementById('param-azimuths') !== null")  # the form is built from GET /v1/params
        yield opened


def get(service, path: str) -> dict:
    response = httpx.get(f"{service.url}{path}", headers={"Authorization": f"Bearer {service.key}"}, timeout=30)
    assert response.status_code == 200, response.text
    return response.json()


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def text_of(page, element_id: str) -> str:
    return page.evaluate(f"document.getElementById({json.dumps(element_id)}).textContent")


def name_bundle(page, version: str) -> None:
    page.evaluate(f"""(() => {{
        document.getElementById('bake-name').value = 'page-clips';
        document.getElementById('bake-version').value = {json.dumps(version)};
        document.getElementById('bake-publish').checked = false;
    }})()""")


def press_bake(page) -> tuple[str, str | None]:
    """Press "Upload and bake" and wait until the page is done with it: (the status line, the bake id if one started)."""
    page.evaluate("delete document.getElementById('bake-form-status').dataset.bake; document.getElementById('start-bake').click()")
    page.wait_for("!document.getElementById('start-bake').disabled", timeout=120)
    return text_of(page, "bake-form-status"), page.evaluate("document.getElementById('bake-form-status').dataset.bake || null")


def notice(page) -> str | None:
    """The note on unused files, or None while it is hidden."""
    return page.evaluate("document.getElementById('input-notice').hidden ? null : document.getElementById('input-notice-text').textContent")


def test_a_dropped_timeline_is_named_by_the_bake_once_the_note_on_unused_files_is_dismissed(service, page, shared_asset, tmp_path):
    robot = {name: shared_asset(f"robot_clips/{name}") for name in ROBOT_FILES}
    stray_json, stray_text = tmp_path / "notes.json", tmp_path / "readme.txt"
    stray_json.write_text(json.dumps({"fps": 24, "clips": ["Idle"]}))
    stray_text.write_text("not an input")
    page.drop_files("#drop-zone > p", [*robot.values(), stray_json, stray_text])

    # The timeline is known by its content: the bake is of several clips, and every dropped input is listed.
    page.wait_for("document.getElementById('chosen-files').dataset.mode === 'timeline'")
    chosen = text_of(page, "chosen-files")
    assert all(name in chosen for name in ROBOT_FILES), chosen
    assert notice(page) == "Not used: notes.json (a JSON without segments, so not a timeline); readme.txt (not an input of a bake)."
    offered = page.evaluate("[...document.querySelectorAll('#character-clips option')].map((option) => option.value)")
    assert {"Idle", "Walking", "Running"} <= set(offered), offered  # the robot's clips, read from its glTF

    # While the note is up nothing is uploaded and no bake starts; no later status hides the note or the refusal.
    name_bundle(page, "1.0.0")
    status, bake_id = press_bake(page)
    assert bake_id is None and status.startswith("Not baking: some files were not used"), status
    assert page.evaluate("document.getElementById('bake-form-status').classList.contains('error')")
    time.sleep(PAST_ONE_POLL_S)
    assert text_of(page, "bake-form-status") == status and notice(page) is not None and "queued" not in status
    assert get(service, "/v1/bakes")["count"] == 0 and get(service, "/v1/assets")["count"] == 0

    page.evaluate("document.getElementById('dismiss-notice').click()")
    assert notice(page) is None and text_of(page, "bake-form-status") == ""
    status, bake_id = press_bake(page)
    assert bake_id and status == f"Bake {bake_id} queued.", status
    inputs = get(service, f"/v1/bakes/{bake_id}")["inputs"]
    assert set(inputs) == {"character", "cloth", "timeline", "textures"}, inputs
    timeline = get(service, f"/v1/assets/{inputs['timeline']}")
    assert timeline["kind"] == "timeline" and timeline["files"]["file"]["sha256"] == sha256(robot["timeline.json"])
    assert timeline["info"]["clips"] == {"Idle": 80, "Walking": 23, "Running": 23}
    cloth = get(service, f"/v1/assets/{inputs['cloth']}")["files"]
    assert (cloth["cache"]["sha256"], cloth["mesh"]["sha256"]) == (sha256(robot["garment.pc2"]), sha256(robot["garment.obj"]))
    assert get(service, f"/v1/assets/{inputs['character']}")["files"]["file"]["sha256"] == sha256(robot["robot.glb"])


def test_a_timeline_the_server_refuses_leaves_its_refusal_on_show_and_starts_nothing(service, page, clip_samples, shared_asset):
    walking = clip_samples["Walking"]
    page.drop_files("#drop-zone > p", [walking / "character.glb", walking / "cloth.pc2", walking / "cloth.obj", shared_asset("robot_clips/timeline.json")])
    page.wait_for("document.getElementById('chosen-files').dataset.mode === 'timeline'")
    assert notice(page) is None
    before = get(service, "/v1/bakes")["count"]
    name_bundle(page, "2.0.0")
    status, bake_id = press_bake(page)
    # The robot's timeline plays 717 frames of Idle, Walking and Running; this cache is 3 Walking cycles.
    assert bake_id is None and status.startswith("Invalid file: the timeline does not fit the cloth and the character"), status
    assert "/total_frames is 717, but the cloth cache has 73 frames" in status, status
    time.sleep(PAST_ONE_POLL_S)
    assert text_of(page, "bake-form-status") == status and "queued" not in status
    assert get(service, "/v1/bakes")["count"] == before


def test_rows_of_clip_and_cache_make_a_bake_naming_a_cloth_asset_per_clip(service, page, clip_samples):
    walking, running = clip_samples["Walking"], clip_samples["Running"]
    page.drop_files("#drop-zone > p", [walking / "character.glb", walking / "cloth.pc2"])
    page.wait_for("document.getElementById('chosen-files').textContent.includes('character.glb')")
    for k, (clip, folder) in enumerate(clip_samples.items(), start=1):
        page.evaluate("document.getElementById('add-clip').click()")
        row = f"#clip-rows .clip-row:nth-child({k})"
        page.evaluate(f"""(() => {{ const input = document.querySelector('{row} .clip-name'); input.value = '{clip}';
                           input.dispatchEvent(new Event('input')); }})()""")
        page.set_files(f"{row} .clip-cache", [folder / "cloth.pc2"])
        page.set_files(f"{row} .clip-mesh", [folder / "cloth.obj"])
    page.wait_for("document.getElementById('chosen-files').textContent.includes('Running: cloth.pc2 + cloth.obj')")
    assert page.evaluate("document.getElementById('chosen-files').dataset.mode") == "clip_cloth"

    # The single cloth cache dropped first does not go with a cache per clip: refused here, before any upload.
    name_bundle(page, "3.0.0")
    before = get(service, "/v1/assets")["count"]
    status, bake_id = press_bake(page)
    assert bake_id is None and "one cache per clip stands alone: remove the cloth cloth.pc2" in status, status
    assert get(service, "/v1/assets")["count"] == before
    page.screenshot(SCREENSHOTS / "new-bake-clips.png", selector="#new-bake", height=900)

    page.evaluate("document.querySelector('#chosen-files [data-input=cloth] button').click()")
    status, bake_id = press_bake(page)
    assert bake_id and status == f"Bake {bake_id} queued.", status
    inputs = get(service, f"/v1/bakes/{bake_id}")["inputs"]
    assert "cloth" not in inputs and "timeline" not in inputs
    assert [clip for clip, _ in inputs["clip_cloth"]] == ["Walking", "Running"]
    for (clip, asset_id), folder in zip(inputs["clip_cloth"], (walking, running)):
        files = get(service, f"/v1/assets/{asset_id}")["files"]
        assert (files["cache"]["sha256"], files["mesh"]["sha256"]) == (sha256(folder / "cloth.pc2"), sha256(folder / "cloth.obj")), clip
