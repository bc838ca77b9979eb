"""The bake's stages end to end (crowdbake.stages, `crowdbake bake`) on a small procedural sample:
a bundle that verify_bundle accepts, byte-identical rebakes, idempotent stages, clear input errors."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from crowdbake.cli.bake import format_summary
from crowdbake.errors import InputError, StageOrderError, VersionConflict
from crowdbake.formats.texel_codecs import unpack_uvblock
from crowdbake.formats.bundle import verify_bundle
from crowdbake.params import BakeParams
from crowdbake.stages import STAGES
from crowdbake.stages.cycle import stage_cycle
from crowdbake.stages.impostors import (
    SCENE_FILE, impostor_tasks, load_plan, load_scene, part_path, spread_gaps, stage_impostor_views,
)
from crowdbake.stages.impostor_plan import stage_impostor_plan
from crowdbake.stages.pack import stage_pack
from crowdbake.stages.poses import TEXTURES_FILE, stage_poses, stage_textures
from crowdbake.stages.publish import stage_publish
from crowdbake.stages.runner import run_bake
from crowdbake.stages.validate import BakeInputs, gltf_dependencies, load_job, stage_validate

pytest.importorskip("pyrender")

# Small enough to bake in seconds: 2 frames x 4 azimuths x 2 elevations of 32² texels.
SMALL = BakeParams(impostor_frames=2, azimuths=4, elevations_deg=(0.0, 30.0), tile_size=32, lod_triangles=1200, cycle_views=3, candidates=3,
                   detail_map=True)
CYCLE_FRAMES = 24
# The sample's 64² diffuse texture 0 through DXT3 (measured 38.7 dB; 30.4 to 38.7 over all 8): colour bound.
DIFFUSE_PSNR_DB = 30.0


@pytest.fixture(scope="module")
def sample(small_sample) -> Path:
    """The session's sample (sample_fixtures.SMALL_SAMPLE: 24-frame cycles)."""
    return small_sample


def inputs_for(sample: Path, params: BakeParams = SMALL, **changes) -> BakeInputs:
    values = dict(
        character=sample / "character.glb",
        cloth=sample / "cloth.pc2",
        cloth_mesh=sample / "cloth.obj",
        textures=sample / "textures",
        cycle=None,
        name="sample",
        version="1.0",
        params=params,
    )
    values.update(changes)
    return BakeInputs(**values)


def tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def baked(sample, tmp_path_factory):
    root = tmp_path_factory.mktemp("baked")
    summary = run_bake(inputs_for(sample), root / "bundles", work=root / "work")
    return root, summary


def test_bake_writes_a_bundle_that_verifies(sample, baked):
    root, summary = baked
    assert summary.bundle == root / "bundles" / "sample" / "1.0"
    bundle = verify_bundle(summary.bundle)
    manifest = bundle.manifest
    # Format 4: the one cycle is the one clip, named as a reader names a v1 bundle's; the skinned glTF's
    # body stored as skinning (CBSK), the cloth quantized.
    assert manifest["format_version"] == 4 and [clip.name for clip in bundle.ranges.clips] == ["cycle"]
    assert bundle.ranges.pose_frames == CYCLE_FRAMES and manifest["frames_per_second"] == 24.0
    assert {path: type(cache).__name__ for path, cache in bundle.pose_caches.items()} == {
        "meshes/body_lod0.cbsk": "SkinnedPoseCache", "meshes/body_lod1.cbsk": "SkinnedPoseCache",
        "meshes/cloth_lod0.cbpc": "PoseCache", "meshes/cloth_lod1.cbpc": "PoseCache"}
    assert {cache.version for path, cache in bundle.pose_caches.items() if path.endswith(".cbpc")} == {2}
    assert manifest["impostor"]["frame_indices"] == [0, 12]
    assert manifest["impostor"]["azimuths_deg"] == [0.0, 90.0, 180.0, 270.0]
    assert {(m["part"], m["lod"]) for m in manifest["meshes"]} == {("body", 0), ("body", 1), ("cloth", 0), ("cloth", 1)}
    low = sum(m["triangle_count"] for m in manifest["meshes"] if m["lod"] == 1)
    assert abs(low - SMALL.lod_triangles) <= 0.05 * SMALL.lod_triangles
    formats = {path: bundle.textures[path].pixel_format for path in manifest["impostor"]["maps"].values()}
    assert formats == {"impostor/normal.cbtx": "bc5", "impostor/uv.cbtx": "uvblock", "impostor/detail.cbtx": "bc2",
                       "impostor/surface.cbtx": "bc2"}
    assert manifest["materials"] == [{"name": "character", "diffuse": "textures/character_diffuse.cbtx", "variations": 8}]
    # Every frame of the low LOD is the high LOD's vertices (a subset carried over), each LOD's positions
    # within half a 16-bit step of its own frame bounds (pose_codec): together, a step of the wider LOD's.
    from scipy.spatial import cKDTree

    for part, suffix in (("body", "cbsk"), ("cloth", "cbpc")):
        high = bundle.pose_caches[f"meshes/{part}_lod0.{suffix}"].positions[5]
        low_positions = bundle.pose_caches[f"meshes/{part}_lod1.{suffix}"].positions[5]
        step = (high.max(axis=0) - high.min(axis=0)).max() / 65535
        distances, _ = cKDTree(high).query(low_positions, p=np.inf)
        assert distances.max() <= step + 1e-6
    # The compressed files decode to what went in: the diffuse texture within the stated error with its
    # region codes exact, the detail map's alpha whole region codes and zero outside the UV map's coverage.
    from PIL import Image

    from crowdbake.bake import compression

    diffuse = bundle.textures["textures/character_diffuse.cbtx"]
    decoded = compression.decode(diffuse.layers[0], diffuse.pixel_format, diffuse.width, diffuse.height)
    source = np.array(Image.open(sample / "textures" / "diffuse_00.png").convert("RGBA"))
    errors = compression.compression_error(source, decoded)
    assert errors["alpha_max"] == 0 and errors["rgb_psnr_db"] >= DIFFUSE_PSNR_DB
    detail = bundle.textures["impostor/detail.cbtx"]
    uv = bundle.textures["impostor/uv.cbtx"]
    for layer in range(2):
        alpha = compression.decode(detail.layers[layer], "bc2", detail.width, detail.height)[..., 3]
        u, v, material, covered = unpack_uvblock(uv.layers[layer], uv.width, uv.height)
        assert (material[covered] == 0).all() and (u[~covered] == 0).all() and (v[~covered] == 0).all()
        assert (alpha % 17 == 0).all() and (alpha[~covered] == 0).all() and covered.any()
    fidelity = json.loads((summary.bundle / "fidelity.json").read_text())
    assert fidelity["impostor"]["views"] == 8 and 0.3 < fidelity["impostor"]["ssim_mean"] <= 1.0
    assert fidelity["nearest_view"]["ssim_mean"] < fidelity["impostor"]["ssim_mean"]
    memory = json.loads((summary.bundle / "texture_memory.json").read_text())
    assert memory["paper"]["detail_mapped_mib"][0] == memory["paper"]["uv_mapped_mib"][0] == 16
    # The GL context that drew the maps, in both reports and the summary: this process's platform, every task.
    assert fidelity["gl_renderers"] == memory["gl_renderers"] == summary.gl_renderers
    assert [gl["impostor_tasks"] for gl in summary.gl_renderers] == [4]
    assert summary.gl_renderers[0]["platform"] == os.environ["PYOPENGL_PLATFORM"] and summary.gl_renderers[0]["renderer"]
    assert {k: v for k, v in summary.gl_renderers[0].items() if k != "impostor_tasks"} == fidelity["runtime"]["gl_renderer"]
    assert f"gl       4 impostor tasks drawn on {summary.gl_renderers[0]['renderer']}, OpenGL " in format_summary(summary)
    assert set(summary.timings_s) == set(STAGES)
    assert summary.impostor["views"] == 16 and summary.impostor["tasks"] == 4


def test_baking_twice_gives_identical_bytes(sample, baked, tmp_path):
    """Same inputs, fresh work folder, in this process (the fixture's bake ran poses and the impostor tasks
    in two worker processes), the impostor tasks in the opposite order and before the poses stage: every
    byte of the bundle, manifest included, is the same (created comes from the inputs' modification time)."""
    root, summary = baked
    work = tmp_path / "work"
    stage_validate(inputs_for(sample), work)
    stage_cycle(work)
    stage_impostor_plan(work)
    for task in reversed(impostor_tasks(work)):
        stage_impostor_views(work, task)
    assert not (work / "poses").exists()
    stage_poses(work)
    stage_pack(work)
    first = tree(summary.bundle)
    assert tree(work / "bundle") == first
    manifest = json.loads(first["manifest.json"])
    job = load_job(work)
    assert manifest["created"] == job.created and job.created_from == "input modification time"
    # Publishing the same bytes again is a no-op.
    assert stage_publish(work, root / "bundles") == summary.bundle
    assert tree(summary.bundle) == first


def test_impostor_plan_draws_the_poses_stage_geometry(baked):
    """The impostor tasks draw the plan's scene, made without the poses stage: at every baked frame it is
    the pose caches' high LOD to the bit, with the same framing and textures."""
    from crowdbake.formats.skinned_cache import read_any_pose_frame
    from crowdbake.stages.impostors import load_poses

    work = baked[0] / "work"
    plan, poses = load_plan(work), load_poses(work)
    assert (plan.bounds, plan.layout, plan.frame_indices, plan.fidelity_frame) == (poses.bounds, poses.layout, poses.frame_indices, poses.fidelity_frame)
    high = [part for part in poses.parts if part.lod == 0]
    for frame in plan.frame_indices:
        scene = load_scene(work, plan, frame)
        cached = [read_any_pose_frame(work / "poses" / part.file, frame) for part in high]
        assert np.array_equal(scene.positions, np.concatenate([c[2] for c in cached]))
        assert np.array_equal(scene.normals, np.concatenate([c[3] for c in cached]))
        assert np.array_equal(scene.uvs, np.concatenate([c[1] for c in cached]))
    with np.load(work / "poses" / "textures.npz") as textures:
        assert np.array_equal(scene.diffuse[0], textures["material_0_v0"])
        assert np.array_equal(scene.diffuse_runtime[0], textures["material_0_decoded_v0"])
    assert (work / "impostor" / SCENE_FILE).is_file()


def test_bake_reports_wall_cpu_and_render_seconds(baked):
    timings = baked[1].timings
    assert set(timings["stages"]) == set(STAGES)
    assert 0 < timings["render_s"] < timings["total_s"] and timings["cpu_s"] > 0
    assert timings["render_s"] == pytest.approx(sum(stage["render_s"] for stage in timings["stages"].values()))
    # Every GL render of the bake is counted, those of the worker processes included: one shader pass a
    # task draws all its views' maps, and fidelity-frame tasks draw their references too.
    tasks = impostor_tasks(baked[0] / "work")
    assert timings["stages"]["impostors"]["renders"] >= len(tasks) + sum(task.references for task in tasks)
    assert timings["stages"]["cycle"]["renders"] > 0 and timings["peak_rss_mib"]["process"] > 0


def test_the_timeline_names_every_item_where_and_when_it_ran(baked):
    """timings.timeline: every stage run here and every worker item, with its process, start and end (seconds
    from the bake's start) and CPU seconds; the textures were encoded in a worker, the poses stage waited for them."""
    timings = baked[1].timings
    timeline = timings["timeline"]
    assert [span["start_s"] for span in timeline] == sorted(span["start_s"] for span in timeline)
    assert all(0 <= span["start_s"] <= span["end_s"] <= timings["total_s"] and span["cpu_s"] >= 0 for span in timeline)
    items = {span["item"]: span for span in timeline}
    assert {"validate", "cycle"} <= set(items)
    if timings["workers"] > 1:
        assert items["textures"]["pid"] != items["cycle"]["pid"]
        assert items["textures"]["end_s"] <= items["poses"]["start_s"]
        assert {f"impostor_views:{task.id}" for task in impostor_tasks(baked[0] / "work")} <= set(items)
        assert {"references", "scores", "pack", "export", "publish", "commit_export"} <= set(items)
        assert max(span["process_peak_rss_mib"] for span in timeline if "process_peak_rss_mib" in span) == timings["peak_rss_mib"]["largest_worker"]


def test_the_textures_need_the_job_alone(sample, baked, tmp_path):
    """stage_textures runs on a validated job with no cycle yet (the runner encodes the textures while the
    cycle is searched); the poses stage then keeps its output as it is, and it holds the bake's textures."""
    work = tmp_path / "work"
    stage_validate(inputs_for(sample), work)
    record = stage_textures(work)
    assert not (work / "cycle").exists()
    path = work / "poses" / TEXTURES_FILE
    written, stamp = path.read_bytes(), path.stat().st_mtime_ns
    assert stage_textures(work) == record and path.stat().st_mtime_ns == stamp
    stage_cycle(work)
    stage_impostor_plan(work)
    poses = stage_poses(work).record
    assert path.stat().st_mtime_ns == stamp and path.read_bytes() == written
    assert poses.materials == record.materials and poses.outfit_count == record.outfit_count == 8
    with np.load(path) as mine, np.load(baked[0] / "work" / "poses" / TEXTURES_FILE) as bakes:
        assert mine.files == bakes.files and all(np.array_equal(mine[name], bakes[name]) for name in mine.files)


def test_the_last_frames_tasks_alternate_so_their_packs_run_side_by_side():
    from crowdbake.stages.records import ImpostorTask
    from crowdbake.stages.plan import task_order

    tasks = [ImpostorTask(id=f"f{frame:04d}-e{ring}", frame=frame, elevation=ring, views=[[0, ring]], references=frame == 0)
             for frame in (0, 4, 8, 12) for ring in range(3)]
    order = [task.id for task in task_order(tasks, 2)]
    assert order == ["f0000-e0", "f0000-e1", "f0000-e2", "f0004-e0", "f0004-e1", "f0004-e2",
                     "f0008-e0", "f0012-e0", "f0008-e1", "f0012-e1", "f0008-e2", "f0012-e2"]
    assert task_order(tasks, 0) == task_order(tasks, 1) == tasks
    assert sorted(task.id for task in task_order(tasks, 5)) == sorted(task.id for task in tasks)


def test_workers_get_the_reusing_malloc_and_this_process_keeps_its_own():
    """The fork server, and so every worker, starts with WORKER_MALLOC in its environment (glibc reads it at
    start); the caller's environment is as it was."""
    import os

    from crowdbake.stages import worker_pool as runner

    before = {name: os.environ.get(name) for name in runner.WORKER_MALLOC}
    pool = runner.start_pool(2)
    try:
        seen = {name: pool.submit(os.getenv, name).result(timeout=60) for name in runner.WORKER_MALLOC}
    finally:
        pool.shutdown(wait=True)
    assert seen == runner.WORKER_MALLOC
    assert {name: os.environ.get(name) for name in runner.WORKER_MALLOC} == before


def test_the_scored_azimuth_gaps_spread_round_the_ring():
    assert spread_gaps(4) == [0, 1, 2, 3] and spread_gaps(16) == list(range(16))
    assert spread_gaps(32) == list(range(0, 32, 2))
    assert spread_gaps(24, 16) == [0, 1, 3, 4, 6, 7, 9, 10, 12, 13, 15, 16, 18, 19, 21, 22]
    assert spread_gaps(48, 16) == list(range(0, 48, 3)) and spread_gaps(1) == [0]


def test_fidelity_tasks_render_the_mesh_between_the_scored_azimuths(baked):
    """Each fidelity task holds, for the views whose azimuth gap is scored (all four here), the mesh halfway
    to the next azimuth; fidelity.json's nearest_view and runtime between_azimuths score exactly those."""
    root, summary = baked
    work = root / "work"
    layout = load_plan(work).layout
    count = 0
    for task in impostor_tasks(work):
        with np.load(part_path(work, task)) as part:
            if not task.references:
                assert "reference_between" not in part.files
                continue
            between = part["between_views"].tolist()
            assert between == [view for view in part["views"].tolist() if view[0] in spread_gaps(len(layout["azimuths_deg"]))]
            assert part["reference_between"].shape[0] == len(part["between_azimuths"]) == len(between)
            count += len(between)
    fidelity = json.loads((summary.bundle / "fidelity.json").read_text())
    assert fidelity["nearest_view"]["views"] == fidelity["runtime"]["between_azimuths"]["views"] == count == 4 * 2


def test_stages_are_idempotent_and_ordered(baked, tmp_path):
    root, _ = baked
    work = root / "work"
    assert stage_poses(work).cached is True
    assert stage_pack(work).cached is True
    task = impostor_tasks(work)[0]
    part = part_path(work, task)
    stamp = part.stat().st_mtime_ns
    assert stage_impostor_views(work, task) == part and part.stat().st_mtime_ns == stamp
    with pytest.raises(StageOrderError):
        stage_poses(tmp_path / "empty")


def other_bytes_published(bundle: Path, tmp_path: Path) -> Path:
    """A bundles folder holding `bundle`'s name and version with other bytes (another `created`)."""
    other_root = tmp_path / "bundles"
    shutil.copytree(bundle, other_root / "sample" / "1.0")
    manifest_path = other_root / "sample" / "1.0" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["created"] = "2001-01-01T00:00:00Z"
    manifest_path.write_text(json.dumps(manifest))
    return other_root


def test_publishing_other_bytes_under_a_published_version_is_refused(baked, tmp_path):
    root, summary = baked
    with pytest.raises(VersionConflict):
        stage_publish(root / "work", other_bytes_published(summary.bundle, tmp_path))


def test_a_version_conflict_leaves_no_export_behind(sample, baked, tmp_path):
    """The runner builds the engine export while publish runs and puts it in place only after publishing:
    a bake refused for a version conflict leaves neither an export nor a staging folder; one that publishes
    has its export in place."""
    root, summary = baked
    assert (root / "exports" / "sample" / "1.0" / "index.json").is_file()
    with pytest.raises(VersionConflict):
        run_bake(inputs_for(sample), other_bytes_published(summary.bundle, tmp_path), work=root / "work", workers=2)
    exports = tmp_path / "exports"
    assert not [p for p in exports.rglob("*") if p.is_file() or p.name.endswith(".partial")] if exports.exists() else True


@pytest.mark.parametrize("workers", [2, 0])
def test_a_bundles_folder_beside_another_does_not_take_its_export(sample, baked, tmp_path, workers):
    """Bundles folders with the same parent share one exports folder: a bake whose export home holds the
    export of other bytes under its name and version fails with ExportConflict before anything is
    published, and leaves that export as it was; one whose home holds its own export keeps it."""
    from crowdbake.errors import ExportConflict

    root, summary = baked
    for same in (False, True):
        parent = tmp_path / ("same" if same else "other")
        home = parent / "exports" / "sample" / "1.0"
        shutil.copytree(root / "exports" / "sample" / "1.0", home)
        if not same:
            index = json.loads((home / "index.json").read_text())
            index["bundle"]["manifest_sha256"] = "0" * 64
            (home / "index.json").write_text(json.dumps(index))
        before = {p: p.read_bytes() for p in sorted(home.rglob("*")) if p.is_file()}
        if same:
            assert run_bake(inputs_for(sample), parent / "bundles", work=root / "work", workers=workers).bundle.is_dir()
        else:
            with pytest.raises(ExportConflict, match="other bytes published as sample/1.0"):
                run_bake(inputs_for(sample), parent / "bundles", work=root / "work", workers=workers)
            assert not (parent / "bundles" / "sample" / "1.0").exists()
        assert {p: p.read_bytes() for p in sorted(home.rglob("*")) if p.is_file()} == before
        assert not list((parent / "exports" / "sample").glob("*.partial"))


def test_bad_inputs_name_their_field(sample, tmp_path):
    bad_mesh = tmp_path / "small.obj"
    bad_mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    cases = [
        (inputs_for(sample, cloth_mesh=bad_mesh), "cloth_mesh"),
        (inputs_for(sample, character=tmp_path / "missing.glb"), "character"),
        (inputs_for(sample, name="Not A Name"), "name"),
        (inputs_for(sample, created="yesterday"), "created"),
        (inputs_for(sample, params=BakeParams(tile_size=30)), "tile_size"),
        (inputs_for(sample, params=BakeParams(lod_ratio=0.2, lod_triangles=100)), "lod_ratio"),
        (inputs_for(sample, params=BakeParams(elevations_deg=(0.0, 0.0))), "elevations_deg"),
        (inputs_for(sample, params=BakeParams(uv_format="rgba8")), "uv_format"),
    ]
    for inputs, field in cases:
        with pytest.raises(InputError) as caught:
            stage_validate(inputs, tmp_path / "work")
        assert caught.value.field == field, caught.value.message
    with pytest.raises(InputError, match="unknown parameter"):
        BakeParams.from_dict({"tiles": 4})
    params = BakeParams.from_dict(SMALL.to_dict())
    assert params == SMALL and json.loads(json.dumps(params.to_dict())) == SMALL.to_dict()
    assert BakeInputs.from_dict(json.loads(json.dumps(inputs_for(sample).to_dict()))) == inputs_for(sample)


def test_command_line_bake_with_a_given_cycle(sample, baked, tmp_path, capsys):
    from crowdbake.cli import main

    root, _ = baked
    cycle = root / "work" / "cycle" / "cycle.json"  # with looped.pc2 beside it: the search is skipped
    arguments = [
        "bake", str(sample / "character.glb"), "--cloth", str(sample / "cloth.pc2"), "--cloth-mesh", str(sample / "cloth.obj"),
        "--textures", str(sample / "textures"), "--cycle", str(cycle), "--name", "sample", "--version", "2",
        "--out", str(tmp_path / "bundles"), "--frames", "1", "--azimuths", "2", "--elevations", "0", "--tile", "16",
        "--lod-triangles", "900", "--created", "2006-09-04T12:00:00Z", "--uv-format", "rgba16",
        "--figure4", str(tmp_path / "figure4.png"),
    ]
    assert main(arguments) == 0
    out = capsys.readouterr().out
    assert "verified" in out and "fidelity impostor vs mesh" in out and "figure 4" in out
    bundle = verify_bundle(tmp_path / "bundles" / "sample" / "2")
    assert bundle.manifest["created"] == "2006-09-04T12:00:00Z"
    # --uv-format rgba16: the older, twice as large UV map is still written on request.
    uv_map = bundle.textures["impostor/uv.cbtx"]
    assert uv_map.pixel_format == "rgba16" and len(uv_map.layers[0]) == 8 * uv_map.width * uv_map.height
    assert json.loads((tmp_path / "bundles" / "sample" / "2" / "fidelity.json").read_text())["uv_map_format"] == "rgba16"
    assert bundle.ranges.clips[0].source_start_frame == json.loads(cycle.read_text())["start_frame"]
    assert (tmp_path / "figure4.png").stat().st_size > 0 and (tmp_path / "figure4.json").is_file()

    assert main(arguments[:-2] + ["--tile", "30"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("crowdbake bake: error: --tile") and "\n" not in error


def test_gltf_files_must_stay_beside_the_gltf(tmp_path):
    (tmp_path / "buffers").mkdir()
    (tmp_path / "buffers" / "body.bin").write_bytes(b"\0" * 8)
    (tmp_path / "skin.png").write_bytes(b"png")
    gltf = tmp_path / "character.gltf"
    gltf.write_text(json.dumps({"buffers": [{"uri": "buffers/body.bin"}, {"uri": "data:application/octet-stream;base64,AA=="}], "images": [{"uri": "skin.png"}]}))
    assert gltf_dependencies(gltf) == ["buffers/body.bin", "skin.png"]
    gltf.write_text(json.dumps({"buffers": [{"uri": "../outside.bin"}]}))
    with pytest.raises(InputError) as caught:
        gltf_dependencies(gltf)
    assert caught.value.field == "character"
