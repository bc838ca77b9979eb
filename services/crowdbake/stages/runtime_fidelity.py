"""The impostor as crowdview draws it (blended views and frames, reprojected), scored against the mesh at
the 1:1 switch distance: fidelity.json's `runtime` section, written by the pack stage.

The pictures are drawn by crowdview's own impostor shader in the bake's GL context
(crowdbake.render.runtime_shader), from the bundle's own bytes: the UV map in its pixel format, the normal
and surface maps after block compression, the diffuse texture as decoded; which views and frames it blends
is crowdbake.bake.view_blend's choice. (crowdbake.reference.runtime_picture draws the same picture in
numpy, the reference the shader is tested against.) Three sets of cameras:

- `at_views`: every baked view of the fidelity frame, from the mesh references the impostor tasks rendered
  (the runtime draws one sample of weight 1 there);
- `between_views`: halfway between baked azimuths, halfway between baked elevations and halfway between the
  fidelity frame and the next baked frame (four views times two frames blended), one camera per azimuth
  gap (at most BETWEEN_AZIMUTHS of them, spread evenly) and elevation gap;
- `between_azimuths`: the impostor tasks' references halfway between azimuths at a baked elevation and
  frame (two views blended), the cameras of fidelity.json's `nearest_view`: at most BETWEEN_AZIMUTHS gaps
  spread round each ring (crowdbake.stages.impostors.spread_gaps).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from crowdbake.bake import fidelity, impostor_views, pose_ranges, view_blend
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.formats.binary import TextureArray, decode_texture_array
from crowdbake.render.runtime_shader import RuntimeAtlas, RuntimePicture
from crowdbake.stages.impostors import BETWEEN_AZIMUTHS, MAP_MAKER, spread_gaps
from crowdbake.stages.records import ImpostorTask, PosesRecord


def parsed_map(data: bytes | TextureArray | None, where: str) -> TextureArray | None:
    """A bundle's CBTX file (bytes) parsed; a TextureArray or None as it is."""
    return data if data is None or isinstance(data, TextureArray) else decode_texture_array(data, where)


def runtime_textures(work: Path) -> dict[str, np.ndarray]:
    """What runtime_atlas reads of the poses stage's textures (work/poses/textures.npz): the decoded diffuse
    arrays ("material_<m>_decoded") and the outfit map ("outfits")."""
    with np.load(Path(work) / "poses" / "textures.npz") as data:
        return {name: data[name] for name in data.files if name == "outfits" or name.endswith("_decoded")}


def halfway_frame(poses: PosesRecord) -> tuple[int, view_blend.FrameWeights]:
    """The cycle frame halfway (rounded down) from the fidelity frame to the next baked frame, and its weights."""
    indices, cycle_frames = list(poses.frame_indices), poses.cycle_frames
    ranges = poses.bundle_ranges()
    if ranges is not None:
        # Several clips: the fidelity frame is the first clip's first, and its loop (pose frames 0 ..
        # frames - 1, its baked frames the first layers) wraps on itself.
        cycle_frames = ranges.clips[0].frames
        indices = [f for f in indices if f < cycle_frames]
    k = indices.index(poses.fidelity_frame)
    following = indices[(k + 1) % len(indices)]
    span = following - indices[k] if following > indices[k] else following + cycle_frames - indices[k]
    frame = (indices[k] + span // 2) % cycle_frames if len(indices) > 1 else indices[k]
    return frame, view_blend.blend_frame_weights(frame, indices, cycle_frames)


def between_cameras(layout: AtlasLayout, max_azimuths: int = BETWEEN_AZIMUTHS) -> list[tuple[float, float]]:
    """(azimuth, elevation) halfway between neighbouring baked azimuths and elevations (one ring: its elevation),
    for at most `max_azimuths` azimuth gaps spread evenly round the ring, each at every elevation gap."""
    azimuths = sorted(layout.azimuths_deg)
    elevations = sorted(layout.elevations_deg)
    mid_azimuths = [((a + b) / 2.0) % 360.0 for a, b in zip(azimuths, azimuths[1:] + [azimuths[0] + 360.0])]
    if len(azimuths) == 1:
        mid_azimuths = [(azimuths[0] + 180.0) % 360.0]
    mid_azimuths = [mid_azimuths[i] for i in spread_gaps(len(mid_azimuths), max_azimuths)]
    mid_elevations = [(a + b) / 2.0 for a, b in zip(elevations, elevations[1:])] or elevations
    return [(a, e) for e in mid_elevations for a in mid_azimuths]


def render_mesh_references(work: Path, poses: PosesRecord, frame: int, cameras: list[tuple[float, float]], supersample: int) -> list[np.ndarray]:
    """The mesh at cycle frame `frame` seen from each (azimuth, elevation), shaded as the fidelity references are
    (crowdbake.render.map_shader.draw_references): (S, S, 3) float32 images."""
    from crowdbake.render.impostor import shared_renderer
    from crowdbake.stages.impostors import load_pose_scene

    if not cameras:
        return []
    scene = load_pose_scene(work, poses, frame)
    tile = int(poses.layout["tile_size"])
    views = [impostor_views.ortho_view(poses.center, poses.radius, azimuth, elevation, tile * supersample) for azimuth, elevation in cameras]
    references = shared_renderer(tile).shader_references(views, scene.positions, scene.normals, scene.uvs, scene.faces,
                                                          scene.triangle_material, scene.diffuse_runtime, scene.outfit_row, supersample)
    return list(references)


REFERENCES_FILE = "runtime_references.npz"
# What draws the scored pictures, in the pack stage's scores key: scores of another maker are redrawn.
RUNTIME_PICTURES = "runtime_shader-2"  # 2: every clip and transition scored (runtime.ranges)


def between_references(work: Path, poses: PosesRecord, supersample: int) -> list[np.ndarray]:
    """render_mesh_references for score_runtime's between_views cameras, kept in work/pack/REFERENCES_FILE
    under a key of the poses and the cameras: the bake runner renders them in a worker as soon as the poses
    stage is done (prepare_between_references), so the pack stage only reads them."""
    from crowdbake.stages.workdir import WorkDir, npz_bytes, stage_key, write_bytes_atomic

    layout = poses.atlas_layout()
    frame, _ = halfway_frame(poses)
    cameras = between_cameras(layout)
    key = stage_key("runtime-references", WorkDir(work).key_of("poses"), frame, cameras, supersample, MAP_MAKER)
    path = Path(work) / "pack" / REFERENCES_FILE
    if path.is_file():
        with np.load(path) as data:
            if str(data["key"]) == key:
                return list(data["references"])
    references = render_mesh_references(work, poses, frame, cameras, supersample)
    write_bytes_atomic(path, npz_bytes({"key": np.array(key), "references": np.stack(references)}))
    return references


def picture_at(layout: AtlasLayout, azimuth: float, elevation: float, frames: view_blend.FrameWeights) -> RuntimePicture:
    """What crowdview hands its impostor shader for a camera at (azimuth, elevation) degrees and cycle
    position `frames` (crowdbake.bake.view_blend.blend_view_weights, as crowdview's view_blend.cpp)."""
    weights = view_blend.blend_view_weights(azimuth, elevation, layout.azimuths_deg, layout.elevations_deg)
    return RuntimePicture(float(azimuth), float(elevation), weights.tiles, weights.weights, frames.layers, frames.weight)


def runtime_atlas(poses: PosesRecord, layout: AtlasLayout, uv_map: TextureArray, normal_map: TextureArray,
                  surface_map: TextureArray | None, texture_arrays: dict[str, np.ndarray]) -> RuntimeAtlas:
    """The bundle's impostor as crowdview samples it (crowdbake.render.runtime_shader.RuntimeAtlas):
    variation 0 of every material as decoded, outfit 0."""
    return RuntimeAtlas(layout.tile_size, tuple(layout.azimuths_deg), tuple(layout.elevations_deg),
                        np.asarray(poses.center, dtype=np.float64), float(poses.radius), uv_map, normal_map, surface_map,
                        [texture_arrays[f"material_{m}_decoded"][0] for m in range(len(poses.materials))],
                        [material.pixel_format != "bc1" for material in poses.materials], texture_arrays["outfits"][0],
                        layout.crop_box)


def scored_cameras(work: Path, poses: PosesRecord, layout: AtlasLayout, tasks: list[ImpostorTask], parts: dict[str, dict[str, np.ndarray]],
                   supersample: int) -> list[tuple[str, dict[str, float], np.ndarray, RuntimePicture]]:
    """(section, camera, mesh reference, picture) of every camera score_runtime scores (module docstring):
    section "at_views", "between_azimuths" or "between_views"; camera {"azimuth_deg", "elevation_deg"};
    the reference (S, S, 3) float32; what crowdview's shader is handed there."""
    layer = list(poses.frame_indices).index(poses.fidelity_frame)
    baked_frame = view_blend.FrameWeights((layer, layer), 0.0)
    scored: list[tuple[str, dict[str, float], np.ndarray, RuntimePicture]] = []
    for task in tasks:
        if not task.references:
            continue
        data = parts[task.id]
        for index, (a, e) in enumerate(data["views"].tolist()):
            azimuth, elevation = layout.azimuths_deg[a], layout.elevations_deg[e]
            scored.append(("at_views", {"azimuth_deg": azimuth, "elevation_deg": elevation}, data["reference"][index],
                           picture_at(layout, azimuth, elevation, baked_frame)))
        for (_, e), mid, reference in zip(data["between_views"].tolist(), data["between_azimuths"].tolist(), data["reference_between"]):
            elevation = layout.elevations_deg[e]
            scored.append(("between_azimuths", {"azimuth_deg": mid, "elevation_deg": elevation}, reference,
                           picture_at(layout, mid, elevation, baked_frame)))
    _, frame_weights = halfway_frame(poses)
    for (a, e), reference in zip(between_cameras(layout), between_references(work, poses, supersample)):
        scored.append(("between_views", {"azimuth_deg": a, "elevation_deg": e}, reference, picture_at(layout, a, e, frame_weights)))
    return scored


def range_cameras(layout: AtlasLayout) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """A range's cameras: (azimuth, elevation) at baked views (RANGE_SCORE_AZIMUTHS azimuths spread round each
    baked ring) and halfway between views (between_cameras, as many gaps)."""
    azimuths = [layout.azimuths_deg[i] for i in spread_gaps(len(layout.azimuths_deg), pose_ranges.RANGE_SCORE_AZIMUTHS)]
    return [(a, e) for e in layout.elevations_deg for a in azimuths], between_cameras(layout, pose_ranges.RANGE_SCORE_AZIMUTHS)


def score_ranges(work: Path, poses: PosesRecord, layout: AtlasLayout, atlas: RuntimeAtlas, supersample: int) -> list[dict[str, Any]]:
    """fidelity.json's `runtime.ranges`: every clip and transition of a several-clip bundle scored as the
    runtime draws it (pose_ranges.scored_frames): at baked views of its baked frame, and halfway between
    views and frames. Mesh references drawn here; [] for a bundle of one clip (the sections above score it)."""
    from crowdbake.render.impostor import shared_renderer

    ranges = poses.bundle_ranges()
    if ranges is None:
        return []
    at_cameras, between = range_cameras(layout)
    indices = list(poses.frame_indices)
    renderer = shared_renderer(layout.tile_size)
    scored = []
    for entry in pose_ranges.scored_frames(ranges, indices):
        layer, following = indices.index(entry["frame"]), indices.index(entry["next"])
        references = render_mesh_references(work, poses, entry["frame"], at_cameras, supersample)
        references += render_mesh_references(work, poses, entry["between_frame"], between, supersample)
        still = view_blend.FrameWeights((layer, layer), 0.0)
        moving = view_blend.FrameWeights((layer, following), entry["between_weight"])
        pictures = renderer.runtime_impostors(atlas, [picture_at(layout, a, e, still) for a, e in at_cameras] +
                                              [picture_at(layout, a, e, moving) for a, e in between])
        scores = [fidelity.compare(reference, picture.astype(np.float64)) for reference, picture in zip(references, pictures)]
        scored.append({**{key: entry[key] for key in ("kind", "name", "frame", "between_frame", "between_weight")},
                       "at_views": fidelity.summarize(scores[:len(at_cameras)]), "between_views": fidelity.summarize(scores[len(at_cameras):])})
    return scored


def score_runtime(work: Path, poses: PosesRecord, layout: AtlasLayout, tasks: list[ImpostorTask], parts: dict[str, dict[str, np.ndarray]],
                  uv_file: bytes | TextureArray, normal_file: bytes | TextureArray, texture_arrays: dict[str, np.ndarray],
                  supersample: int, surface_file: bytes | TextureArray | None = None, warp: bool = True) -> dict[str, Any]:
    """fidelity.json's `runtime` section (module docstring): SSIM and PSNR of crowdview's blended impostor,
    each sample reprojected with the surface map when the bundle has one (crowdview's default; warp False:
    its `full` blend, unmoved samples weighed by the surface map's alpha), drawn by crowdview's own shader
    in this process's GL context (crowdbake.render.runtime_shader), whose GL strings go in `gl_renderer`."""
    from crowdbake.render.impostor import shared_renderer

    atlas = replace(runtime_atlas(poses, layout, parsed_map(uv_file, "uv map"), parsed_map(normal_file, "normal map"),
                                  parsed_map(surface_file, "surface map"), texture_arrays), warp=warp)
    scored = scored_cameras(work, poses, layout, tasks, parts, supersample)
    frame, frame_weights = halfway_frame(poses)
    renderer = shared_renderer(layout.tile_size)
    pictures = renderer.runtime_impostors(atlas, [picture for *_, picture in scored])
    sections: dict[str, list[dict[str, Any]]] = {"at_views": [], "between_views": [], "between_azimuths": []}
    for (section, camera, reference, _), picture in zip(scored, pictures):
        sections[section].append({**camera, **fidelity.compare(reference, picture.astype(np.float64))})
    return {
        "description": "crowdview's blended impostor (runtime/README.md 'Impostor blending'), drawn by its own shader "
        "(crowdbake.render.runtime_shader), against the mesh at 1:1: at_views at the baked views of the fidelity frame; "
        "between_views halfway between baked azimuths, elevations and frames; between_azimuths halfway between azimuths "
        "at baked elevations",
        "frame": poses.fidelity_frame,
        "between_frame": frame,
        "between_frame_weight": frame_weights.weight,
        "diffuse_lookup": "crowdview's: trilinear over glGenerateMipmap's chain, level from the UV map's quad gradients",
        "reprojection": "surface map (depth and motion), runtime/src/shaders/impostor_warp.glsl" if surface_file is not None else "none",
        "gl_renderer": renderer.gl.to_json(),
        "at_views": fidelity.summarize(sections["at_views"]),
        "between_views": fidelity.summarize(sections["between_views"]),
        "between_azimuths": fidelity.summarize(sections["between_azimuths"]),
        "per_view": sections["at_views"],
        "per_between_view": sections["between_views"],
        "ranges": score_ranges(work, poses, layout, atlas, supersample),
    }
