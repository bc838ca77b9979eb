"""Stage 5, pack: atlases, block compression (paper section 5: DXT1 for RGB, DXT3 for RGBA), the
impostor's fidelity, the texture memory of figure 4 and the manifest → work/bundle/ (verified).

Reads the JobRecord, CycleRecord, PosesRecord and every impostor part; writes the bundle and the PackRecord.
"""
from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from crowdbake.bake import compression, map_codecs, pose_ranges, texture_memory
from crowdbake.bake.atlas import AtlasLayout, assemble
from crowdbake.bake.impostor_budget import DETAIL_FORMATS, map_formats
from crowdbake.errors import StageOrderError
from crowdbake.export import textures as export_textures
from crowdbake.formats.binary import TextureArray, encode_texture_array, layer_size
from crowdbake.formats.bundle import FORMAT_VERSION, SKINNED_FORMAT_VERSION, BundleFile, build_manifest, verify_bundle, write_bundle
from crowdbake.formats.ranges import read_ranges
from crowdbake.stages.cycle import bundle_cycle_document
from crowdbake.stages.fidelity import score_fidelity
from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, gl_renderers, impostor_tasks, load_plan, load_poses, next_baked_frame, part_path, part_record
from crowdbake.stages.poses import DIFFUSE_ERRORS
from crowdbake.stages.runtime_fidelity import RUNTIME_PICTURES, score_runtime
from crowdbake.stages.records import CycleRecord, ImpostorPlan, ImpostorTask, MaterialInfo, PackRecord, PosesRecord
from crowdbake.stages.validate import load_job
from crowdbake.stages.workdir import (
    Progress, StageOutcome, WorkDir, json_bytes, npz_bytes, read_json, report, stage_key, write_bytes_atomic, write_json_atomic,
)

# Variations drawn in the figure-4 series at least: twice the paper's 8 diffuse textures (figure 2b), so the
# crossover of a bundle with 16-bit UV maps (about 8) shows.
FIGURE4_MIN_VARIATIONS = 16


class Parts:
    """The impostor parts by task id, each read from its file when asked for and not kept: the pack stage
    holds one frame's parts at a time, not the whole bake's (tens of MB a frame at the default sizes)."""

    def __init__(self, work: Path, tasks: list[ImpostorTask]):
        missing = [task.id for task in tasks if not part_path(work, task).is_file()]
        if missing:
            raise StageOrderError(f"{len(missing)} impostor tasks have not run, first {missing[0]}")
        self._paths = {task.id: part_path(work, task) for task in tasks}

    def __getitem__(self, task_id: str) -> dict[str, np.ndarray]:
        with np.load(self._paths[task_id]) as data:
            return {name: data[name] for name in data.files}


def _split_layers(encoded: np.ndarray, material: MaterialInfo) -> list[bytes]:
    size = layer_size(material.pixel_format, material.width, material.height)
    data = encoded.tobytes()
    return [data[k * size : (k + 1) * size] for k in range(material.variations)]


def _worst_errors(errors: list[dict], pixel_format: str) -> dict:
    return {
        "pixel_format": pixel_format,
        "layers": len(errors),
        "rgb_max": max(e["rgb_max"] for e in errors),
        "rgb_mean_abs": float(np.mean([e["rgb_mean_abs"] for e in errors])),
        "rgb_rmse_worst": max(e["rgb_rmse"] for e in errors),
        "rgb_psnr_db_worst": min(e["rgb_psnr_db"] for e in errors),
        "alpha_max": max(e["alpha_max"] for e in errors),
    }


def _nonnegative(value: Any) -> float:
    """Seam ratios for the manifest: a number >= 0 (an undefined ratio, for a still cloth, is 0)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return 0.0
    return number if np.isfinite(number) and number >= 0 else 0.0


def _mesh_files(work: Path, poses: PosesRecord, files: list[BundleFile]) -> list[dict]:
    """The pose caches, as baked, and their manifest entries."""
    meshes = []
    for part in poses.parts:
        path = f"meshes/{part.file}"
        files.append(BundleFile(path, (work / "poses" / part.file).read_bytes(), "pose-cache"))
        meshes.append({"part": part.part, "kind": part.kind, "lod": part.lod, "material": part.material,
                       "vertex_count": part.vertex_count, "triangle_count": part.triangle_count, "file": path})
    return meshes


def _texture_files(work: Path, poses: PosesRecord, texture_arrays, files: list[BundleFile], compression_report: dict) -> list[dict]:
    """Diffuse texture arrays and the outfit map; the diffuse compression errors (measured by the poses
    stage, crowdbake.stages.poses.DIFFUSE_ERRORS) go to compression_report."""
    measured = read_json(Path(work) / "poses" / DIFFUSE_ERRORS)
    entries = []
    for index, material in enumerate(poses.materials):
        path = f"textures/{material.name}_diffuse.cbtx"
        data = encode_texture_array(material.width, material.height, material.pixel_format,
                                    _split_layers(texture_arrays[f"material_{index}_encoded"], material))
        files.append(BundleFile(path, data, "diffuse"))
        entries.append({"name": material.name, "diffuse": path, "variations": material.variations})
        if material.pixel_format != "rgba8":
            compression_report[f"diffuse_{material.name}"] = _worst_errors(measured[material.name], material.pixel_format)
    outfits = texture_arrays["outfits"]
    files.append(BundleFile("textures/outfits.cbtx", encode_texture_array(16, len(outfits), "rgba8", outfits[None]), "outfit-colours"))
    return entries


def encode_frame(layout: AtlasLayout, frame_parts: list[dict[str, np.ndarray]], formats: dict[str, str], fidelity_frame: bool,
                 for_export: bool = False) -> tuple[dict, dict, dict, dict]:
    """One baked frame's atlases from its tasks' parts, encoded in the bundle's formats.

    Returns (layers {kind: bytes}, compression errors {kind: compression_error dict} of the block-compressed
    kinds, over covered texels), for the fidelity frame its atlases as stored plus "uv16" and the decoded
    normal map "normal_decoded" when compressed (else {}), and with `for_export` the layers the engine
    export converts, already converted (crowdbake.export.textures.PreparedLayers' fields, else {})."""
    atlases = {}
    for kind in formats:
        tiles = {}
        for data in frame_parts:
            for (a, e), tile in zip(data["views"].tolist(), data[kind]):
                tiles[(a, e)] = tile
        atlases[kind] = assemble(layout, tiles)
    covered = atlases["uv"][..., 3] > 0
    if layout.crop is not None and int(covered.sum()) != sum(int((tile[..., 3] > 0).sum()) for data in frame_parts for tile in data["uv"]):
        raise RuntimeError(f"the impostor crop {layout.crop} cuts off covered texels: the silhouette box missed part of the character")
    # The tiles carry 16-bit UV maps; what the bundle stores (and fidelity measures) is `stored`.
    stored = dict(atlases, uv16=atlases["uv"])
    export_layers = {}
    if formats["uv"] == "uv32":
        stored["uv"] = map_codecs.uv_map_to_uv32(atlases["uv"])
    elif formats["uv"] == "uvblock":
        uvblock = map_codecs.uv_map_to_uvblock(atlases["uv"])
        if fidelity_frame or for_export:  # fidelity and the export read the decoded texels, as uv32 words
            stored["uv"] = export_layers["uv32"] = map_codecs.uvblock_to_uv32(uvblock, layout.width, layout.height)
    layers, errors, fidelity_atlases = {}, {}, {}
    for kind, pixel_format in formats.items():
        if pixel_format == "rgba16":
            encoded = atlases[kind].astype("<u2").tobytes()
        elif pixel_format == "uv32":
            encoded = stored[kind].astype("<u4").tobytes()
        elif pixel_format == "uvblock":
            encoded = uvblock
        elif pixel_format == "bc5":  # normals: two components in each tile's view (map_codecs.normal_atlas_to_view_xy)
            in_view = map_codecs.normal_atlas_to_view_xy(atlases[kind], layout)
            encoded = compression.encode(in_view, pixel_format)
        else:
            encoded = compression.encode(atlases[kind], pixel_format)
        layers[kind] = encoded
        if pixel_format in ("bc1", "bc2", "bc5"):
            decoded = compression.decode(encoded, pixel_format, layout.width, layout.height)
            errors[kind] = compression.compression_error(in_view if pixel_format == "bc5" else atlases[kind], decoded, covered)
            if kind == "normal" and pixel_format == "bc5" and (fidelity_frame or for_export):
                decoded = export_textures.model_space_codes(decoded, layout)  # what fidelity and the export read
                if for_export:
                    export_layers["model_normal_bc1"] = compression.encode_bc1(decoded)
            if fidelity_frame and kind == "normal":
                fidelity_atlases["normal_decoded"] = decoded
    if fidelity_frame:
        fidelity_atlases.update(stored)
    return layers, errors, fidelity_atlases, export_layers if for_export else {}


def frame_path(work: Path, frame: int) -> Path:
    return WorkDir(work).root / "pack" / "frames" / f"f{int(frame):04d}.npz"


def stage_pack_frame(work: Path, frame: int) -> Path:
    """Assemble and encode one baked frame's atlases into work/pack/frames/f<frame>.npz (+ .json: its key
    and compression errors) as soon as that frame's impostor tasks are done, while others still render.

    Needs the frame's parts and the impostor plan only (not the poses stage). Idempotent: a file written
    from the same parts and formats is kept. stage_pack reads these files, and writes any that are missing.
    """
    work = Path(work)
    folder = WorkDir(work)
    plan = load_plan(work)
    params = load_job(work).bake_params
    formats = map_formats(params.compress, params.uv_format, params.detail_map)
    tasks = [task for task in impostor_tasks(work) if task.frame == frame]
    if not tasks:
        raise ValueError(f"pack frame {frame} is not one of the baked frames {plan.frame_indices}")
    part_keys = [None if (stats := part_record(work, task)) is None else stats.key for task in tasks]
    key = stage_key("pack-frame", folder.key_of("impostor"), part_keys, formats, params.export)
    path = frame_path(work, frame)
    sidecar = path.with_suffix(".json")
    if path.is_file() and sidecar.is_file():
        try:
            if read_json(sidecar).get("key") == key:
                return path
        except (OSError, ValueError):
            pass
    parts = Parts(work, tasks)
    layout = AtlasLayout.from_manifest(plan.layout)
    layers, errors, fidelity_atlases, export_layers = encode_frame(layout, [parts[task.id] for task in tasks], formats, frame == plan.fidelity_frame,
                                                                   for_export=params.export)
    arrays = {f"layer_{kind}": np.frombuffer(data, dtype=np.uint8) for kind, data in layers.items()}
    arrays.update({f"fidelity_{name}": atlas for name, atlas in fidelity_atlases.items()})
    arrays.update({f"export_{name}": np.frombuffer(data, dtype=np.uint8) if isinstance(data, bytes) else data for name, data in export_layers.items()})
    write_bytes_atomic(path, npz_bytes(arrays))
    write_json_atomic(sidecar, {"key": key, "errors": errors})
    return path


def prepared_export_layers(work: Path) -> export_textures.PreparedLayers:
    """The layers the frames in work/pack/frames converted for the engine export (encode_frame's for_export)
    and the diffuse layers the poses stage decoded (work/poses/textures.npz), keyed by the digests of their
    bundle layers. A file that cannot be read adds nothing: the export converts those layers itself."""
    import zipfile

    prepared = export_textures.PreparedLayers()
    try:
        with np.load(WorkDir(work).root / "poses" / "textures.npz") as textures:
            for name in textures.files:
                if name.startswith("material_") and name.endswith("_encoded"):
                    decoded = textures[name[: -len("_encoded")] + "_decoded"]
                    for layer, texels in zip(np.split(textures[name], len(decoded)), decoded):
                        prepared.rgba8[export_textures.layer_digest(layer.tobytes())] = texels
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        pass
    for path in sorted((WorkDir(work).root / "pack" / "frames").glob("f*.npz")):
        try:
            with np.load(path) as data:
                if "export_model_normal_bc1" in data.files:
                    prepared.model_normal_bc1[export_textures.layer_digest(data["layer_normal"].tobytes())] = data["export_model_normal_bc1"].tobytes()
                if "export_uv32" in data.files:
                    prepared.uv32[export_textures.layer_digest(data["layer_uv"].tobytes())] = data["export_uv32"]
        except (OSError, ValueError, KeyError, zipfile.BadZipFile):
            continue
    return prepared


SCORES_FILE = "scores.json"


def score_frames(record: PosesRecord | ImpostorPlan) -> list[int]:
    """The baked frames the scores read: the fidelity frame and the next one (runtime between_views is halfway
    to it), and with several clips each clip's and transition's scored frame and its next (runtime.ranges)."""
    frames = {record.fidelity_frame, next_baked_frame(record, record.fidelity_frame)}
    ranges = record.bundle_ranges()
    if ranges is not None:
        for entry in pose_ranges.scored_frames(ranges, list(record.frame_indices)):
            frames |= {entry["frame"], entry["next"]}
    return sorted(frames)


def stage_pack_scores(work: Path) -> Path:
    """fidelity.json's scores (crowdbake.stages.fidelity.score_fidelity and its `runtime` section,
    crowdbake.stages.runtime_fidelity.score_runtime) → work/pack/SCORES_FILE, as soon as the poses, the
    fidelity frame's tasks and the two frames the scores read are done (stage_pack_frame packs those if they
    are not yet): the bake runner runs this in a worker while other impostor tasks still render, and
    stage_pack only reads it. Idempotent: kept when written from the same poses, parts and frames."""
    work = Path(work)
    folder = WorkDir(work)
    poses = load_poses(work)
    layout = poses.atlas_layout()
    params = load_job(work).bake_params
    formats = map_formats(params.compress, params.uv_format, params.detail_map)
    tasks = impostor_tasks(work)
    frame_paths = {frame: stage_pack_frame(work, frame) for frame in score_frames(poses)}
    scored = [task for task in tasks if task.references]
    key = stage_key("pack-scores", folder.key_of("poses"), [read_json(path.with_suffix(".json"))["key"] for path in frame_paths.values()],
                    [None if (stats := part_record(work, task)) is None else stats.key for task in scored], formats, RUNTIME_PICTURES)
    path = folder.root / "pack" / SCORES_FILE
    if path.is_file():
        try:
            if read_json(path).get("key") == key:
                return path
        except (OSError, ValueError):
            pass
    layer_of = {frame: k for k, frame in enumerate(poses.frame_indices)}
    layers: dict[str, list[bytes]] = {kind: [b""] * len(poses.frame_indices) for kind in formats}
    for frame, frame_path in frame_paths.items():
        with np.load(frame_path) as data:
            for kind in formats:
                layers[kind][layer_of[frame]] = data[f"layer_{kind}"].tobytes()
            if frame == poses.fidelity_frame:
                fidelity_atlases = {name[len("fidelity_"):]: data[name] for name in data.files if name.startswith("fidelity_")}
    # Only the two frames' layers are filled: the scores read no other.
    maps = {kind: TextureArray(layout.width, layout.height, formats[kind], tuple(layers[kind])) for kind in formats}
    parts = Parts(work, scored)
    with np.load(folder.root / "poses" / "textures.npz") as texture_arrays:
        fidelity_doc = score_fidelity(poses, layout, scored, parts, fidelity_atlases, texture_arrays, formats)
        fidelity_doc["runtime"] = score_runtime(folder.root, poses, layout, scored, parts, maps["uv"], maps["normal"], texture_arrays,
                                                FIDELITY_SUPERSAMPLE, maps["surface"])
    write_json_atomic(path, {"key": key, "fidelity": fidelity_doc})
    return path


def _impostor_files(work: Path, poses: PosesRecord, layout: AtlasLayout, formats: dict[str, str],
                    files: list[BundleFile], compression_report: dict, progress: Progress | None, steps: int) -> dict:
    """Impostor atlases (layer k = frame_indices[k]), encoded frame by frame (stage_pack_frame: done already
    when the runner packed frames as their tasks finished); returns the manifest's maps."""
    layers: dict[str, list[bytes]] = {kind: [] for kind in formats}
    normal_errors, detail_errors = [], []
    for step, frame in enumerate(poses.frame_indices, start=1):
        path = stage_pack_frame(work, frame)
        errors = read_json(path.with_suffix(".json"))["errors"]
        with np.load(path) as data:
            for kind in formats:
                layers[kind].append(data[f"layer_{kind}"].tobytes())
        if "normal" in errors:
            normal_errors.append(errors["normal"])
        if "detail" in errors:
            detail_errors.append(errors["detail"])
        report(progress, "pack", step, steps)
    maps = {}
    for kind, role in (("normal", "impostor-normal"), ("uv", "impostor-uv"), ("detail", "impostor-detail"), ("surface", "impostor-surface")):
        if kind not in formats:
            continue
        path = f"impostor/{kind}.cbtx"
        files.append(BundleFile(path, encode_texture_array(layout.width, layout.height, formats[kind], layers[kind]), role))
        layers[kind] = []  # the CBTX holds them now
        maps[kind] = path
    if normal_errors:
        compression_report["impostor_normal"] = _worst_errors(normal_errors, formats["normal"])
    if detail_errors:
        compression_report["impostor_detail"] = _worst_errors(detail_errors, formats["detail"])
    return maps


def _texture_memory(poses: PosesRecord, layout: AtlasLayout, formats: dict[str, str]) -> dict:
    """Figure 4 from this bundle's bytes (layer payloads: what a GPU holds)."""
    frames = len(poses.frame_indices)
    stored_kinds = list(formats)
    # A bundle without detail maps still draws figure 4: what they would hold, in the format they would have.
    formats = {"detail": DETAIL_FORMATS[formats["normal"] != "rgba8"], **formats}
    layer_bytes = {kind: layer_size(formats[kind], layout.width, layout.height) * frames for kind in formats}
    diffuse_per_variation = sum(layer_size(m.pixel_format, m.width, m.height) for m in poses.materials)
    bundle_bytes = texture_memory.MapBytes(layer_bytes["normal"], layer_bytes["uv"], layer_bytes["detail"], diffuse_per_variation,
                                           layer_bytes["surface"])
    variations = max(m.variations for m in poses.materials)
    report = texture_memory.texture_memory_report(bundle_bytes, max(FIGURE4_MIN_VARIATIONS, variations), variations)
    stored = {kind: layer_bytes[kind] for kind in stored_kinds}
    # What one clip's impostor holds on a GPU (no mipmaps): the maps the bundle stores.
    report["impostor"] = {"stored_bytes": stored, "stored_mib": sum(stored.values()) / texture_memory.MIB, "frames": frames,
                          "views": len(layout.views), "tile_size": layout.tile_size, "crop": layout.crop_box_manifest(),
                          "budget": poses.budget}
    ranges = poses.bundle_ranges()
    if ranges is not None:
        # Several clips: the budget holds per clip (a runtime holds the layers of the clips its characters play).
        per_layer = sum(stored.values()) / frames
        report["impostor"]["ranges"] = [{**entry, "stored_mib": per_layer * len(entry["baked_frames"]) / texture_memory.MIB}
                                        for entry in pose_ranges.frames_per_range(ranges, poses.frame_indices)]
    return report


def _cycle_section(cycle: CycleRecord) -> dict:
    return {
        "source_start_frame": cycle.start_frame,
        "source_end_frame": cycle.start_frame + cycle.cycle_frames,
        "frames": cycle.cycle_frames,
        "closing": cycle.closing,
        "position_jump_ratio": _nonnegative(cycle.position_jump_ratio),
        "velocity_jump_ratio": _nonnegative(cycle.velocity_jump_ratio),
    }



def stage_pack(work: Path, progress: Progress | None = None) -> StageOutcome[PackRecord]:
    """Atlases, block compression, fidelity, figure-4 memory and the manifest → work/bundle/ (verified)."""
    started = time.perf_counter()
    folder = WorkDir(work)
    job = load_job(work)
    tasks = impostor_tasks(work)
    task_keys = [None if (stats := part_record(work, task)) is None else stats.key for task in tasks]
    key = stage_key("pack", folder.key_of("poses"), task_keys)
    bundle_dir = folder.bundle
    cached = folder.cached("pack", key, PackRecord, [bundle_dir / "manifest.json"])
    if cached is not None:
        return StageOutcome(cached, True, 0.0)
    params = job.bake_params
    poses = load_poses(work)
    cycle = folder.load("cycle", CycleRecord)
    layout = poses.atlas_layout()
    Parts(work, tasks)  # StageOrderError unless every impostor task has run
    steps = len(poses.frame_indices) + 3
    report(progress, "pack", 0, steps)

    files: list[BundleFile] = []
    meshes = _mesh_files(folder.root, poses, files)
    # Read lazily: each array when asked for (the diffuse layers, encoded and decoded, are tens of MB).
    texture_arrays = np.load(folder.root / "poses" / "textures.npz")
    with texture_arrays:
        compression_report: dict[str, Any] = {}
        material_entries = _texture_files(folder.root, poses, texture_arrays, files, compression_report)
        formats = map_formats(params.compress, params.uv_format, params.detail_map)
        maps = _impostor_files(work, poses, layout, formats, files, compression_report, progress, steps)
        outfit_count = int(len(texture_arrays["outfits"]))
    # Fidelity at 1:1 texel-to-pixel, per view, between views, and as crowdview draws (already scored when the
    # runner ran stage_pack_scores in a worker).
    fidelity_doc = read_json(stage_pack_scores(work))["fidelity"]
    fidelity_doc["compression"] = compression_report
    # What drew the maps and references: the same scores from llvmpipe and from a GPU may differ.
    renderers = gl_renderers(work)
    fidelity_doc["gl_renderers"] = renderers
    files.append(BundleFile("fidelity.json", json_bytes(fidelity_doc), "fidelity"))
    report(progress, "pack", len(poses.frame_indices) + 1, steps)
    memory_doc = {**_texture_memory(poses, layout, formats), "gl_renderers": renderers}
    files.append(BundleFile("texture_memory.json", json_bytes(memory_doc), "texture-memory"))
    cycle_document = bundle_cycle_document(read_json(folder.root / "cycle" / "cycle.json"))
    files.append(BundleFile("cycle.json", json_bytes(cycle_document), "cycle"))

    # One cycle is one clip named `cycle`, as a reader sees a version-1 bundle.
    ranges = cycle.bundle_ranges() or read_ranges({"format_version": 1, "cycle": _cycle_section(cycle)})
    timing = {"pose_frames": ranges.pose_frames, "clips": [clip.to_manifest() for clip in ranges.clips],
              "transitions": [transition.to_manifest() for transition in ranges.transitions]}
    sections = {
        "frames_per_second": poses.frames_per_second,
        **timing,
        "materials": material_entries,
        "outfits": {"file": "textures/outfits.cbtx", "count": outfit_count, "regions": 16},
        "meshes": meshes,
        "impostor": {**layout.to_manifest(), "frame_indices": poses.frame_indices, "bounds": poses.bounds, "maps": maps},
    }
    if params.accept_out_of_bounds:  # what the bake was told to publish beyond its quality bounds, for the next reader
        sections["accepted_out_of_bounds"] = cycle_document.get("out_of_bounds") or []
    # Format 4 only where a body is skinned (SPEC.md "Version 4"): a reader of format 3 reads the rest.
    skinned = any(part.file.endswith(".cbsk") for part in poses.parts)
    manifest = build_manifest(job.name, job.version, sections, files, created=job.created,
                              format_version=SKINNED_FORMAT_VERSION if skinned else FORMAT_VERSION)
    if bundle_dir.exists():
        shutil.rmtree(bundle_dir)
    write_bundle(bundle_dir, manifest, files)
    verify_bundle(bundle_dir)
    report(progress, "pack", steps, steps)
    record = PackRecord(
        files={f.path: len(f.data) for f in sorted(files, key=lambda f: f.path)},
        fidelity={**{k: fidelity_doc[k] for k in ("impostor", "nearest_view", "impostor_uncompressed_normals")},
                  "runtime": {k: fidelity_doc["runtime"][k] for k in ("at_views", "between_views", "between_azimuths", "ranges")
                              if k in fidelity_doc["runtime"]}},
        uv_precision=fidelity_doc["uv_precision"],
        compression=compression_report,
        texture_memory={
            "paper_mib": {"1": memory_doc["paper"]["uv_mapped_mib"][0], "detail_8": memory_doc["paper"]["detail_mapped_mib"][7],
                          "uv_8": memory_doc["paper"]["uv_mapped_mib"][7]},
            "bundle_break_even_variations": memory_doc["bundle"]["break_even_variations"],
            "break_even_variations": memory_doc["break_even_variations"],
            "impostor": memory_doc["impostor"],
        },
        gl_renderers=renderers,
    )
    seconds = time.perf_counter() - started
    folder.save("pack", key, record, seconds)
    return StageOutcome(record, False, seconds)
