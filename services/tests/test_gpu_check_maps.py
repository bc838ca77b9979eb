"""The GPU check's second mode (scripts/gpu-check/maps.py): the bake's GL passes drawn under OSMesa, drawn
again on an EGL device and compared map by map. Here both are Mesa's llvmpipe, so every map must agree
exactly; a map changed in the stored file must show up in the report; the check's own choice of device
must refuse a software rasteriser."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import numpy as np
import pytest

from egl_fixtures import platform_env
from repo_paths import REPO_ROOT

MAPS_SCRIPT = REPO_ROOT / "scripts" / "gpu-check" / "maps.py"


def load_maps():
    spec = importlib.util.spec_from_file_location("gpu_check_maps", MAPS_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


maps = load_maps()


def test_map_differences_are_shares_of_each_channels_range():
    reference = np.zeros((2, 4, 4, 2), np.uint8)
    drawn = reference.copy()
    drawn[0, 1, 1, 1] = 51  # a fifth of the range in one texel's second channel
    found = maps.map_differences(reference, drawn)
    assert found["max_abs"] == [0.0, 0.2]
    assert found["mean_abs"][0] == 0.0 and found["mean_abs"][1] == pytest.approx(0.2 / 32, abs=1e-6)
    assert found["texels_differing"] == pytest.approx(1 / 32)
    assert maps.map_differences(reference, reference)["texels_differing"] == 0.0
    with pytest.raises(ValueError, match="cannot be compared"):
        maps.map_differences(reference, drawn[:1])


def test_silhouette_agreement_is_the_covered_texels_intersection_over_union():
    ours = np.array([[0, 1, 1], [0, 0, 0]], np.float32)
    theirs = np.array([[0, 1, 0], [1, 0, 0]], np.float32)
    assert maps.silhouette_agreement(ours, theirs) == pytest.approx(1 / 3)
    assert maps.silhouette_agreement(np.zeros(3), np.zeros(3)) == 1.0


def run_maps(*args: str, platform: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(MAPS_SCRIPT), *args], env=platform_env(platform), capture_output=True, text=True,
                          timeout=300)


def test_maps_drawn_under_osmesa_and_again_on_mesas_egl_device_agree_and_a_changed_map_shows(small_bake, egl_or_skip, tmp_path):
    _, work = small_bake
    stored = tmp_path / "maps.npz"
    drawn = run_maps("draw", str(work), str(stored), platform="osmesa")
    assert drawn.returncode == 0, drawn.stderr

    report_path = tmp_path / "report.json"
    compared = run_maps("compare", str(work), str(stored), str(report_path), "--gl-device", "software", platform="egl")
    assert compared.returncode == 0, compared.stderr
    report = json.loads(report_path.read_text())
    assert report["gl"]["platform"] == "egl" and report["reference_gl"]["platform"] == "osmesa"
    assert set(report["maps"]) == {"normal", "uv", "detail", "surface", "coverage", "footprint_normal", "references"}
    assert all(max(m["max_abs"]) == 0.0 for m in report["maps"].values()) and report["silhouette_iou_worst_task"] == 1.0

    with np.load(stored) as data:
        arrays = {k: data[k] for k in data.files}
    normal = next(k for k in arrays if k.endswith("/normal"))
    arrays[normal] = arrays[normal].copy()
    arrays[normal][0, 0, 0, 0] ^= 0xFF  # one texel's x, inverted
    np.savez_compressed(stored, **arrays)
    compared = run_maps("compare", str(work), str(stored), str(report_path), "--gl-device", "software", platform="egl")
    assert compared.returncode == 0, compared.stderr
    changed = json.loads(report_path.read_text())["maps"]
    assert changed["normal"]["max_abs"][0] > 0.0 and changed["normal"]["texels_differing_worst_task"] > 0.0
    assert max(changed["uv"]["max_abs"]) == 0.0


def test_the_check_refuses_a_software_rasteriser_unless_asked_for_one(small_bake, egl_or_skip, tmp_path):
    _, work = small_bake
    refused = run_maps("compare", str(work), str(tmp_path / "none.npz"), str(tmp_path / "report.json"), platform="egl")
    assert refused.returncode == 3 and "software rasteriser" in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "report.json").exists()
    empty = run_maps("compare", str(tmp_path), str(tmp_path / "none.npz"), str(tmp_path / "report.json"), "--gl-device", "software",
                     platform="egl")
    assert empty.returncode == 2 and "no impostor plan" in empty.stderr
