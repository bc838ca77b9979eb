"""A smaller run of the load benchmark (services/benchmarks/load_service.py): concurrent uploads with
duplicates among them, bakes queued on two workers while clients read the API; nothing is lost,
nothing is duplicated, every API read answers. The figures themselves are the benchmark's job
(docs/reliability.md), not this test's: it asserts outcomes, not speed."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from reliability_fixtures import require_redis_server

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "services" / "benchmarks"))
import load_service  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_concurrent_uploads_and_queued_bakes_lose_and_duplicate_nothing(sample, tmp_path):
    require_redis_server()
    result = load_service.run_load(sample, uploads=16, duplicates=6, bakes=4, workers=2, clients=2, timeout=300, root=tmp_path / "load")
    assert result["problems"] == [], result
    assert result["uploads"]["requests"] == 22 and result["bakes"]["bakes"] == 4
    latency = result["bakes"]["api_latency_during_bakes"]
    assert latency["count"] > 0 and result["bakes"]["api_read_errors"] == 0
    print(f"\nload (small): {result['uploads']['uploads_per_s']} uploads/s, {result['bakes']['bakes_per_minute']} bakes/min, "
          f"API p50 {latency['p50_ms']:.1f} ms p99 {latency['p99_ms']:.1f} ms while baking")
