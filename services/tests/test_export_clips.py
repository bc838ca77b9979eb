"""The export of a bundle of several clips (crowdbake.export.animations): every clip and every transition a
named glTF animation, listed in export.json with the frame range the VAT shaders play.

The pure plan is checked on the v2 test vector, whose ranges are known; the VAT shaders' numpy twin against
the glTF animation's own interpolation; then two real exports are read back: the vector bundle (tiny, with
Blender's importer and with cloth bones) and the robot of robot_clips (the session's one robot bake), each
through the Khronos glTF-Validator and against the bundle's pose caches at the poses the manifest names.
"""
from __future__ import annotations

import functools
import importlib.util
import json
import os
import subprocess
import sys
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from repo_paths import REPO_ROOT, VECTORS
from test_export import MORPH_TOLERANCE_M, PREVIEW_DIR, check_skinned_part, morph_played, node_tool, read_accessor, skin_played
from test_export_bones import read_accessor_vec4
from crowdbake.export.animations import animation_plans, vat_range_uniforms, vat_shader_twin
from crowdbake.export.cloth_bones import skin
from crowdbake.export.glb import path_weights
from crowdbake.export.writer import export_bundle
from crowdbake.formats.bundle import verify_bundle
from crowdbake.formats.ranges import Ranges, Transition

VECTOR_BUNDLE = VECTORS / "v2" / "good" / "bundle"
V1_BUNDLE = VECTORS / "v1" / "good" / "bundle"
ROBOT_NAMES = ["Idle", "Walking", "Running", "Idle -> Walking", "Walking -> Running", "Running -> Walking"]


@pytest.fixture(scope="module")
def vector_export(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clip_export") / "vector"
    export_bundle(VECTOR_BUNDLE, out)
    return out


# ----------------------------------------------------------------------------- the plan, on known ranges


def test_a_clip_loops_its_range_and_a_transition_carries_both_joins():
    """The vector: clip a = pose frames 0..3, b = 4..5, then a -> b and b -> a. A clip's last key is its first
    frame again; a transition's first key is the from clip's leave pose, its last the to clip's arrive pose."""
    ranges = verify_bundle(VECTOR_BUNDLE).ranges
    plans = animation_plans(ranges)
    assert [p.name for p in plans] == ["a", "b", "a -> b", "b -> a"]
    assert plans[0].keys.tolist() == [0, 1, 2, 3, 0] and plans[1].keys.tolist() == [4, 5, 4]
    assert plans[0].loop and not plans[2].loop
    for plan, t in zip(plans[2:], ranges.transitions):
        source, target = ranges.clips[t.from_clip], ranges.clips[t.to_clip]
        assert plan.keys[0] == source.first_frame + t.leave_frame and plan.keys[-1] == target.first_frame + t.arrive_frame
        assert plan.keys[1:-1].tolist() == list(range(t.first_frame, t.first_frame + t.frames))
        assert (plan.from_clip, plan.to_clip) == (source.name, target.name)


def test_a_second_transition_between_the_same_clips_gets_a_name_of_its_own():
    ranges = verify_bundle(VECTOR_BUNDLE).ranges
    again = Transition(**{**ranges.transitions[0].__dict__, "first_frame": ranges.pose_frames})
    twice = Ranges(ranges.pose_frames + again.frames, ranges.clips, (*ranges.transitions, again))
    assert [p.name for p in animation_plans(twice)][2:] == ["a -> b", "b -> a", "a -> b (2)"]


def test_a_v1_bundle_keeps_its_one_cycle():
    """A v1 bundle reads as one clip `cycle` over every frame: the one animation its export always had."""
    ranges = verify_bundle(V1_BUNDLE).ranges
    (plan,) = animation_plans(ranges)
    frames = ranges.pose_frames
    assert plan.name == "cycle" and plan.loop and plan.keys.tolist() == [*range(frames), 0]


def test_the_vat_shaders_play_what_the_gltf_animation_keys():
    """For every clip and transition of the vector, the pose the VAT shaders blend (their numpy twin) at any
    frame is the one a glTF player gives from the animation's keys: LINEAR between key j and j + 1, a clip
    wrapping at its duration, a transition holding its first and last key."""
    ranges = verify_bundle(VECTOR_BUNDLE).ranges
    for plan in animation_plans(ranges):
        frames = np.linspace(-3.0, plan.key_count + 2.0, 157)
        f0, f1, t = vat_shader_twin(frames, vat_range_uniforms(plan))
        shader = np.zeros((frames.size, ranges.pose_frames))
        np.add.at(shader, (np.arange(frames.size), f0), 1 - t)
        np.add.at(shader, (np.arange(frames.size), f1), t)
        played = np.mod(frames, plan.key_count - 1) if plan.loop else frames
        one_hot = np.eye(ranges.pose_frames)[plan.keys]
        gltf = np.stack([np.interp(played, np.arange(plan.key_count), one_hot[:, k]) for k in range(ranges.pose_frames)], axis=1)
        np.testing.assert_allclose(shader, gltf, atol=1e-9, err_msg=plan.name)


# ----------------------------------------------------------------------------- real exports


def check_clip_export(bundle_dir: Path, out: Path) -> list[str]:
    """What an export of several clips promises; returns the animations' names."""
    bundle = verify_bundle(bundle_dir)
    ranges, fps = bundle.ranges, bundle.manifest["frames_per_second"]
    sidecar = json.loads((out / "export.json").read_text())
    glbs = sorted(out.glob("*.glb"))
    for report in node_tool("validate-gltf.mjs", *glbs):
        assert report["errors"] == 0 and report["warnings"] == 0, report["messages"][:5]

    # export.json: every clip, then every transition, with its glTF animation and its VAT range.
    animations = sidecar["animations"]
    clip_names = [c.name for c in ranges.clips]
    assert [a["name"] for a in animations[: len(clip_names)]] == clip_names
    assert [a["gltf_animation"] for a in animations] == list(range(len(ranges.clips) + len(ranges.transitions)))
    for entry, clip in zip(animations, ranges.clips):
        assert entry["playback"] == "loop" and entry["keys"] == clip.frames + 1 and entry["seconds"] == pytest.approx(clip.frames / fps)
        assert entry["vat"] == {"first_frame": clip.first_frame, "frames": clip.frames, "loop": 1,
                                "before_frame": clip.first_frame + clip.frames - 1, "after_frame": clip.first_frame}
    for entry, t in zip(animations[len(clip_names):], ranges.transitions):
        source, target = ranges.clips[t.from_clip], ranges.clips[t.to_clip]
        assert entry["name"].startswith(f"{source.name} -> {target.name}") and entry["playback"] == "once"
        assert (entry["from"], entry["to"], entry["leave_frame"], entry["arrive_frame"]) == (source.name, target.name, t.leave_frame, t.arrive_frame)
        assert entry["seconds"] == pytest.approx((t.frames + 1) / fps)
        assert entry["vat"] == {"first_frame": t.first_frame, "frames": t.frames, "loop": 0, "before_frame": source.first_frame + t.leave_frame,
                                "after_frame": target.first_frame + t.arrive_frame}

    # Each .glb: the same animations by name and index; each keys the morph target of its own pose frames,
    # and played at its first and last key shows the poses the manifest's ranges name.
    for lod in sidecar["lods"]:
        assert all(part["vat"]["frame_count"] == ranges.pose_frames for part in lod["parts"])
        gltf = pygltflib.GLTF2.load(out / lod["glb"])
        blob = gltf.binary_blob()
        assert [a.name for a in gltf.animations] == [a["name"] for a in animations]
        for part in (p for p in lod["parts"] if p["playback"] == "skin"):  # every key of every animation, and its bytes
            cache = bundle.pose_caches[next(m["file"] for m in bundle.manifest["meshes"] if m["lod"] == lod["lod"] and m["part"] == part["part"])]
            check_skinned_part(gltf, blob, part, cache, animation_plans(ranges))
        for entry, animation in zip(animations, gltf.animations):
            assert animation.extras["crowdbake"]["playback"] == entry["playback"]
            sampler = animation.samplers[0]
            times = read_accessor(gltf, blob, sampler.input)
            np.testing.assert_allclose(times, np.arange(entry["keys"]) / fps, rtol=1e-6)
            weights = read_accessor(gltf, blob, sampler.output).reshape(entry["keys"], ranges.pose_frames)
            # Key j weighs 1 the targets on its pose frame's path (glb.QuantizedPart): the frame shown is the one
            # whose path those are.
            morphed = next(m for m in gltf.meshes if len(m.primitives[0].targets or []) == ranges.pose_frames)
            paths = path_weights(np.array(morphed.extras["crowdbake"]["morph_parents"]), np.arange(ranges.pose_frames))
            assert set(np.unique(weights)) <= {0.0, 1.0}
            shown = np.array([int(np.flatnonzero((paths == row).all(axis=1))[0]) for row in weights])
            vat = entry["vat"]
            if entry["playback"] == "loop":
                assert shown.tolist() == [*range(vat["first_frame"], vat["first_frame"] + vat["frames"]), vat["first_frame"]]
            else:
                assert shown.tolist() == [vat["before_frame"], *range(vat["first_frame"], vat["first_frame"] + vat["frames"]), vat["after_frame"]]
            for part in lod["parts"]:
                cache = bundle.pose_caches[next(m["file"] for m in bundle.manifest["meshes"] if m["lod"] == lod["lod"] and m["part"] == part["part"])]
                mesh_index = next(k for k, mesh in enumerate(gltf.meshes) if mesh.name == part["part"])
                node = next(n for n in gltf.nodes if n.mesh == mesh_index)
                primitive = gltf.meshes[mesh_index].primitives[0]
                if part["playback"] == "skin":  # a skinned body: its joints' keys (and corrective targets) play it
                    played = skin_played(gltf, blob, mesh_index, animation, (0, entry["keys"] - 1))
                    assert np.abs(played - cache.positions[shown[[0, -1]]]).max() < MORPH_TOLERANCE_M, (entry["name"], part["part"])
                    continue
                parents = np.array(gltf.meshes[mesh_index].extras["crowdbake"]["morph_parents"])
                for key in (0, entry["keys"] - 1):
                    played, _ = morph_played(gltf, blob, node, primitive, path_weights(parents, [shown[key]])[0])
                    assert np.abs(played - cache.positions[shown[key]]).max() < MORPH_TOLERANCE_M, (entry["name"], part["part"], key)
    return [a["name"] for a in animations]


def test_the_vector_bundle_exports_every_clip_and_transition(vector_export):
    assert check_clip_export(VECTOR_BUNDLE, vector_export) == ["a", "b", "a -> b", "b -> a"]
    sidecar = json.loads((vector_export / "export.json").read_text())
    assert sidecar["format_version"] == 5 and sidecar["frame_count"] == verify_bundle(VECTOR_BUNDLE).ranges.pose_frames


def test_the_robot_exports_every_clip_and_transition(robot_bake, tmp_path):
    """Issue 31's "done when": the robot's export passes the glTF-Validator with every clip and transition as
    an animation. Its body (a skinned pose cache) is a glTF skin, a quarter of its morph targets' bytes. The three.js preview draws it playing its first clip, Idle (its VAT range, its impostor
    layers)."""
    out = tmp_path / "robot"
    export_bundle(robot_bake[0], out)
    assert check_clip_export(robot_bake[0], out) == ROBOT_NAMES
    assert [part["playback"] for part in json.loads((out / "export.json").read_text())["lods"][0]["parts"]] == ["skin", "morph"]
    status = preview_status(out, tmp_path)
    assert status["ready"] is True, status
    assert status["clip"] == json.loads((out / "export.json").read_text())["animations"][0]["vat"]
    assert sum(status["lod"].values()) == 16


def preview_status(export: Path, tmp_path: Path) -> dict:
    """The three.js preview page's status on `export` (16 characters, time 0), served from a local HTTP server."""
    from test_export_preview import page_status, preview_browser

    if not (PREVIEW_DIR / "node_modules" / "three").is_dir():
        pytest.skip(f"npm packages missing: run `npm ci` in {PREVIEW_DIR} (scripts/setup.sh does)")
    root = tmp_path / "www"
    root.mkdir()
    (root / "preview").symlink_to(PREVIEW_DIR, target_is_directory=True)
    (root / "export").symlink_to(export, target_is_directory=True)

    class Quiet(SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(root)))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{httpd.server_address[1]}/preview/index.html?export=../export/&time=0&count=16"
        with preview_browser(tmp_path / "profile") as browser:
            return page_status(browser, url)
    finally:
        httpd.shutdown()


def test_cloth_bones_play_every_clip_and_transition(tmp_path):
    """--cloth-bones on a v2 bundle: the garment's bones are fitted over every pose frame, and each animation
    keys them at its own poses: skinning its keys gives the pose caches at those poses within the fit's error."""
    pytest.importorskip("py_dem_bones", reason="py-dem-bones is not installed (services/requirements.txt pins it)")
    from crowdbake.export.writer import ClothBonesRequest

    out = tmp_path / "bones"
    export_bundle(VECTOR_BUNDLE, out, cloth_bones=ClothBonesRequest(count=2, iterations=3))
    for report in node_tool("validate-gltf.mjs", *sorted(out.glob("*.glb"))):
        assert report["errors"] == 0 and report["warnings"] == 0, report["messages"][:5]
    bundle = verify_bundle(VECTOR_BUNDLE)
    plans = animation_plans(bundle.ranges)
    sidecar = json.loads((out / "export.json").read_text())
    lod = sidecar["lods"][0]
    part = next(p for p in lod["parts"] if p["kind"] == "garment")
    cache = bundle.pose_caches[next(m["file"] for m in bundle.manifest["meshes"] if m["lod"] == 0 and m["part"] == part["part"])]
    gltf = pygltflib.GLTF2.load(out / lod["glb"])
    blob = gltf.binary_blob()
    mesh_index = next(k for k, mesh in enumerate(gltf.meshes) if mesh.name == part["part"])
    primitive = gltf.meshes[mesh_index].primitives[0]
    joints = gltf.skins[next(n for n in gltf.nodes if n.mesh == mesh_index).skin].joints
    rest = read_accessor(gltf, blob, primitive.attributes.POSITION).astype(np.float64)
    influences = read_accessor_vec4(gltf, blob, primitive.attributes.JOINTS_0).astype(int)
    weights = read_accessor_vec4(gltf, blob, primitive.attributes.WEIGHTS_0).astype(np.float64)
    assert [a.name for a in gltf.animations] == [p.name for p in plans]
    for plan, animation in zip(plans, gltf.animations):
        tracks = {(joints.index(c.target.node), c.target.path): read_accessor_vec4(gltf, blob, animation.samplers[c.sampler].output)
                  for c in animation.channels if c.target.node in joints}
        rotations = np.stack([tracks[(b, "rotation")] for b in range(len(joints))], axis=1)
        translations = np.stack([tracks[(b, "translation")] for b in range(len(joints))], axis=1)
        assert rotations.shape[0] == plan.key_count
        error = np.linalg.norm(skin(rest, influences, weights, rotations, translations) - cache.positions[plan.keys], axis=-1)
        assert error.max() * 1000 <= part["bones"]["max_mm"] + 0.05, plan.name


def test_blender_sees_every_clip_and_transition(vector_export, tmp_path, capsys):
    """Blender's glTF importer makes an action of each animation; playing each one gives the bundle's poses
    at that animation's keys (the poses the manifest's ranges name), within 1 mm."""
    if importlib.util.find_spec("bpy") is None:
        pytest.skip("Blender's bpy module is not installed (pip install 'crowdbake[alembic]')")
    bundle = verify_bundle(VECTOR_BUNDLE)
    plans = {plan.name: plan for plan in animation_plans(bundle.ranges)}
    out = tmp_path / "seen.npz"
    glb = vector_export / "character_lod0.glb"
    run = subprocess.run([sys.executable, "-m", "crowdbake.export.blender_round_trip", str(glb), str(out), "--bundle", str(VECTOR_BUNDLE)],
                         capture_output=True, text=True, timeout=300, cwd=REPO_ROOT, env={**os.environ, "PYTHONPATH": str(REPO_ROOT / "services")})
    assert run.returncode == 0 and out.is_file(), run.stderr[-2000:]
    # The round trip compares with the bundle itself and says so, one line per animation.
    assert run.stdout.strip().splitlines()[-1].startswith("Blender plays every animation of LOD 0 within 1 mm of the bundle"), run.stdout
    assert all(any(line.startswith(f"{name}: ") for line in run.stdout.splitlines()) for name in plans), run.stdout
    seen = np.load(out)
    info = json.loads(str(seen["info"]))
    assert sorted(info["actions"]) == sorted(plans)
    for k, name in enumerate(info["actions"]):
        assert len(info["action_keys"][name]) == plans[name].key_count, name
        for mesh in (m for m in bundle.manifest["meshes"] if m["lod"] == 0):
            expected = bundle.pose_caches[mesh["file"]].positions[plans[name].keys]
            assert float(np.abs(seen[f"action_{k}_mesh_{mesh['part']}"] - expected).max()) < 1e-3, (name, mesh["part"])
    # An animation played 2 mm off is named, and the comparison fails.
    arrays = {key: seen[key] for key in seen.files}
    moved = info["actions"][-1]
    for key in [key for key in arrays if key.startswith(f"action_{len(info['actions']) - 1}_mesh_")]:
        arrays[key] = arrays[key] + np.float32(0.002)
    np.savez(tmp_path / "moved.npz", **arrays)
    from crowdbake.export.blender_round_trip import compare_with_bundle

    capsys.readouterr()
    assert compare_with_bundle(glb, tmp_path / "moved.npz", VECTOR_BUNDLE, 1.0) == 1
    off = capsys.readouterr()
    assert moved in off.err and "farther than 1 mm" in off.err, off.err
