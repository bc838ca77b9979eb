"""A body stored as skinning (CBSK, crowdbake.bake.body_skin and crowdbake.stages.body_skin): the matrices
follow the vertex frames the bake would have stored, on the sample (one clip, root motion kept) and on
the robot of robot_clips (real Blender data: three clips and transitions whose joins blend two clips),
at both LODs; and where skinning cannot say what the vertex frames say, the body keeps vertex frames."""
from __future__ import annotations

import subprocess
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from crowdbake.bake.body_skin import SKIN_NORMAL_TOLERANCE_DEG, SKIN_POSITION_TOLERANCE_M, cycle_times, frames_disagreement, without_root_offsets
from crowdbake.bake.poses import FALLBACK_NORMAL
from crowdbake.bake.skinning import joint_matrices, pose_at_times
from crowdbake.formats.bundle import verify_bundle
from crowdbake.formats.gltf import load_character
from crowdbake.formats.skinned_cache import SkinnedPoseCache, skin_frames, weight_codes
from crowdbake.stages.body_skin import why_not_skinned
from crowdbake.stages.records import CycleRecord
from crowdbake.stages.validate import load_job
from crowdbake.stages.workdir import WorkDir
from repo_paths import REPO_ROOT


def vertex_frames_of_the_body(work):
    """What the poses stage would store as the body's vertex frames (high LOD), from the bake's work folder."""
    from crowdbake.stages.poses import high_parts

    folder = WorkDir(work)
    job = load_job(work)
    character = load_character(folder.inputs / job.inputs["character"], animation=job.bake_params.animation)
    high, _kinds, _materials = high_parts(job, folder.load("cycle", CycleRecord), folder, character, skin_body=False)
    return high["body"]


def assert_skinned_like_the_vertex_frames(bundle_dir, work):
    bundle = verify_bundle(bundle_dir)
    assert bundle.manifest["format_version"] == 4
    high = bundle.pose_caches["meshes/body_lod0.cbsk"]
    low = bundle.pose_caches["meshes/body_lod1.cbsk"]
    assert isinstance(high, SkinnedPoseCache) and isinstance(low, SkinnedPoseCache)
    body = vertex_frames_of_the_body(work)
    no_normal = (body.normals == FALLBACK_NORMAL.astype(np.float32)).all(axis=-1)  # a blended join without one
    distance, angle = frames_disagreement(high.positions, high.normals, body.positions, body.normals, no_normal)
    assert distance <= SKIN_POSITION_TOLERANCE_M and angle <= SKIN_NORMAL_TOLERANCE_DEG, (distance, angle)
    # The low LOD's vertices are high-LOD vertices with their influences: each skins to its high twin.
    kept = [int(np.flatnonzero((high.rest_positions == p).all(axis=1) & (high.rest_normals == n).all(axis=1))[0])
            for p, n in zip(low.rest_positions, low.rest_normals)]
    assert np.abs(low.positions - high.positions[:, kept]).max() <= 1e-6
    # The whole point: a few KiB a frame where vertex frames store every vertex (10 bytes each, quantized).
    frame_bytes = 48 * high.joint_count
    assert frame_bytes < 10 * high.vertex_count / 4, (frame_bytes, high.vertex_count)
    return distance, angle


def test_the_sample_body_skins_to_its_vertex_frames(baked_sample):
    assert_skinned_like_the_vertex_frames(*baked_sample)


def test_the_robots_body_skins_to_its_vertex_frames_across_clips_and_blended_joins(robot_bake):
    assert_skinned_like_the_vertex_frames(*robot_bake)


def test_cycle_times_are_the_times_the_body_is_posed_at(small_sample):
    """pose_body_cycle's frames are the character posed at cycle_times, to the bit: a looped walk whose
    cycle wraps past the animation's end, and one that starts mid-loop."""
    from crowdbake.bake.body_skin import pose_body_cycle

    character = load_character(small_sample / "character.glb")
    for start, frames in ((0, 24), (17, 30)):
        positions, normals = pose_body_cycle(character, 24.0, start, frames)
        again, again_normals = pose_at_times(character, cycle_times(float(character.animation_duration), 24.0, start, frames))
        assert np.array_equal(positions, again) and np.array_equal(normals, again_normals)


def test_root_offsets_move_every_skinned_vertex(small_sample):
    character = load_character(small_sample / "character.glb")
    matrices = joint_matrices(character, np.arange(3) / 24.0)[:, :, :3]
    offsets = np.float32([[0.0, 0.0, 0.5], [0.1, 0.0, 1.0], [0.2, 0.05, 1.5]])
    codes = weight_codes(character.weights)
    before, _ = skin_frames(character.positions, character.normals, character.joints, codes, matrices)
    after, _ = skin_frames(character.positions, character.normals, character.joints, codes, without_root_offsets(matrices, offsets))
    assert np.abs((before - after) - offsets[:, None, :]).max() < 1e-5


def test_a_body_skinning_cannot_express_keeps_vertex_frames():
    skinned = SimpleNamespace(morph_targets=[], joint_count=40)
    assert why_not_skinned(SimpleNamespace(bake_params=SimpleNamespace(skinning=True)), skinned) is None
    assert "vertex frames" in why_not_skinned(SimpleNamespace(bake_params=SimpleNamespace(skinning=False)), skinned)
    huge = SimpleNamespace(morph_targets=[], joint_count=2000)
    assert "2000 joints" in why_not_skinned(SimpleNamespace(bake_params=SimpleNamespace(skinning=True)), huge)


@pytest.fixture(scope="module")
def baked_sample(small_bake):
    return small_bake


# ------------------------------------------------------------------ crowdview: skinned against vertex frames

CROWDVIEW = REPO_ROOT / "build" / "runtime" / "crowdview"


def as_vertex_frames(bundle_dir, out_dir):
    """The bundle with each skinned body (CBSK) stored as the quantized vertex frames it skins to (CBPC
    version 2, format 3): what the bake writes with --no-skinning (test_the_*_body_skins_to_its_vertex_
    frames holds those frames to these), so crowdview draws the same poses both ways."""
    from crowdbake.formats.binary import encode_quantized_pose_cache
    from crowdbake.formats.bundle import FORMAT_VERSION, BundleFile, build_manifest, write_bundle

    bundle = verify_bundle(bundle_dir)
    renamed, files = {}, []
    for entry in bundle.manifest["files"]:
        cache = bundle.pose_caches.get(entry["path"])
        if isinstance(cache, SkinnedPoseCache):
            renamed[entry["path"]] = entry["path"].replace(".cbsk", ".cbpc")
            data = encode_quantized_pose_cache(cache.indices, cache.uvs, cache.positions, cache.normals, cache.frames_per_second)
            files.append(BundleFile(renamed[entry["path"]], data, entry["role"]))
        else:
            files.append(BundleFile(entry["path"], (bundle_dir / entry["path"]).read_bytes(), entry["role"], entry["media_type"]))
    sections = {key: value for key, value in bundle.manifest.items() if key not in ("format", "format_version", "name", "version", "created", "producer", "files")}
    sections["meshes"] = [dict(mesh, file=renamed.get(mesh["file"], mesh["file"])) for mesh in sections["meshes"]]
    manifest = build_manifest(bundle.manifest["name"], "vertex-frames", sections, files, bundle.manifest["created"], format_version=FORMAT_VERSION)
    return write_bundle(out_dir, manifest, files)


def crowdview_picture(bundle, path, lod: str) -> np.ndarray:
    if not CROWDVIEW.is_file():
        pytest.skip(f"crowdview is not built at {CROWDVIEW} (scripts/setup.sh builds it)")
    run = subprocess.run([str(CROWDVIEW), "--bundle", str(bundle), "--headless", "--count", "40", "--seed", "3", "--lod", lod,
                          "--camera", "street", "--width", "480", "--height", "270", "--screenshot", str(path),
                          "--shaders", str(REPO_ROOT / "runtime" / "src" / "shaders")], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return np.asarray(Image.open(path).convert("RGB")).astype(np.float64)


def assert_same_pictures(skinned_bundle, frames_bundle, tmp_path):
    """crowdview's high and low LOD frames of the skinned bundle against the vertex-frame one: mean absolute
    difference at most 1/255 and SSIM at least 0.99 (issue figures; the cloth and impostors are alike)."""
    from skimage.metrics import structural_similarity

    assert verify_bundle(frames_bundle).manifest["format_version"] == 3
    for lod in ("high", "low"):
        skinned = crowdview_picture(skinned_bundle, tmp_path / f"skinned_{lod}.png", lod)
        frames = crowdview_picture(frames_bundle, tmp_path / f"frames_{lod}.png", lod)
        assert (np.abs(skinned - np.roll(skinned, 1, axis=0)).sum(axis=-1) > 30).mean() > 0.01  # characters were drawn
        difference = float(np.abs(skinned - frames).mean())
        similarity = float(structural_similarity(skinned, frames, channel_axis=2, data_range=255))
        assert difference <= 1.0 and similarity >= 0.99, (lod, difference, similarity)


def test_crowdview_draws_the_skinned_sample_as_its_vertex_frames(small_bake, tmp_path):
    assert_same_pictures(small_bake[0], as_vertex_frames(small_bake[0], tmp_path / "frames"), tmp_path)


def test_crowdview_draws_the_skinned_robot_as_its_vertex_frames(robot_bake, tmp_path):
    assert_same_pictures(robot_bake[0], as_vertex_frames(robot_bake[0], tmp_path / "frames"), tmp_path)


def test_a_skin_a_reader_would_refuse_is_not_published(small_bake):
    """A joint scaled to nothing (a rig hiding a prop) makes a singular matrix, which the skinned pose cache
    refuses: the bake asks the reader's rules first (reader_refusal) and keeps vertex frames then."""
    from dataclasses import replace

    from crowdbake.bake.body_skin import BodySkin
    from crowdbake.stages.body_skin import reader_refusal, skinned_body

    work = small_bake[1]
    folder, job = WorkDir(work), load_job(work)
    character = load_character(folder.inputs / job.inputs["character"], animation=job.bake_params.animation)
    skinned = skinned_body(job, folder.load("cycle", CycleRecord), folder.inputs, character, vertex_frames_of_the_body(work))
    assert skinned.skin is not None and reader_refusal(skinned, 24.0) is None
    matrices = skinned.skin.matrices.copy()
    weighted = int(np.bincount(skinned.skin.joints[skinned.skin.weights > 0].ravel()).argmax())
    matrices[:, weighted, :, :3] *= 1e-3  # |det| 1e-9
    collapsed = replace(skinned, skin=BodySkin(skinned.skin.rest_positions, skinned.skin.rest_normals, skinned.skin.joints,
                                               skinned.skin.weights, matrices))
    assert "singular" in reader_refusal(collapsed, 24.0)
