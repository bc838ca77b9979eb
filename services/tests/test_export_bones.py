"""Cloth as bones (crowdbake.export.cloth_bones, `crowdbake export --cloth-bones`): the garment's loop fitted
with a few rigid bones by Dem Bones and written as an ordinary skinned glTF mesh.

Synthetic motions whose answer is known check the pure parts; the small sample's export with 4 bones is then
read back three ways: the Khronos glTF-Validator, our own skinning of the glTF's joints, weights and keys (the
error it gives is the one export.json reports), and Blender's importer playing the animation.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pygltflib
import pytest

from repo_paths import REPO_ROOT
from test_export import node_tool, read_accessor
from crowdbake.cli import main as cli_main
from crowdbake.export.cloth_bones import choose_bone_count, decompose_cloth, matrix_quaternions, quaternion_matrices, skin, top_influences
from crowdbake.formats.bundle import verify_bundle

pytest.importorskip("py_dem_bones", reason="py-dem-bones is not installed (services/requirements.txt pins it)")


def rigid_sheet(frames: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 6 x 6 sheet of vertices turning about +Y and sliding: (F, 36, 3) positions, (50, 3) triangles, and the
    motion's rotations (F, 3, 3) and translations (F, 3)."""
    x, z = np.meshgrid(np.linspace(-0.3, 0.3, 6), np.linspace(-0.3, 0.3, 6))
    rest = np.stack([x.ravel(), np.full(36, 1.0), z.ravel()], axis=1)
    rows = np.arange(36).reshape(6, 6)
    triangles = np.concatenate([np.stack([rows[:-1, :-1].ravel(), rows[1:, :-1].ravel(), rows[:-1, 1:].ravel()], 1),
                                np.stack([rows[1:, :-1].ravel(), rows[1:, 1:].ravel(), rows[:-1, 1:].ravel()], 1)])
    angles = np.linspace(0.0, 0.6, frames)
    rotations = np.stack([[[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]] for a in angles])
    translations = np.stack([[0.1 * k, 0.02 * k, 0.0] for k in range(frames)])
    return np.einsum("fij,vj->fvi", rotations, rest) + translations[:, None], triangles, rotations, translations


def test_one_bone_recovers_a_rigid_motion():
    """A sheet moving rigidly is one bone exactly: the error is nil and the bone's keys are the motion."""
    positions, triangles, rotations, translations = rigid_sheet()
    bones = decompose_cloth(positions, triangles, bones=1, iterations=5)
    assert bones.bone_count == 1 and bones.rms_m < 1e-6 and bones.max_m < 1e-5
    np.testing.assert_allclose(quaternion_matrices(bones.rotations[:, 0]), rotations, atol=1e-6)
    np.testing.assert_allclose(bones.translations[:, 0], translations, atol=1e-6)
    assert (bones.weights[:, 0] == 1).all() and not bones.weights[:, 1:].any()


def test_an_error_budget_picks_the_fewest_bones():
    positions, triangles, _, _ = rigid_sheet()
    assert choose_bone_count(positions, triangles, budget_mm=0.01, counts=(1, 2), iterations=3).bone_count == 1
    with pytest.raises(ValueError, match="budget"):
        choose_bone_count(positions, triangles, budget_mm=0.0)
    with pytest.raises(ValueError, match="bones must be between 1 and the vertex count 36"):
        decompose_cloth(positions, triangles, bones=37)


def test_each_tried_bone_count_is_reported_as_it_is_made():
    """`--cloth-bones auto` was silent for minutes while it tried count after count: on_try sees each one.
    A sheet whose two halves move apart needs two bones, so one bone is tried and found over budget first."""
    positions, triangles, _, _ = rigid_sheet()
    split = positions.copy()
    split[:, 18:, 1] += np.linspace(0.0, 0.2, positions.shape[0])[:, None]  # the far half rises, the near one turns
    tried = []
    chosen = choose_bone_count(split, triangles, budget_mm=1.0, counts=(1, 2), iterations=3, on_try=tried.append)
    assert [b.bone_count for b in tried] == [1, 2] and tried[0].rms_m * 1000 > 1.0
    assert tried[-1] is chosen


def test_cli_prints_each_garments_bones_as_they_are_fitted(small_bake, tmp_path, capsys):
    """`crowdbake export --cloth-bones auto` printed nothing until the end (92 s on the sample): each garment
    now gets a stderr line per count tried and one for the count chosen, with the RMS error export.json keeps."""
    out = tmp_path / "auto"
    arguments = ["export", str(small_bake[0]), "--out", str(out), "--cloth-bones", "auto", "--cloth-bones-budget", "1000",
                 "--cloth-bones-iterations", "1"]
    assert cli_main(arguments) == 0
    err = capsys.readouterr().err.splitlines()
    sidecar = json.loads((out / "export.json").read_text())
    garments = [(lod["lod"], part) for lod in sidecar["lods"] for part in lod["parts"] if part["kind"] == "garment"]
    assert garments
    for lod, part in garments:
        label = f"crowdbake export: {part['part']} lod {lod}: "
        tried = [line for line in err if line.startswith(f"{label}tried ")]
        chosen = [line for line in err if line.startswith(f"{label}4 bones, ")]
        assert len(tried) == 1 and tried[0].endswith(" mm RMS (budget 1000 mm)") and len(chosen) == 1, err
        assert tried[0].startswith(f"{label}tried 4 bones, "), tried
        rms_mm = float(chosen[0].removeprefix(f"{label}4 bones, ").split(" mm RMS")[0])
        assert rms_mm == pytest.approx(part["bones"]["rms_mm"], abs=0.006)


def test_top_influences_keep_the_four_largest_and_sum_to_one():
    weights = np.array([[0.5, 0.0], [0.2, 0.0], [0.1, 1.0], [0.1, 0.0], [0.1, 0.0]])  # (B = 5, V = 2)
    joints, kept = top_influences(weights)
    assert joints.dtype == np.uint16 and kept.dtype == np.float32 and joints.shape == kept.shape == (2, 4)
    assert joints[0, :3].tolist() == [0, 1, 2] and kept[0].sum() == np.float32(1.0)
    np.testing.assert_allclose(kept[0, :3], np.array([0.5, 0.2, 0.1]) / 0.9, rtol=1e-6)
    assert joints[1, 0] == 2 and kept[1].tolist() == [1.0, 0.0, 0.0, 0.0]


def test_rotations_round_trip_as_quaternions():
    rng = np.random.default_rng(5)
    q = rng.normal(size=(7, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, 3:] < 0, -1, 1)
    np.testing.assert_allclose(matrix_quaternions(quaternion_matrices(q)), q, atol=1e-9)
    # A slightly sheared matrix becomes its nearest rotation.
    sheared = quaternion_matrices(q[0]) + 1e-4 * rng.normal(size=(3, 3))
    assert abs(np.linalg.norm(matrix_quaternions(sheared)) - 1) < 1e-12


def played_by_bones(gltf: pygltflib.GLTF2, blob: bytes, mesh_name: str) -> np.ndarray:
    """(F, V, 3): the skinned mesh as a glTF reader plays it at the animation's frame keys, from the file alone."""
    mesh_index = next(k for k, mesh in enumerate(gltf.meshes) if mesh.name == mesh_name)
    node = next(n for n in gltf.nodes if n.mesh == mesh_index)
    primitive = gltf.meshes[mesh_index].primitives[0]
    rest = read_accessor(gltf, blob, primitive.attributes.POSITION)
    joints = read_accessor_vec4(gltf, blob, primitive.attributes.JOINTS_0)
    weights = read_accessor_vec4(gltf, blob, primitive.attributes.WEIGHTS_0)
    skin_joints = gltf.skins[node.skin].joints
    animation = gltf.animations[0]
    tracks = {}
    for channel in animation.channels:
        if channel.target.node in skin_joints:
            tracks[(skin_joints.index(channel.target.node), channel.target.path)] = read_accessor_vec4(gltf, blob, animation.samplers[channel.sampler].output)
    rotations = np.stack([tracks[(b, "rotation")] for b in range(len(skin_joints))], axis=1)[:-1]  # the last key repeats frame 0
    translations = np.stack([tracks[(b, "translation")] for b in range(len(skin_joints))], axis=1)[:-1]
    return skin(rest.astype(np.float64), joints.astype(int), weights.astype(np.float64), rotations, translations)


def read_accessor_vec4(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """A VEC3/VEC4 accessor's rows; normalized integers as the floats they stand for (max(c / max, -1))."""
    accessor = gltf.accessors[index]
    view = gltf.bufferViews[accessor.bufferView]
    dtype = np.dtype({pygltflib.FLOAT: "<f4", pygltflib.UNSIGNED_SHORT: "<u2", pygltflib.SHORT: "<i2"}[accessor.componentType])
    width = {"VEC3": 3, "VEC4": 4}[accessor.type]
    rows = np.frombuffer(blob, dtype, accessor.count * width, view.byteOffset + (accessor.byteOffset or 0)).reshape(accessor.count, width)
    if accessor.normalized and accessor.componentType == pygltflib.SHORT:  # snorm16 rotations
        return np.maximum(rows / 32767.0, -1.0)
    return rows


def test_bones_export_validates_reports_its_error_and_plays_in_blender(small_bake, tmp_path):
    """`--cloth-bones 4`: each garment is a skinned mesh of 4 joints animated by the `cycle` animation (the body
    keeps its morph targets); the glTF-Validator finds nothing; skinning the file's own data gives back the
    RMS and maximum error export.json reports; Blender plays it the same within 1 mm."""
    import importlib.util

    bundle_dir, _ = small_bake
    out = tmp_path / "bones"
    assert cli_main(["export", str(bundle_dir), "--out", str(out), "--cloth-bones", "4", "--cloth-bones-iterations", "3"]) == 0
    sidecar = json.loads((out / "export.json").read_text())
    bundle = verify_bundle(bundle_dir)
    for report in node_tool("validate-gltf.mjs", *sorted(out.glob("*.glb"))):
        assert report["errors"] == 0 and report["warnings"] == 0, report["messages"][:5]
    for lod in sidecar["lods"]:
        gltf = pygltflib.GLTF2.load(out / lod["glb"])
        blob = gltf.binary_blob()
        for part in lod["parts"]:
            mesh = next(m for m in gltf.meshes if m.name == part["part"])
            if part["kind"] != "garment":
                assert "bones" not in part and (mesh.primitives[0].targets or part["playback"] == "skin")  # a skinned body stays a skin
                continue
            bones = part["bones"]
            assert bones["count"] == 4 and bones["asked"] == 4 and not mesh.primitives[0].targets and bones["bytes"] > 0
            cache = bundle.pose_caches[next(m["file"] for m in bundle.manifest["meshes"] if m["lod"] == lod["lod"] and m["part"] == part["part"])]
            error = np.linalg.norm(played_by_bones(gltf, blob, part["part"]) - cache.positions, axis=-1)
            assert np.sqrt((error ** 2).mean()) * 1000 == pytest.approx(bones["rms_mm"], abs=0.01)
            assert error.max() * 1000 == pytest.approx(bones["max_mm"], abs=0.05)
            assert 0.1 < bones["rms_mm"] < 100  # a real approximation of real cloth, not a copy
    if importlib.util.find_spec("bpy") is None:
        pytest.skip("Blender's bpy module is not installed (pip install 'crowdbake[alembic]')")
    lod = sidecar["lods"][-1]
    run = subprocess.run([sys.executable, "-m", "crowdbake.export.blender_round_trip", str(out / lod["glb"]), str(tmp_path / "seen.npz")],
                         capture_output=True, text=True, timeout=300, cwd=REPO_ROOT, env={**os.environ, "PYTHONPATH": str(REPO_ROOT / "services")})
    assert run.returncode == 0, run.stderr[-2000:]
    seen = np.load(tmp_path / "seen.npz")
    gltf = pygltflib.GLTF2.load(out / lod["glb"])
    garment = next(p["part"] for p in lod["parts"] if p["kind"] == "garment")
    np.testing.assert_allclose(seen[f"mesh_{garment}"], played_by_bones(gltf, gltf.binary_blob(), garment), atol=1e-3)


@pytest.mark.parametrize("value", ["0", "many", "257", "1000000"])
def test_cli_refuses_a_bone_count_it_cannot_use(small_bake, tmp_path, capsys, value):
    assert cli_main(["export", str(small_bake[0]), "--out", str(tmp_path / "out"), "--cloth-bones", value]) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "--cloth-bones" in error and repr(value) in error
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("iterations", ["0", "101", "1000000000"])
def test_cli_refuses_iterations_beyond_the_stated_budget(small_bake, tmp_path, capsys, iterations):
    """A billion Dem Bones iterations ran for over ten minutes; the bound is in --help and one line says it."""
    arguments = ["export", str(small_bake[0]), "--out", str(tmp_path / "out"), "--cloth-bones", "4", "--cloth-bones-iterations", iterations]
    assert cli_main(arguments) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and "--cloth-bones-iterations from 1 to 100" in error
    assert not (tmp_path / "out").exists()
