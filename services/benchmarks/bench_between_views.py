"""Where the impostor loses fidelity between baked views and frames: crowdview's reconstruction against the
mesh, one offset at a time, blended against nearest-sample.

    PYTHONPATH=services python services/benchmarks/bench_between_views.py --work WORK \\
        [--azimuths 16] [--methods nearest blend] [--out out/bench/between_views.json]

WORK is a bake's work folder with its pack stage run (`crowdbake bake ... --work WORK`). Cases, each a set of
cameras against the mesh rendered there (crowdbake.stages.runtime_fidelity.render_mesh_references):

- `at_views`: every baked view of the fidelity frame (the impostor tasks' own references);
- `a_azimuth`: halfway between baked azimuths, at a baked elevation and the fidelity frame (the tasks'
  `reference_between`);
- `b_elevation`: halfway between baked elevation rings, at a baked azimuth and the fidelity frame;
- `c_frame`: at a baked view, halfway from the fidelity frame to the next baked frame;
- `d_all`: halfway in all three (fidelity.json runtime.between_views' cameras and frame).

`--azimuths` of the baked azimuths (or of the gaps between them) are used, spread evenly, at every ring
or ring gap. Methods: `blend` is crowdview's blend (crowdbake.reference.impostor_blend, decoded from the bundle's
files, as runtime_fidelity scores it); `nearest` draws the one (view, frame) sample of highest blend weight,
ties going to the lower azimuth, ring and frame (the paper's nearest view and frame). Candidates reproject
every sample before the same blend (crowdbake.reference.impostor_warp), from per-texel depth and motion taken
from the mesh at each baked view (SurfaceFields; what a bake could store beside the maps): `warp` (depth),
`warp_motion` (and 3D motion to both neighbouring baked frames), `warp_velocity` (one motion field a layer,
reversed for the way back), `warp_velocity_bc1` (depth and in-tile motion through one BC1 layer),
`warp_planar8` (8-bit, in-tile motion), `warp_oracle` (motion to the cycle frame itself: the ceiling).
`sharpen2`/`sharpen4` raise the blend weights to a power: no change exactly halfway. Mesh references are
cached in WORK/bench_between/ (keyed by frame and camera), so later runs only blend and score.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from crowdbake.bake import fidelity, impostor_views, shading, view_blend  # noqa: E402
from crowdbake.reference import impostor_blend, impostor_warp  # noqa: E402
from crowdbake.reference.coverage import Coverage, interpolate  # noqa: E402
from crowdbake.reference.runtime_picture import AtlasTiles  # noqa: E402
from crowdbake.reference.triangle_ids import TriangleIdRenderer  # noqa: E402
from crowdbake.stages.impostors import FIDELITY_SUPERSAMPLE, impostor_tasks, load_poses, nearest_inside, part_path  # noqa: E402
from crowdbake.stages.runtime_fidelity import halfway_frame, render_mesh_references  # noqa: E402

Camera = tuple[float, float, int]  # azimuth, elevation (degrees), cycle frame
Sample = tuple[float, int, int]  # weight, atlas tile, atlas layer


class Bench:
    """A baked work folder's decoded atlases, textures and cached mesh references."""

    def __init__(self, work: Path):
        self.work = work
        self.poses = load_poses(work)
        self.layout = self.poses.atlas_layout()
        bundle = work / "bundle"
        maps = json.loads((bundle / "manifest.json").read_text())["impostor"]["maps"]
        self.tiles = AtlasTiles(self.layout, (bundle / maps["uv"]).read_bytes(), (bundle / maps["normal"]).read_bytes())
        textures = dict(np.load(work / "poses" / "textures.npz"))
        self.diffuse = [textures[f"material_{m}_decoded"][0] for m in range(len(self.poses.materials))]
        self.chains = [impostor_blend.mip_chain(texture) for texture in self.diffuse]
        self.outfit_row = textures["outfits"][0]
        self.size = self.layout.tile_size
        self.frames = list(self.poses.frame_indices)
        self.cache_dir = work / "bench_between"
        self.cache_dir.mkdir(exist_ok=True)
        self._references: dict[str, np.ndarray] = {}
        self._load_cache()

    def _load_cache(self) -> None:
        for path in sorted(self.cache_dir.glob("references_*.npz")):
            with np.load(path) as cached:
                self._references.update({key: cached[key] for key in cached.files})
        # The impostor tasks' references at the baked views and halfway in azimuth, fidelity frame.
        for task in impostor_tasks(self.work):
            if not task.references:
                continue
            with np.load(part_path(self.work, task)) as part:
                for (a, e), reference, between, mid in zip(part["views"].tolist(), part["reference"], part["reference_between"],
                                                           part["between_azimuths"]):
                    elevation = self.layout.elevations_deg[e]
                    self._references[_key(self.layout.azimuths_deg[a], elevation, task.frame)] = reference
                    self._references[_key(float(mid), elevation, task.frame)] = between

    def references(self, cameras: list[Camera]) -> list[np.ndarray]:
        """The mesh reference of every camera, rendering (and caching) the missing ones."""
        missing: dict[int, list[tuple[float, float]]] = {}
        for azimuth, elevation, frame in cameras:
            if _key(azimuth, elevation, frame) not in self._references:
                missing.setdefault(frame, []).append((azimuth, elevation))
        for frame, views in missing.items():
            images = render_mesh_references(self.work, self.poses, frame, views, FIDELITY_SUPERSAMPLE)
            fresh = {_key(a, e, frame): image.astype(np.float32) for (a, e), image in zip(views, images)}
            self._references.update(fresh)
            path = self.cache_dir / f"references_{frame:04d}_{len(list(self.cache_dir.glob('references_*.npz')))}.npz"
            np.savez(path, **fresh)
        return [self._references[_key(*camera)] for camera in cameras]

    def frame_weights(self, frame: int) -> view_blend.FrameWeights:
        return view_blend.blend_frame_weights(frame, self.frames, self.poses.cycle_frames)

    def samples(self, azimuth: float, elevation: float, frame: int) -> list[Sample]:
        """crowdview's (weight, tile, layer) samples for a camera (impostor_blend.samples_for)."""
        views = view_blend.blend_view_weights(azimuth, elevation, self.layout.azimuths_deg, self.layout.elevations_deg)
        return impostor_blend.samples_for(views, self.frame_weights(frame))

    def light(self, azimuth: float, elevation: float) -> np.ndarray:
        return shading.camera_light(impostor_views.ortho_view(self.poses.center, self.poses.radius, azimuth, elevation, self.size))

    def blend(self, samples: list[Sample], azimuth: float, elevation: float) -> np.ndarray:
        decoded = [(w, self.tiles.tile(tile, layer)) for w, tile, layer in samples]
        return impostor_blend.blend_image(decoded, self.diffuse, self.outfit_row, self.light(azimuth, elevation), self.size, self.chains,
                                          reprojected=False)


def _key(azimuth: float, elevation: float, frame: int) -> str:
    return f"a{azimuth:.4f}_e{elevation:.4f}_f{int(frame)}"


def nearest_sample(samples: list[Sample]) -> list[Sample]:
    """The single sample of highest weight (the first of equals: lower azimuth, ring, frame), weight 1."""
    best = max(range(len(samples)), key=lambda index: (samples[index][0], -index))
    return [(1.0, samples[best][1], samples[best][2])]


def method_blend(bench: Bench, azimuth: float, elevation: float, frame: int) -> np.ndarray:
    return bench.blend(bench.samples(azimuth, elevation, frame), azimuth, elevation)


def method_nearest(bench: Bench, azimuth: float, elevation: float, frame: int) -> np.ndarray:
    return bench.blend(nearest_sample(bench.samples(azimuth, elevation, frame)), azimuth, elevation)


_ID_RENDERERS: dict[int, TriangleIdRenderer] = {}


def id_coverage(view: impostor_views.OrthoView, positions: np.ndarray, faces: np.ndarray) -> Coverage:
    """Exact coverage of `view` from the test oracle's triangle-id render (crowdbake.reference), one
    renderer a view size kept open for the run: a GL context costs more than a render."""
    if view.size not in _ID_RENDERERS:
        _ID_RENDERERS[view.size] = TriangleIdRenderer(view.size).__enter__()
    renderer = _ID_RENDERERS[view.size]
    renderer.set_mesh(positions, faces)
    return renderer.coverage(view, positions, faces)


class SurfaceFields:
    """Per baked (tile, layer): the surface point's depth along the view axis and its motion to the previous
    and next baked frames, from the mesh (what a bake could store beside the maps), dilated into the background."""

    def __init__(self, bench: Bench):
        self.bench = bench
        self._scenes: dict[int, object] = {}
        self._fields: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.mask_mismatch = 0

    def _scene(self, frame: int):
        from crowdbake.stages.impostors import load_pose_scene

        if frame not in self._scenes:
            self._scenes[frame] = load_pose_scene(self.bench.work, self.bench.poses, frame)
        return self._scenes[frame]

    def view(self, tile: int) -> impostor_views.OrthoView:
        layout, poses = self.bench.layout, self.bench.poses
        columns = len(layout.azimuths_deg)
        return impostor_views.ortho_view(poses.center, poses.radius, layout.azimuths_deg[tile % columns],
                                        layout.elevations_deg[tile // columns], layout.tile_size)

    def fields(self, tile: int, layer: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth (S, S), motion to the previous baked frame (S, S, 3), motion to the next (S, S, 3))."""
        if (tile, layer) not in self._fields:
            frames = self.bench.frames
            scene = self._scene(frames[layer])
            view = self.view(tile)
            coverage = id_coverage(view, scene.positions, scene.faces)
            mask = coverage.mask
            self.mask_mismatch += int((mask != self.bench.tiles.tile(tile, layer).covered).sum())
            points = interpolate(scene.positions, scene.faces, coverage)
            depth = np.where(mask, (points - view.center) @ view.back, 0.0)
            motions = []
            for other in (frames[layer - 1], frames[(layer + 1) % len(frames)]):
                moved = interpolate(self._scene(other).positions, scene.faces, coverage)
                motions.append(np.where(mask[..., None], moved - points, 0.0))
            nearest = nearest_inside(mask)
            if nearest is not None:
                depth = depth[nearest[0], nearest[1]]
                motions = [m[nearest[0], nearest[1]] for m in motions]
            self._fields[(tile, layer)] = (depth, motions[0], motions[1])
        return self._fields[(tile, layer)]


    def motion_to(self, tile: int, layer: int, frame: int) -> np.ndarray:
        """(S, S, 3) motion of each texel's surface point to cycle frame `frame` (any, baked or not), dilated."""
        scene = self._scene(self.bench.frames[layer])
        view = self.view(tile)
        coverage = id_coverage(view, scene.positions, scene.faces)
        points = interpolate(scene.positions, scene.faces, coverage)
        moved = interpolate(self._scene(frame).positions, scene.faces, coverage)
        nearest = nearest_inside(coverage.mask)
        motion = np.where(coverage.mask[..., None], moved - points, 0.0)
        return motion if nearest is None else motion[nearest[0], nearest[1]]


def oracle_image(bench: Bench, azimuth: float, elevation: float, frame: int) -> np.ndarray:
    """warp_motion with each sample's motion taken to the cycle frame itself (no linear interpolation
    between baked frames): the ceiling of motion fields, what is left being occlusion and resampling."""
    surface = surface_fields(bench)
    target = impostor_views.ortho_view(bench.poses.center, bench.poses.radius, azimuth, elevation, bench.size)
    decoded = []
    for w, tile, layer in bench.samples(azimuth, elevation, frame):
        depth = surface.fields(tile, layer)[0]
        field = surface.motion_to(tile, layer, frame) if bench.frames[layer] != frame else None
        xy, _ = impostor_warp.reproject(surface.view(tile), depth, target, field, 1.0)
        decoded.append((w, impostor_warp.gather(bench.tiles.tile(tile, layer), xy)))
    return impostor_blend.blend_image(decoded, bench.diffuse, bench.outfit_row, bench.light(azimuth, elevation), bench.size, bench.chains)


_SURFACE: dict[int, SurfaceFields] = {}


def surface_fields(bench: Bench) -> SurfaceFields:
    if id(bench) not in _SURFACE:
        _SURFACE[id(bench)] = SurfaceFields(bench)
    return _SURFACE[id(bench)]


def quantized(values: np.ndarray, limit: float, bits: int | None) -> np.ndarray:
    """Values in [-limit, limit] rounded to `bits` bits (unchanged when bits is None)."""
    if bits is None:
        return values
    steps = (1 << bits) - 1
    codes = np.rint((np.clip(values, -limit, limit) + limit) / (2 * limit) * steps)
    return codes / steps * (2 * limit) - limit


def bc1_roundtrip(depth: np.ndarray, motion: np.ndarray, view: impostor_views.OrthoView, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth (±radius) and the tile-plane motion (right, up components, ±radius/2) through one BC1 layer."""
    from crowdbake.bake import compression

    channels = [(depth, radius), (motion @ view.right, radius / 2), (motion @ view.up, radius / 2)]
    rgb = [np.rint((np.clip(v, -r, r) + r) / (2 * r) * 255) for v, r in channels]
    rgba = np.dstack(rgb + [np.full_like(depth, 255)]).astype(np.uint8)
    size = depth.shape[0]
    back = compression.decode_bc1(compression.encode_bc1(rgba), size, size)[..., :3].astype(np.float64) / 255
    decoded = [back[..., k] * 2 * r - r for k, (_, r) in enumerate(channels)]
    return decoded[0], decoded[1][..., None] * view.right + decoded[2][..., None] * view.up


def warped_image(bench: Bench, azimuth: float, elevation: float, frame: int, motion: bool, samples: list[Sample] | None = None,
                 max_miss: float | None = None, backward: str = "stored", planar: bool = False, bits: int | None = None,
                 iterations: int = impostor_warp.DEFAULT_ITERATIONS, bc1: bool = False) -> np.ndarray:
    """crowdview's blend of the same samples, each reprojected to the camera (and, with `motion`, to the
    cycle frame) first (crowdbake.reference.impostor_warp)."""
    surface = surface_fields(bench)
    target = impostor_views.ortho_view(bench.poses.center, bench.poses.radius, azimuth, elevation, bench.size)
    frames = bench.frame_weights(frame)
    decoded = []
    for w, tile, layer in samples if samples is not None else bench.samples(azimuth, elevation, frame):
        depth, to_previous, to_next = surface.fields(tile, layer)
        view = surface.view(tile)
        if backward == "negated_next":  # constant velocity: one motion field a layer
            to_previous = -to_next
        elif backward == "central":  # one field a layer: the mean of the motion to the next and from the previous
            to_next = (to_next - to_previous) / 2.0
            to_previous = -to_next
        if planar:  # motion in the tile's plane only: two channels
            to_previous = to_previous - (to_previous @ view.back)[..., None] * view.back
            to_next = to_next - (to_next @ view.back)[..., None] * view.back
        radius = bench.poses.radius
        if bc1:  # one RGB layer a tile: depth, and the constant-velocity motion in the tile's plane
            depth, to_next = bc1_roundtrip(depth, to_next, view, radius)
            to_previous = -to_next
        depth = quantized(depth, radius, bits)
        to_previous, to_next = quantized(to_previous, radius / 2, bits), quantized(to_next, radius / 2, bits)
        fraction, field = 0.0, None
        if motion and frames.layers[0] != frames.layers[1]:
            # The earlier baked frame moves forward by the frame weight, the later one back by the rest.
            fraction, field = (frames.weight, to_next) if layer == frames.layers[0] else (1.0 - frames.weight, to_previous)
        xy, miss = impostor_warp.reproject(view, depth, target, field, fraction, iterations)
        valid = None if max_miss is None else miss <= max_miss
        decoded.append((w, impostor_warp.gather(bench.tiles.tile(tile, layer), xy, valid)))
    return impostor_blend.blend_image(decoded, bench.diffuse, bench.outfit_row, bench.light(azimuth, elevation), bench.size, bench.chains)


def sharpened(samples: list[Sample], power: float) -> list[Sample]:
    total = sum(w ** power for w, _, _ in samples)
    return [(w ** power / total, tile, layer) for w, tile, layer in samples]


METHODS: dict[str, Callable[[Bench, float, float, int], np.ndarray]] = {
    "nearest": method_nearest,
    "blend": method_blend,
    "sharpen2": lambda b, a, e, f: b.blend(sharpened(b.samples(a, e, f), 2.0), a, e),
    "sharpen4": lambda b, a, e, f: b.blend(sharpened(b.samples(a, e, f), 4.0), a, e),
    "warp": lambda b, a, e, f: warped_image(b, a, e, f, motion=False),
    "warp_motion": lambda b, a, e, f: warped_image(b, a, e, f, motion=True),
    "warp_nearest": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, samples=nearest_sample(b.samples(a, e, f))),
    "warp_oracle": oracle_image,
    "warp_motion_it2": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, iterations=2),
    "warp_motion_it8": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, iterations=8),
    "warp_motion_miss1": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, max_miss=1.0),
    "warp_velocity": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, backward="negated_next"),
    "warp_central": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, backward="central"),
    "warp_central_planar8": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, backward="central", planar=True, bits=8),
    "warp_planar": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, planar=True),
    "warp_velocity_bc1": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, backward="negated_next", bc1=True),
    "warp_planar8": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, planar=True, bits=8),
    "warp_planar6": lambda b, a, e, f: warped_image(b, a, e, f, motion=True, planar=True, bits=6),
}


def spread(values: list[float], count: int) -> list[float]:
    """At most `count` of `values`, evenly spaced through the list."""
    if len(values) <= count:
        return list(values)
    return [values[i] for i in np.linspace(0, len(values), count, endpoint=False).astype(int)]


def cases(bench: Bench, azimuth_count: int) -> dict[str, list[Camera]]:
    """The cameras of every case (module docstring)."""
    azimuths = sorted(bench.layout.azimuths_deg)
    elevations = sorted(bench.layout.elevations_deg)
    mid_azimuths = [((a + b) / 2.0) % 360.0 for a, b in zip(azimuths, azimuths[1:] + [azimuths[0] + 360.0])]
    mid_elevations = [(a + b) / 2.0 for a, b in zip(elevations, elevations[1:])] or elevations
    base = bench.poses.fidelity_frame
    between_frame, _ = halfway_frame(bench.poses)
    some_azimuths, some_mids = spread(azimuths, azimuth_count), spread(mid_azimuths, azimuth_count)
    return {
        "at_views": [(a, e, base) for e in elevations for a in azimuths],
        "a_azimuth": [(a, e, base) for e in elevations for a in some_mids],
        "b_elevation": [(a, e, base) for e in mid_elevations for a in some_azimuths],
        "c_frame": [(a, e, between_frame) for e in elevations for a in some_azimuths],
        "d_all": [(a, e, between_frame) for e in mid_elevations for a in some_mids],
    }


def score_case(bench: Bench, cameras: list[Camera], method: Callable) -> dict:
    references = bench.references(cameras)
    scores = [fidelity.compare(reference, method(bench, *camera))["ssim"] for camera, reference in zip(cameras, references)]
    return {"cameras": len(scores), "ssim_mean": float(np.mean(scores)), "ssim_worst": float(np.min(scores)),
            "per_camera": [round(s, 5) for s in scores]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--azimuths", type=int, default=16, help="azimuths (or azimuth gaps) per ring, spread evenly")
    parser.add_argument("--methods", nargs="+", default=["nearest", "blend"], choices=sorted(METHODS))
    parser.add_argument("--cases", nargs="+", default=None, help="cases to score (default: all)")
    parser.add_argument("--out", type=Path, default=Path("out/bench/between_views.json"))
    args = parser.parse_args()

    clock = time.perf_counter()
    bench = Bench(args.work)
    chosen = cases(bench, args.azimuths)
    if args.cases:
        chosen = {name: chosen[name] for name in args.cases}
    result: dict = {"work": str(args.work), "layout": {"azimuths": len(bench.layout.azimuths_deg),
                    "elevations_deg": list(bench.layout.elevations_deg), "frames": bench.frames, "tile": bench.size},
                    "between_frame": halfway_frame(bench.poses)[0], "cases": {}}
    print(f"{'case':<12} {'cameras':>7} " + " ".join(f"{m + ' mean/worst':>22}" for m in args.methods))
    for name, cameras in chosen.items():
        scores = {method: score_case(bench, cameras, METHODS[method]) for method in args.methods}
        result["cases"][name] = scores
        print(f"{name:<12} {len(cameras):>7} " + " ".join(
            f"{scores[m]['ssim_mean']:>13.4f} / {scores[m]['ssim_worst']:.4f}" for m in args.methods), flush=True)
    if id(bench) in _SURFACE:
        result["surface_mask_mismatch_texels"] = _SURFACE[id(bench)].mask_mismatch
        print(f"surface fields: {result['surface_mask_mismatch_texels']} texels whose coverage differs from the bundle's")
    result["seconds"] = time.perf_counter() - clock
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
