"""services/benchmarks/bench_archetype_budget.py: a bundle as baked, read back from its reports."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_archetype_budget as budget_bench  # noqa: E402


def ranged(name: str, at_views: float, between: float) -> dict:
    return {"name": name, "at_views": {"ssim_mean": at_views}, "between_views": {"ssim_mean": between}}


def test_as_baked_reads_each_ranges_fidelity_and_the_worst_and_mean(tmp_path):
    chosen = {"tile": 88, "azimuths": 8, "frames": [6, 12, 15]}
    (tmp_path / "texture_memory.json").write_text(json.dumps({"impostor": {"budget": {"chosen": chosen}}}))
    ranges = [ranged("Idle", 0.949, 0.835), ranged("Running", 0.948, 0.838), ranged("Idle -> Running", 0.947, 0.77349)]
    (tmp_path / "fidelity.json").write_text(json.dumps({"runtime": {"ranges": ranges}}))
    baked = budget_bench.baked_fidelity(tmp_path)
    assert baked["chosen"] == chosen
    assert baked["between"] == {"Idle": 0.835, "Running": 0.838, "Idle -> Running": 0.7735}
    assert baked["worst"] == 0.7735
    assert baked["mean"] == pytest.approx((0.835 + 0.838 + 0.7735) / 3)
    assert baked["at_views"]["Running"] == 0.948


def test_a_bundle_of_one_clip_has_no_ranges_to_read(tmp_path):
    (tmp_path / "texture_memory.json").write_text(json.dumps({"impostor": {"budget": {"chosen": {"tile": 88}}}}))
    (tmp_path / "fidelity.json").write_text(json.dumps({"runtime": {}}))
    baked = budget_bench.baked_fidelity(tmp_path)
    assert baked["worst"] is None and baked["mean"] is None and baked["between"] == {}
