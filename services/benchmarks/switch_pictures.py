"""Pictures of the LOD switch: the mesh against crowdview's impostor at the 1:1 switch distance, at a baked
view and halfway between baked views and frames (docs/bake.md, "What the runtime draws").

    PYTHONPATH=services python services/benchmarks/switch_pictures.py --work WORK [--azimuth-index 2]
        [--out docs/img/impostor_switch.png] [--scale 2]

WORK is a bake's work folder (`crowdbake bake ... --work WORK`, its pack stage run). Row 1: a baked view of
the fidelity frame. Row 2: halfway to the next azimuth, halfway between the lowest two elevation rings and
halfway to the next baked frame. Columns: the mesh (crowdbake.reference.mesh_reference, 3x3 samples a
pixel), crowdview's default impostor (`--impostor-blend warp`: every sample reprojected by the surface map,
crowdbake.reference.impostor_warp), the plain blend (`full`, crowdbake.reference.impostor_blend), the paper's nearest
view and frame, all decoded from the bundle's files, and 4x the absolute difference of the default from the mesh.
Each picture is one tile, scaled up by --scale with nearest-neighbour so pixels stay visible.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.bake import fidelity, impostor_views, shading, view_blend  # noqa: E402
from crowdbake.reference import impostor_blend  # noqa: E402
from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, load_poses  # noqa: E402
from crowdbake.reference.runtime_picture import AtlasTiles, sample_tile  # noqa: E402
from crowdbake.stages.runtime_fidelity import halfway_frame, render_mesh_references  # noqa: E402


def main() -> int:
    import cv2

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--azimuth-index", type=int, default=2, help="baked azimuth of row 1 (index)")
    parser.add_argument("--out", type=Path, default=Path("docs/img/impostor_switch.png"))
    parser.add_argument("--scale", type=int, default=2)
    args = parser.parse_args()

    poses = load_poses(args.work)
    layout = poses.atlas_layout()
    bundle = args.work / "bundle"
    maps = json.loads((bundle / "manifest.json").read_text())["impostor"]["maps"]
    surface = (bundle / maps["surface"]).read_bytes() if "surface" in maps else None
    tiles = AtlasTiles(layout, (bundle / maps["uv"]).read_bytes(), (bundle / maps["normal"]).read_bytes(), surface, poses.radius)
    textures = dict(np.load(args.work / "poses" / "textures.npz"))
    diffuse = [textures[f"material_{m}_decoded"][0] for m in range(len(poses.materials))]
    chains = [impostor_blend.mip_chain(texture) for texture in diffuse]
    size = layout.tile_size
    layer = list(poses.frame_indices).index(poses.fidelity_frame)
    azimuths, elevations = list(layout.azimuths_deg), sorted(layout.elevations_deg)
    a = args.azimuth_index % len(azimuths)
    step = (azimuths[(a + 1) % len(azimuths)] - azimuths[a]) % 360.0 or 360.0
    between_frame, between_weights = halfway_frame(poses)
    cases = [
        ("baked view", azimuths[a], elevations[0], poses.fidelity_frame, view_blend.FrameWeights((layer, layer), 0.0)),
        ("halfway", azimuths[a] + step / 2.0, (elevations[0] + elevations[min(1, len(elevations) - 1)]) / 2.0, between_frame, between_weights),
    ]

    def draw(weights: list[tuple[float, int, int]], azimuth: float, elevation: float,
             frames: view_blend.FrameWeights | None = None) -> np.ndarray:
        """The samples blended; with `frames`, each reprojected to the camera and that cycle position first."""
        view = impostor_views.ortho_view(poses.center, poses.radius, azimuth, elevation, size)
        samples = [(w, tiles.tile(tile, k) if frames is None else sample_tile(tiles, tile, k, view, frames)) for w, tile, k in weights]
        return impostor_blend.blend_image(samples, diffuse, textures["outfits"][0], shading.camera_light(view), size, chains,
                                          reprojected=frames is not None)

    rows = []
    for label, azimuth, elevation, frame, frames in cases:
        mesh = render_mesh_references(args.work, poses, frame, [(azimuth, elevation)], FIDELITY_SUPERSAMPLE)[0]
        weights = impostor_blend.samples_for(view_blend.blend_view_weights(azimuth, elevation, azimuths, layout.elevations_deg), frames)
        reprojected = draw(weights, azimuth, elevation, frames)
        blended = draw(weights, azimuth, elevation)
        nearest_tile = view_blend.blend_view_weights(azimuth, elevation, azimuths, layout.elevations_deg)
        best = int(np.argmax(nearest_tile.weights))
        nearest_layer = frames.layers[1] if frames.weight > 0.5 else frames.layers[0]
        nearest = draw([(1.0, nearest_tile.tiles[best], nearest_layer)], azimuth, elevation)
        difference = np.clip(np.abs(mesh - reprojected) * 4.0, 0.0, 1.0)
        print(f"{label}: azimuth {azimuth:.2f}, elevation {elevation:.1f}, frame {frame} (frame weight {frames.weight:.2f}): "
              f"SSIM reprojected {fidelity.compare(mesh, reprojected)['ssim']:.3f}, blended {fidelity.compare(mesh, blended)['ssim']:.3f}, "
              f"nearest {fidelity.compare(mesh, nearest)['ssim']:.3f}")
        rows.append(np.concatenate([mesh, reprojected, blended, nearest, difference], axis=1))
    picture = np.concatenate(rows, axis=0)
    picture = np.repeat(np.repeat(picture, args.scale, axis=0), args.scale, axis=1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), (picture[..., ::-1] * 255.0 + 0.5).astype(np.uint8))
    print(f"wrote {args.out}: columns mesh, reprojected impostor, blended, nearest view and frame, 4x |mesh - reprojected|")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
