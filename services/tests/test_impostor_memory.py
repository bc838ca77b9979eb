"""What one character's impostor costs in memory.

The crop (SPEC.md "Impostor maps", crowdbake.bake.atlas): the atlas stores of every tile only the box the
character covers over every view and frame. A small bake with and without it: the crop must save memory
and change nothing crowdview draws, through crowdview's own shader (crowdbake.render.runtime_shader).
Detail maps are stored only when asked for (`detail_map`); crowdview says so where it would need them."""
from __future__ import annotations

import json
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from crowdbake.cli.bake import format_summary
from crowdbake.formats.bundle import verify_bundle
from sample_fixtures import small_bake_params

pytest.importorskip("pyrender")
from crowdbake.render.impostor import BakeRenderer  # noqa: E402
from crowdbake.stages.impostors import load_poses  # noqa: E402
from crowdbake.stages import impostor_plan  # noqa: E402
from crowdbake.stages.impostor_plan import probe_setting  # noqa: E402
from crowdbake.stages.runner import run_bake  # noqa: E402
from crowdbake.stages.runtime_fidelity import halfway_frame, picture_at, runtime_atlas, runtime_textures  # noqa: E402
from crowdbake.stages.validate import BakeInputs  # noqa: E402
from crowdbake.bake import view_blend  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[2]
CROWDVIEW = REPO_ROOT / "build" / "runtime" / "crowdview"
PARAMS = small_bake_params()


@pytest.fixture(scope="module")
def bakes(small_sample, small_bake, tmp_path_factory):
    """{crop: (bundle folder, poses, maps, textures)} of the small sample baked with the defaults (the
    session's small bake: cropped, no detail maps) and without the crop, with detail maps."""
    out = {}
    for crop in (True, False):
        if crop:
            bundle, work = small_bake
        else:
            root = tmp_path_factory.mktemp("whole_tiles")
            summary = run_bake(BakeInputs(character=small_sample / "character.glb", cloth=small_sample / "cloth.pc2",
                                          cloth_mesh=small_sample / "cloth.obj", textures=small_sample / "textures", cycle=None,
                                          name="sample", version="1.0", params=replace(PARAMS, crop=False, detail_map=True)),
                               root / "bundles", work=root / "work")
            bundle, work = summary.bundle, root / "work"
        baked = verify_bundle(bundle)
        maps = {kind: baked.textures[path] for kind, path in baked.manifest["impostor"]["maps"].items()}
        out[crop] = bundle, load_poses(work), maps, runtime_textures(work)
    return out


def test_the_crop_stores_less_and_says_where(bakes):
    cropped, whole = (json.loads((bakes[crop][0] / "manifest.json").read_text())["impostor"] for crop in (True, False))
    assert "crop" not in whole
    crop = cropped["crop"]
    assert all(crop[k] % 4 == 0 for k in crop) and crop["x"] + crop["width"] <= 64 and crop["y"] + crop["height"] <= 64
    for kind in ("normal", "uv", "surface"):
        small = (bakes[True][0] / cropped["maps"][kind]).stat().st_size
        large = (bakes[False][0] / whole["maps"][kind]).stat().st_size
        assert small < 0.75 * large, f"{kind}: {small} bytes cropped against {large}"


def test_crowdviews_shader_draws_the_same_pictures_from_cropped_maps(bakes):
    pictures = {}
    for crop, (_, poses, maps, textures) in bakes.items():
        layout = poses.atlas_layout()
        layer = list(poses.frame_indices).index(poses.fidelity_frame)
        baked = view_blend.FrameWeights((layer, layer), 0.0)
        _, between = halfway_frame(poses)
        cameras = [(a, e, baked) for a in layout.azimuths_deg for e in layout.elevations_deg]
        cameras += [(22.5, 0.0, baked), (157.5, 30.0, between), (292.5, 15.0, between), (0.0, 30.0, between)]
        atlas = runtime_atlas(poses, layout, maps["uv"], maps["normal"], maps.get("surface"), textures)
        with BakeRenderer(layout.tile_size) as renderer:
            pictures[crop] = renderer.runtime_impostors(atlas, [picture_at(layout, a, e, f) for a, e, f in cameras])
    drawn = (pictures[True] > 0).any(axis=-1)
    assert drawn.mean() > 0.1, "the pictures show the character"
    # The same texels, the same weights: equal but for a reprojection that, outside the silhouette,
    # reads the crop's border where the whole tile held the dilation's value further out.
    differs = np.abs(pictures[True] - pictures[False]).max(axis=-1) > 1.5 / 255
    assert differs.mean() < 0.002, f"{differs.sum()} of {differs.size} pixels differ"


def test_fidelity_scores_agree_with_and_without_the_crop(bakes):
    scores = [json.loads((bakes[crop][0] / "fidelity.json").read_text())["runtime"] for crop in (True, False)]
    for section in ("at_views", "between_views", "between_azimuths"):
        assert scores[0][section]["ssim_mean"] == pytest.approx(scores[1][section]["ssim_mean"], abs=0.002), section


def test_detail_maps_are_stored_only_when_asked_and_figure_4_still_counts_them(bakes):
    cropped, whole = (json.loads((bakes[crop][0] / "manifest.json").read_text()) for crop in (True, False))
    assert set(cropped["impostor"]["maps"]) == {"normal", "uv", "surface"}
    assert set(whole["impostor"]["maps"]) == {"normal", "uv", "surface", "detail"}
    assert not (bakes[True][0] / "impostor" / "detail.cbtx").exists()
    document = json.loads((bakes[True][0] / "texture_memory.json").read_text())
    memory = document["bundle"]["map_bytes"]
    # What the detail maps would hold: BC2, a byte a texel, like the normal map's BC5.
    assert memory["detail"] == memory["normal"] > 0
    # The impostor one clip holds: the stored maps' layers, without their CBTX headers.
    held = document["impostor"]
    assert set(held["stored_bytes"]) == {"normal", "uv", "surface"}
    on_disk = sum((bakes[True][0] / path).stat().st_size for path in cropped["impostor"]["maps"].values())
    assert 0 < on_disk - sum(held["stored_bytes"].values()) < 3 * 64
    assert held["crop"] == cropped["impostor"]["crop"] and held["views"] == 16 and held["frames"] == 2
    # Far under the default budget: the counts asked for.
    assert held["budget"]["budget_mib"] == 16.0 and held["budget"]["fits"]
    assert held["budget"]["chosen"] == held["budget"]["asked"] == {"tile": 64, "azimuths": 8, "frames": 2}


def test_the_rule_fits_the_maps_by_fewer_azimuths(small_sample, bakes, tmp_path):
    """--impostor-choice rule: 32 azimuths asked for, room for 20 (the crop is the same whatever the
    azimuths): azimuths fall, by 4, until the maps fit."""
    whole = json.loads((bakes[True][0] / "texture_memory.json").read_text())["impostor"]
    # One ring of the two: room for 20 azimuths at the small bake's crop and frames.
    budget = whole["stored_mib"] / 2 * 20 / 8 + 1e-9
    params = replace(PARAMS, azimuths=32, elevations_deg=(0.0,), impostor_budget_mib=budget, impostor_choice="rule")
    summary = run_bake(BakeInputs(character=small_sample / "character.glb", cloth=small_sample / "cloth.pc2",
                                  cloth_mesh=small_sample / "cloth.obj", textures=small_sample / "textures", cycle=None,
                                  name="sample", version="1.0", params=params), tmp_path / "bundles", work=tmp_path / "work")
    held = json.loads((summary.bundle / "texture_memory.json").read_text())["impostor"]
    assert held["stored_mib"] <= budget and held["budget"]["fits"]
    assert held["budget"]["chosen"] == {"azimuths": 20, "frames": 2}
    assert [step["azimuths"] for step in held["budget"]["steps"]] == [32, 28, 24, 20]
    manifest = json.loads((summary.bundle / "manifest.json").read_text())["impostor"]
    assert len(manifest["azimuths_deg"]) == 20 and manifest["azimuths_deg"][1] == 18.0
    # The frames the motion asks for come first (2 asked, under the floor: kept), and the summary says so.
    assert held["budget"]["motion"] == {"max_texels": PARAMS.impostor_motion_texels, "frames": 2}
    assert "budget chose 20 azimuths and 2 frames (asked 32 and 2; the motion needs 2 frames)" in format_summary(summary)


def test_the_measured_choice_keeps_the_budget_and_says_what_it_chose(small_sample, bakes, tmp_path):
    """The default choice, under the budget that leaves the rule 20 of 32 azimuths: what it keeps fits, is
    the best measured pair within the tolerance (texture_memory.json's account), and the bundle is what it
    says."""
    whole = json.loads((bakes[True][0] / "texture_memory.json").read_text())["impostor"]
    budget = whole["stored_mib"] / 2 * 20 / 8 + 1e-9
    params = replace(PARAMS, azimuths=32, elevations_deg=(0.0,), impostor_budget_mib=budget)
    summary = run_bake(BakeInputs(character=small_sample / "character.glb", cloth=small_sample / "cloth.pc2",
                                  cloth_mesh=small_sample / "cloth.obj", textures=small_sample / "textures", cycle=None,
                                  name="sample", version="1.0", params=params), tmp_path / "bundles", work=tmp_path / "work")
    held = json.loads((summary.bundle / "texture_memory.json").read_text())["impostor"]
    budget_doc = held["budget"]
    assert held["stored_mib"] <= budget and budget_doc["fits"] and budget_doc["rule"] == "measured"
    layout = budget_doc["layout"]
    # Every tile tried is at least the one asked.
    assert sorted(int(t) for t in layout["probed"]["at_views"]) == [64, 72, 80, 96]
    # Every other azimuth count from 12 and the one asked (those between are interpolated), and 8.
    assert sorted(int(a) for a in layout["probed"]["between_azimuths"]) == [8, 12, 20, 28, 32]
    measured = layout["measured"]
    best = max(entry["margin"] for entry in measured)
    chosen = layout["chosen"]
    assert chosen in measured and chosen["margin"] >= best - 0.01
    assert all(entry["mib"] >= chosen["mib"] for entry in measured if entry["margin"] >= best - 0.01)
    manifest = json.loads((summary.bundle / "manifest.json").read_text())["impostor"]
    assert (manifest["tile_size"], len(manifest["azimuths_deg"])) == (chosen["tile"], chosen["azimuths"])
    assert len(manifest["frame_indices"]) == chosen["frames"] == budget_doc["chosen"]["frames"]
    assert f"chosen by measuring: {chosen['tile']}² tiles, {chosen['azimuths']} azimuths" in format_summary(summary)
    # The shortlist was measured end to end as items of their own (the runner's workers draw them side by
    # side), and the plan kept their scores: measuring inline gives the same choice.
    checks = sorted(entry["item"] for entry in summary.nodes if entry["node"] == "impostor_check")
    assert checks == [f"check-{k}" for k in range(len(measured))]
    stored = [json.loads((tmp_path / "work" / "impostor-probes" / f"{check}.json").read_text()) for check in checks]
    assert [round(document["ssim"], 4) for document in stored] == [entry["between_worst"] for entry in measured]
    setting = probe_setting(tmp_path / "work")
    try:
        probed, tables = impostor_plan._probed(tmp_path / "work", impostor_plan.probe_items(tmp_path / "work"))
        inline = impostor_plan.measured_framing(setting, probed, tables)
    finally:
        setting.scene_at.close()
    assert inline[2]["layout"]["chosen"] == chosen and inline[2]["layout"]["measured"] == measured


def test_crowdview_says_a_bundle_has_no_detail_maps(bakes, tmp_path):
    if not CROWDVIEW.is_file():
        pytest.skip(f"crowdview is not built at {CROWDVIEW} (scripts/setup.sh builds it)")
    bundle = str(bakes[True][0])
    refused = subprocess.run([str(CROWDVIEW), "--bundle", bundle, "--headless", "--lod", "detail"], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "no detail maps" in refused.stderr and "--detail-map" in refused.stderr, refused.stderr
    report = tmp_path / "report.json"
    run = subprocess.run([str(CROWDVIEW), "--bundle", bundle, "--benchmark", "--max-seconds", "3", "--modes", "uv_impostor,detail_impostor",
                          "--width", "160", "--height", "120", "--report", str(report)], capture_output=True, text=True, timeout=120)
    if run.returncode == 3:
        pytest.skip(f"crowdview could not open a GL context here: {run.stderr.strip()[-200:]}")
    assert run.returncode == 0, run.stderr[-2000:]
    assert "detail_impostor left out" in run.stderr
    results = json.loads(report.read_text())["results"]
    assert "uv_impostor" in results and "detail_impostor" not in results
