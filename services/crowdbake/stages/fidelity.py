"""The pack stage's fidelity scoring: the impostor as the runtime draws it against the mesh references the
impostor tasks rendered, at 1:1 texel-to-pixel, per view and between views (crowdbake.bake.fidelity).

Pure over arrays: the atlases, the parts' references and the decoded textures come in, a JSON-able
document (fidelity.json in the bundle) goes out.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from crowdbake.bake import fidelity, impostor_views, shading
from crowdbake.bake.atlas import AtlasLayout, nearest_view, view_tile
from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE
from crowdbake.stages.records import ImpostorTask, PosesRecord


def score_fidelity(poses: PosesRecord, layout: AtlasLayout, tasks: list[ImpostorTask], parts: dict[str, dict[str, np.ndarray]],
                   atlases: dict[str, np.ndarray], texture_arrays: dict[str, np.ndarray], formats: dict[str, str]) -> dict[str, Any]:
    """fidelity.json: SSIM and PSNR per view of the fidelity frame, with and without normal-map compression,
    and the mesh halfway between two azimuths (the scored gaps) against the nearest baked view.

    atlases: the fidelity frame's "uv" (as stored), "uv16", "normal", "surface" (when the bundle has one)
    and, when compressed, "normal_decoded";
    parts: task id -> the task's arrays ("views", "reference", and for the scored azimuth gaps
    (crowdbake.stages.impostors.spread_gaps) "between_views", "between_azimuths", "reference_between").
    """
    centre, radius = poses.center, poses.radius
    count = len(poses.materials)
    runtime_diffuse = [texture_arrays[f"material_{m}_decoded"][0] for m in range(count)]
    outfit_row = texture_arrays["outfits"][0]
    normals_drawn = atlases["normal_decoded"] if "normal_decoded" in atlases else atlases["normal"]

    def coverage_of(a: int, e: int) -> np.ndarray | None:
        """The surface map's alpha of view (a, e): each texel's coverage (None without a surface map)."""
        return view_tile(layout, atlases["surface"], a, e)[..., 3] if "surface" in atlases else None

    per_view, between, uncompressed = [], [], []
    for task in tasks:
        if not task.references:
            continue
        data = parts[task.id]
        for index, (a, e) in enumerate(data["views"].tolist()):
            view = impostor_views.ortho_view(centre, radius, layout.azimuths_deg[a], layout.elevations_deg[e], layout.tile_size)
            light = shading.camera_light(view)
            image, exact = fidelity.impostor_images(view_tile(layout, atlases["uv"], a, e),
                                                    [view_tile(layout, normals_drawn, a, e), view_tile(layout, atlases["normal"], a, e)],
                                                    runtime_diffuse, outfit_row, light, coverage_of(a, e))
            score = fidelity.compare(data["reference"][index], image)
            per_view.append({"azimuth_deg": layout.azimuths_deg[a], "elevation_deg": layout.elevations_deg[e], **score})
            uncompressed.append(fidelity.compare(data["reference"][index], exact))
        for (a, e), azimuth, reference in zip(data["between_views"].tolist(), data["between_azimuths"].tolist(), data["reference_between"]):
            mid_view = impostor_views.ortho_view(centre, radius, azimuth, layout.elevations_deg[e], layout.tile_size)
            na, ne = nearest_view(layout, azimuth, layout.elevations_deg[e])
            near_image = fidelity.impostor_image(
                view_tile(layout, atlases["uv"], na, ne), view_tile(layout, normals_drawn, na, ne),
                runtime_diffuse, outfit_row, shading.camera_light(mid_view), coverage_of(na, ne),
            )
            between.append(
                {"azimuth_deg": azimuth, "elevation_deg": layout.elevations_deg[e], "nearest_azimuth_deg": layout.azimuths_deg[na],
                 **fidelity.compare(reference, near_image)}
            )

    texture_size = max(max(m.width, m.height) for m in poses.materials)
    return {
        "description": "Impostor vs mesh at 1:1 texel-to-pixel (crowdbake.bake.fidelity): SSIM and PSNR per view "
        "of the fidelity frame; nearest_view: the mesh halfway between two azimuths against the nearest baked view",
        "frame": poses.fidelity_frame,
        "tile_size": layout.tile_size,
        "supersample": FIDELITY_SUPERSAMPLE,
        "light": {"ambient": shading.AMBIENT, "diffuse": shading.DIFFUSE, "direction_in_camera": shading.LIGHT_IN_CAMERA.tolist()},
        "normal_map_format": formats["normal"],
        "uv_map_format": formats["uv"],
        "impostor": fidelity.summarize(per_view),
        "impostor_uncompressed_normals": fidelity.summarize(uncompressed),
        "nearest_view": fidelity.summarize(between),
        "per_view": per_view,
        "between_views": between,
        "uv_precision": {"texture_size": texture_size, **fidelity.uv_precision(atlases["uv16"], texture_size, layout.tile_size)},
    }
