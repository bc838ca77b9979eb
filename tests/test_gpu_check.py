"""scripts/gpu-check: what prepare packs, run unpacks and describes. A crowd names a clip mix only where
its bundle holds those clips (crowdview refuses a description naming a clip its bundle lacks), the
bundles survive their trip through xz, and run's crowds name them wherever the scratch folder is."""
from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts" / "gpu-check"


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"gpu_check_{name}", SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


prepare, run = load("prepare"), load("run")
ROBOT = next(a for a in prepare.archetypes(Path("/assets")) if a.name == "robot")


def test_the_robot_plays_its_clip_mix_where_its_bundle_holds_the_clips():
    manifest = {"clips": [{"name": "Idle"}, {"name": "Walking"}, {"name": "Running"}]}
    entry = prepare.crowd_entry(ROBOT, manifest)
    assert [c["clip"] for c in entry["clips"]] == ["Walking", "Running"] and entry["switch_after_s"] == [0.5, 1.5]


def test_a_bundle_that_fell_back_to_one_loop_gets_no_clip_mix():
    entry = prepare.crowd_entry(ROBOT, {"clips": [{"name": "cycle"}]})
    assert "clips" not in entry and "switch_after_s" not in entry
    assert entry == {"name": "robot", "bundle": "bundles/robot", "share": 1}


def test_packed_bundles_unpack_where_the_crowd_names_them(tmp_path):
    bundle = tmp_path / "baked" / "robot" / "1.0.0"
    (bundle / "meshes").mkdir(parents=True)
    (bundle / "manifest.json").write_text('{"name": "robot"}')
    (bundle / "meshes" / "body_lod0.cbpc").write_bytes(bytes(range(256)) * 64)
    folder = tmp_path / "folder"
    (folder / "bundles").mkdir(parents=True)
    linked = tmp_path / "linked"  # a folder of bundles may link to bakes kept elsewhere
    linked.symlink_to(bundle)
    prepare.packed(linked, "robot", folder / "bundles" / "robot.tar.xz")
    (folder / "crowd.json").write_text(json.dumps({"count": 240, "camera": {"kind": "street"}, "archetypes": [{"name": "robot", "bundle": "bundles/robot"}]}))

    unpacked = run.unpack_bundles(folder / "bundles", tmp_path / "scratch")
    crowd = json.loads(run.crowd_of(folder, unpacked, 100000, "overview", tmp_path / "large.json").read_text())

    named = Path(crowd["archetypes"][0]["bundle"])
    assert named.is_absolute() and (named / "meshes" / "body_lod0.cbpc").read_bytes() == bytes(range(256)) * 64
    assert crowd["count"] == 100000 and crowd["camera"] == {"kind": "overview"}
