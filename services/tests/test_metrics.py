"""GET /metrics (crowdbake.metrics): bake figures read from the database at scrape time, HTTP figures
counted by the API process, in the Prometheus text format.

The main test bakes the sample on a real worker (baked_service: uvicorn + Celery on the filesystem
broker) and checks that the exposition says what the bake records say: one bake succeeded and one
failed in validate, each stage's duration observed once with the seconds the API reports, the bake's
wall time, the bytes uploaded, and the requests this test made by route template.
"""
from __future__ import annotations

import datetime as dt
import os
import subprocess
import sys

import pytest
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy.orm import sessionmaker

from baked_service import baked_service
from crowdbake.metrics import (
    DURATION_BUCKETS_S,
    UNMATCHED_ROUTE,
    DatabaseCollector,
    cumulative_buckets,
    seconds_between,
    upload_kind,
)
from service_fixtures import SERVICES_DIR, make_api, obj_bytes, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth

# The stages a bake of one clip runs (its loops stage, a fan-out over a timeline's clips, is skipped).
STAGES = ("validate", "cycle", "probes", "poses", "impostors", "pack", "publish")
# Seconds are stored rounded to the millisecond (records.finish_stage); sums of seven of them differ by less.
SECONDS_TOLERANCE = 0.01
# Multipart framing around an uploaded file: boundaries and part headers, well under a kilobyte.
MULTIPART_OVERHEAD_MAX = 1024


def samples(text: str) -> dict[tuple[str, frozenset], float]:
    """{(sample name, labels): value} of an exposition (parsed with prometheus_client's own parser)."""
    return {(s.name, frozenset(s.labels.items())): s.value for family in text_string_to_metric_families(text) for s in family.samples}


def value(parsed, name: str, **labels) -> float:
    return parsed[(name, frozenset(labels.items()))]


# ------------------------------------------------------------------------------- pure functions


def test_cumulative_buckets_count_values_at_or_below_each_edge():
    assert cumulative_buckets([0.5, 1.0, 3.0, 100.0], (1.0, 2.5, 5.0)) == [("1.0", 2), ("2.5", 2), ("5.0", 3), ("+Inf", 4)]
    assert cumulative_buckets([], (1.0,)) == [("1.0", 0), ("+Inf", 0)]
    with pytest.raises(ValueError, match="increase"):
        cumulative_buckets([1.0], (2.0, 1.0))


def test_seconds_between_accepts_naive_and_aware_utc_and_missing_ends():
    aware = dt.datetime(2006, 9, 4, 12, 0, tzinfo=dt.timezone.utc)
    naive = dt.datetime(2006, 9, 4, 12, 1, 30)  # SQLite hands back naive UTC
    assert seconds_between(aware, naive) == 90.0
    assert seconds_between(None, naive) is None and seconds_between(aware, None) is None


def test_upload_kind_names_the_asset_routes_only():
    assert upload_kind("POST", "/v1/assets/characters") == "character"
    assert upload_kind("POST", "/v1/assets/cloth") == "cloth"
    assert upload_kind("POST", "/v1/assets/textures") == "texture"
    assert upload_kind("GET", "/v1/assets/characters") is None
    assert upload_kind("POST", "/v1/bakes") is None


def test_a_database_that_cannot_be_read_is_reported_not_raised():
    from crowdbake.storage.db import make_engine

    collector = DatabaseCollector(sessionmaker(bind=make_engine("sqlite://")))  # no tables at all
    metrics = {metric.name: metric for metric in collector.collect()}
    assert metrics["crowdbake_database_up"].samples[0].value == 0
    assert "crowdbake_bakes" not in metrics


# --------------------------------------------------------------------------- the app, no worker


def test_queued_bakes_are_the_queue_depth_and_uploads_are_counted(tmp_path):
    """With no worker, every bake started stays queued: the database says so, and so does /metrics."""
    api = make_api(tmp_path)
    points, faces = tiny_cloth(frames=12)
    upload = api.auth("upload")
    glb = tiny_character_glb()
    character = api.client.post("/v1/assets/characters", files={"file": ("walker.glb", glb)}, headers=upload).json()
    cloth = api.client.post("/v1/assets/cloth", files={"cache": ("c.pc2", pc2_bytes(points)), "mesh": ("c.obj", obj_bytes(points[0], faces, tmp_path))},
                            headers=upload).json()
    refused = api.client.post("/v1/assets/textures", files={"file": ("d.png", png_bytes()[:-20])}, headers=upload)
    assert refused.status_code == 422
    for version in ("1.0.0", "1.0.1"):
        body = {"name": "walker", "version": version, "character": character["id"], "cloth": cloth["id"], "params": {"impostor_frames": 2, "tile_size": 32}}
        assert api.client.post("/v1/bakes", json=body, headers=api.auth("ci")).status_code == 202

    response = api.client.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain; version=0.0.4")
    parsed = samples(response.text)
    assert value(parsed, "crowdbake_bakes", state="queued") == 2
    assert value(parsed, "crowdbake_bakes", state="succeeded") == 0
    assert value(parsed, "crowdbake_bake_stages", stage="validate", state="queued") == 2  # due, its message sent
    assert value(parsed, "crowdbake_stage_duration_seconds_count", stage="cycle") == 0
    assert value(parsed, "crowdbake_assets", kind="character") == 1 and value(parsed, "crowdbake_asset_bytes", kind="character") == len(glb)
    stored = value(parsed, "crowdbake_upload_bytes_total", kind="character", outcome="stored")
    assert len(glb) < stored < len(glb) + MULTIPART_OVERHEAD_MAX
    assert value(parsed, "crowdbake_upload_bytes_total", kind="texture", outcome="refused") > 0
    # Latency by route template, never by raw path (ids would make a series per bake).
    assert value(parsed, "crowdbake_http_request_duration_seconds_count", method="POST", route="/v1/bakes", status="202") == 2
    api.client.get("/v1/bakes/bk_nothing", headers=api.auth("bake"))
    api.client.get("/no/such/path")
    parsed = samples(api.client.get("/metrics").text)
    assert value(parsed, "crowdbake_http_request_duration_seconds_count", method="GET", route="/v1/bakes/{bake_id}", status="404") == 1
    assert value(parsed, "crowdbake_http_request_duration_seconds_count", method="GET", route=UNMATCHED_ROUTE, status="404") == 1
    assert not any("bk_nothing" in dict(labels).get("route", "") for _, labels in parsed)


def test_multiprocess_mode_sums_the_processes_sharing_the_folder(tmp_path):
    """PROMETHEUS_MULTIPROC_DIR (uvicorn --workers N): HTTP figures come from the shared folder, bake
    figures still from the database. Run in a subprocess: prometheus_client reads the variable at import."""
    folder = tmp_path / "prometheus"
    folder.mkdir()
    script = f"""
from fastapi.testclient import TestClient
from crowdbake.api.app import create_app
from crowdbake.settings import Settings
for n in range(2):  # two apps write to the folder; /metrics of the last one reads both from it
    client = TestClient(create_app(Settings(data_dir={str(tmp_path / 'data')!r})))
    client.get("/health")
print(client.get("/metrics").text)
"""
    env = dict(os.environ, PROMETHEUS_MULTIPROC_DIR=str(folder), PYTHONPATH=str(SERVICES_DIR))
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    parsed = samples(result.stdout)
    assert value(parsed, "crowdbake_http_request_duration_seconds_count", method="GET", route="/health", status="200") == 2
    assert value(parsed, "crowdbake_bakes", state="queued") == 0 and value(parsed, "crowdbake_database_up") == 1
    assert any(folder.iterdir())


# ------------------------------------------------------------------------- after real bakes


@pytest.fixture(scope="module")
def service(tmp_path_factory, small_sample):
    with baked_service(tmp_path_factory.mktemp("metrics"), small_sample) as running:
        yield running


@pytest.mark.slow  # tens of seconds; runs in CI (CROWDBAKE_SLOW_TESTS=1)
def test_metrics_after_a_bake_show_counts_and_durations(service):
    bake, failed = service.bake, service.failed_bake
    with service.client() as client:
        for _ in range(3):
            assert client.get(f"/v1/bakes/{bake['id']}").status_code == 200
        response = client.get("/metrics")
    assert response.status_code == 200
    parsed = samples(response.text)

    # Queue depth and outcomes: what the database holds.
    assert value(parsed, "crowdbake_bakes", state="succeeded") == 1
    assert value(parsed, "crowdbake_bakes", state="failed") == 1
    assert value(parsed, "crowdbake_bakes", state="queued") == 0 and value(parsed, "crowdbake_bakes", state="running") == 0
    assert value(parsed, "crowdbake_impostor_tasks_pending") == 0
    # Failures by stage, with the error type the bake records.
    assert failed["error"]["stage"] == "validate"
    assert value(parsed, "crowdbake_stage_failures", stage="validate", type=failed["error"]["type"]) == 1
    assert value(parsed, "crowdbake_stage_failures", stage="cycle", type="none") == 0

    # Stage durations: one observation per stage (the failed bake's validate is not a duration of work),
    # with the seconds the API reports for the finished bake, in the bucket they belong to.
    reported = {stage["stage"]: stage["seconds"] for stage in bake["stages"]}
    for stage in STAGES:
        assert value(parsed, "crowdbake_stage_duration_seconds_count", stage=stage) == 1, stage
        assert value(parsed, "crowdbake_stage_duration_seconds_sum", stage=stage) == pytest.approx(reported[stage], abs=SECONDS_TOLERANCE)
        first_edge = next(edge for edge in DURATION_BUCKETS_S if reported[stage] <= edge)
        assert value(parsed, "crowdbake_stage_duration_seconds_bucket", stage=stage, le=repr(first_edge)) == 1
        below = [edge for edge in DURATION_BUCKETS_S if edge < first_edge]
        if below:
            assert value(parsed, "crowdbake_stage_duration_seconds_bucket", stage=stage, le=repr(below[-1])) == 0
    assert value(parsed, "crowdbake_bake_stages", stage="impostors", state="succeeded") == 1
    assert value(parsed, "crowdbake_bake_stages", stage="loops", state="skipped") == 1
    assert value(parsed, "crowdbake_bake_stages", stage="validate", state="failed") == 1

    # Bake wall time: from the first stage's start to the end, as the records say.
    took = (dt.datetime.fromisoformat(bake["finished_at"]) - dt.datetime.fromisoformat(bake["started_at"])).total_seconds()
    assert value(parsed, "crowdbake_bake_duration_seconds_count", state="succeeded") == 1
    assert value(parsed, "crowdbake_bake_duration_seconds_sum", state="succeeded") == pytest.approx(took, abs=SECONDS_TOLERANCE)
    # The work fits in the wall time (a skipped stage did none: no seconds).
    assert took >= sum(seconds for seconds in reported.values() if seconds is not None) - SECONDS_TOLERANCE
    assert value(parsed, "crowdbake_bake_duration_seconds_count", state="failed") == 1
    assert value(parsed, "crowdbake_bake_queue_wait_seconds_count") == 2

    # Upload bytes: the bodies received (files plus multipart framing), by kind.
    for kind, (size, files) in service.uploads.items():
        received = value(parsed, "crowdbake_upload_bytes_total", kind=kind, outcome="stored")
        assert size < received < size + files * MULTIPART_OVERHEAD_MAX, kind
        assert value(parsed, "crowdbake_asset_bytes", kind=kind) == size
    # HTTP latency by route: this test's three reads, on top of the fixture's polling.
    assert value(parsed, "crowdbake_http_request_duration_seconds_count", method="GET", route="/v1/bakes/{bake_id}", status="200") >= 3
    assert value(parsed, "crowdbake_http_request_duration_seconds_count", method="POST", route="/v1/assets/textures", status="201") == service.uploads["texture"][1]
    assert value(parsed, "crowdbake_database_up") == 1


@pytest.mark.slow  # tens of seconds; runs in CI (CROWDBAKE_SLOW_TESTS=1)
def test_metrics_need_no_key(service):
    import httpx

    response = httpx.get(f"{service.url}/metrics", timeout=30)
    assert response.status_code == 200 and "# TYPE crowdbake_bakes gauge" in response.text
    assert service.key not in response.text and service.bake["id"] not in response.text


def test_made_up_http_methods_do_not_grow_the_label_set(tmp_path):
    """3,000 requests with made-up methods used to grow /metrics from 48 KB to 15.9 MB: every method
    became a label value. Unknown methods now count as OTHER."""
    from service_fixtures import make_api

    api = make_api(tmp_path)
    before = len(api.client.get("/metrics").content)
    for index in range(300):
        api.client.request(f"FAKE{index}", "/v1/bakes")
    exposition = api.client.get("/metrics").text
    assert 'method="OTHER"' in exposition and "FAKE1" not in exposition
    assert len(exposition) < before + 20_000


def test_redact_url_hides_passwords_only():
    from crowdbake.settings import redact_url

    assert redact_url("redis://:s3cret@broker:6379/0") == "redis://:***@broker:6379/0"
    assert redact_url("postgresql://bake:pw@db/crowd") == "postgresql://bake:***@db/crowd"
    assert redact_url("redis://broker:6379/0") == "redis://broker:6379/0"
