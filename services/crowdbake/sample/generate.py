"""Generate the procedural sample: a clothed walking character in the formats users bring.

`simulate_sample` is the pure part (arrays in memory); `generate_sample` writes the files of the
output contract:

    character.glb            skinned, animated, textured humanoid (walk cycle of cycle_frames at 24 fps)
    cloth.pc2, cloth.obj     the garment's cache over cycles * cycle_frames frames, and its rest mesh
    textures/diffuse_NN.png  8 diffuse variations, one shared layout, alpha = 17 * region code
    textures/outfits.png     outfit colour map: 16 region columns, one row per outfit
    settling.json            per-cycle RMS distance between frames t and t - cycle_frames
    sample.json              what was generated, region names, file list, quality figures
    timeline.json            with clips only: which clip plays at each cache frame (robot_clips' format)

With clips (simulate_clips_sample) character.glb holds the animations Idle, Walking and Running and the cache
covers the whole sequence; settling.json then gives each timeline segment's cycle gaps.

Frame f of the cache is animation time (f % cycle_frames) / 24 s. Positions are in metres, Y up,
in the same world space as the skinned character. Everything is a deterministic function of the
arguments (garment, cycles or clips, seed, cycle_frames, texture_size, build...): the same arguments give
the same bytes.
"""
from __future__ import annotations

import io
import json
import logging
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from crowdbake.bake.skinning import joint_world_matrices, pose_character, skin
from crowdbake.formats.gltf import Character, write_character
from crowdbake.formats.obj import write_obj
from crowdbake.formats.pc2 import write_pc2
from crowdbake.sample import regions
from crowdbake.sample.cloth_sim import (
    ClothModel,
    build_cloth_model,
    capsule_penetration,
    edge_strain,
    inside_closed_parts,
    settling_curve,
    simulate,
    surface_distance,
)
from crowdbake.sample.garments import GARMENT_SPECS, Garment, GarmentSpec, build_garment, fitted_spec
from crowdbake.sample.colliders import Capsules, capsule_track, fit_capsules
from crowdbake.sample.humanoid import (
    BUILDS,
    JOINT_INDEX,
    STANDARD,
    BodyMesh,
    Build,
    build_body,
    build_character,
    joint_rest_positions,
    torso_skin_weights,
)
from crowdbake.sample.textures import OUTFIT_COUNT, VARIATION_COUNT, diffuse_textures, outfit_map
from crowdbake.sample.clips import (
    DEFAULT_BLEND_FRAMES,
    DEFAULT_SEQUENCE,
    clip_animations,
    clip_periods,
    segment_cycle_gaps,
    sequence_layout,
    sequence_world_matrices,
    timeline_document,
)
from crowdbake.sample.walk import DEFAULT_CYCLE_FRAMES, FPS, walk_channels

logger = logging.getLogger(__name__)

DEFAULT_CYCLES = 20
DEFAULT_TEXTURE_SIZE = 1024
# Jitter (metres, standard deviation) added to the garment's starting shape: breaks the perfect
# left-right symmetry a procedural mesh has and makes the seed matter, far below visible size.
INITIAL_JITTER = 0.001
# RMS distance (metres) between frames one cycle apart under which a cycle counts as settled:
# 5 mm RMS over a skirt is a fold shifting by a few millimetres, below what reads as a jump at
# crowd viewing distances, yet above the ~2 mm contact chatter a settled garment keeps here.
SETTLED_RMS = 0.005
# Depth (metres) a cloth vertex may sit inside a collision capsule before it counts as penetrating:
# friction is applied after the last collision pass and may slide a vertex a hair inwards.
PENETRATION_TOLERANCE = 0.002


@dataclass
class SampleSimulation:
    """Everything simulate_sample computes. points: (cycles * cycle_frames, V, 3) float32 metres."""

    garment_name: str
    cycles: int
    seed: int
    cycle_frames: int
    body: BodyMesh
    character: Character  # texture is None here; generate_sample adds variation 0
    capsules: Capsules
    capsule_track: np.ndarray  # (cycle_frames * substeps, C, 2, 3)
    garment: Garment
    model: ClothModel
    points: np.ndarray
    settling: np.ndarray  # (cycles - 1,) metres, entry c - 1 for cycle c
    # Several clips (crowdbake.sample.clips): capsule_track covers every frame, not one cycle, and
    # frame_skinning (F, J, 4, 4) float32 holds the body's skinning matrices at each cache frame.
    frame_skinning: np.ndarray | None = None

    @property
    def frame_count(self) -> int:
        return int(self.points.shape[0])

    def _track_period(self) -> int:
        return self.cycle_frames if self.frame_skinning is None else len(self.frame_skinning)

    def frame_track_index(self) -> np.ndarray:
        """Index into capsule_track of each cache frame."""
        period = self._track_period()
        substeps = self.capsule_track.shape[0] // period
        return (np.arange(self.frame_count) % period) * substeps

    def posed_body(self, frames: list[int]) -> list[np.ndarray]:
        """The skinned body's positions (Vb, 3) at each of the cache frames."""
        if self.frame_skinning is None:
            posed, _ = pose_character(self.character, FPS, self.cycle_frames)
            return [posed[f % self.cycle_frames] for f in frames]
        body = self.body
        posed, _ = skin(body.positions, body.normals, body.joints, body.weights, self.frame_skinning[frames])
        return list(posed)

    def quality(self, body_frames: int = 4) -> dict:
        """Penetration and stretch figures of the cache.

        Penetration is measured twice: against the collision capsules on every frame (depth beyond
        PENETRATION_TOLERANCE), and against the skinned body mesh itself (inside any closed body part,
        by winding number) on body_frames frames spread over the last cycle, where the pinned
        waistband's largest distance to the torso's surface is measured too. Stretch is edge
        extension in percent over every frame after the first cycle (the first holds the drop from rest).
        """
        depth = capsule_penetration(self.points, self.capsule_track, self.capsules.radii, self.frame_track_index())
        penetrating = (depth > PENETRATION_TOLERANCE).sum(axis=1)
        settled = self.points[self.cycle_frames :] if self.frame_count > self.cycle_frames else self.points
        extension = np.maximum(edge_strain(settled, self.model.stretch, self.model.stretch_rest), 0.0) * 100.0
        last_cycle = self.frame_count - self.cycle_frames
        frames = sorted({max(last_cycle, 0) + k * self.cycle_frames // body_frames for k in range(body_frames)})
        posed = self.posed_body(frames)
        parts = list(self.body.part_faces.values())
        inside_body = [int(inside_closed_parts(self.points[f], body, self.body.faces, parts).sum()) for f, body in zip(frames, posed)]
        first, stop = self.body.part_faces["torso"]
        waistband_gap = max(
            float(surface_distance(self.points[f, self.model.pinned], body, self.body.faces[first:stop]).max())
            for f, body in zip(frames, posed)
        )
        return {
            "vertex_count": int(self.points.shape[1]),
            "capsule_penetration_tolerance_m": PENETRATION_TOLERANCE,
            "penetrating_vertices_max": int(penetrating.max()),
            "penetrating_vertices_mean": round(float(penetrating.mean()), 3),
            "capsule_penetration_depth_max_m": round(float(max(depth.max(), 0.0)), 5),
            "inside_body_mesh_frames": [int(f) for f in frames],
            "inside_body_mesh_vertices": inside_body,
            "waistband_gap_to_body_max_m": round(waistband_gap, 5),
            "edge_stretch_percent_p99": round(float(np.percentile(extension, 99)), 3),
            "edge_stretch_percent_max": round(float(extension.max()), 3),
        }


def settled_cycle(settling: np.ndarray, threshold: float = SETTLED_RMS) -> int | None:
    """The first cycle c (>= 1) whose RMS distance to cycle c - 1 is under threshold, or None.

    That is the first place a cycle search can cut a loop that does not visibly jump; a chaotic
    garment may rise above the threshold again later (the paper saw loose skirts never settle).
    settling: (cycles - 1,) as from settling_curve, entry c - 1 for cycle c.
    """
    below = np.flatnonzero(np.asarray(settling) < threshold)
    return int(below[0]) + 1 if len(below) else None


def _hips_frame(world: np.ndarray, build: Build = STANDARD) -> np.ndarray:
    """(K, 4, 4) transforms taking the hips' current frame back to its rest frame."""
    hips_rest = np.eye(4)
    hips_rest[:3, 3] = joint_rest_positions(build)[JOINT_INDEX["hips"]]
    return hips_rest @ np.linalg.inv(world[:, JOINT_INDEX["hips"]])


def simulate_sample(
    garment: str = "loose",
    cycles: int = DEFAULT_CYCLES,
    seed: int = 0,
    cycle_frames: int = DEFAULT_CYCLE_FRAMES,
    on_frame: Callable[[int], None] | None = None,
    cloth_rows: int | None = None,
    cloth_columns: int | None = None,
    build: Build = STANDARD,
) -> SampleSimulation:
    """Build the humanoid and its walk, cut the garment, and simulate `cycles` walk cycles from rest.

    cloth_rows, cloth_columns: the garment's rings and vertices a ring (None: the garment's own; fewer
    make a coarser, faster cloth for tests); build: the body's proportions (crowdbake.sample.humanoid.BUILDS)."""
    if cycles < 1:
        raise ValueError(f"cycles must be at least 1, got {cycles}")
    spec = garment_spec(garment, cloth_rows, cloth_columns, build)
    body = build_body(build)
    channels, duration = walk_channels(cycle_frames, FPS, build)
    character = build_character(body, channels, duration, texture=None)
    # The body at every substep of one cycle; the simulation reuses it cycle after cycle.
    substeps = spec.params.substeps
    times = np.arange(cycle_frames * substeps) / (FPS * substeps)
    world = joint_world_matrices(character, times)
    dressed = dress(spec, body, character, world, world[::substeps], seed)
    points = simulate(dressed.model, spec.params, dressed.initial, dressed.pin_track, dressed.track, dressed.capsules.radii,
                      cycles * cycle_frames, FPS, on_frame)
    settling = settling_curve(points, cycle_frames)
    logger.info("simulated %s: %d frames of %d vertices", garment, len(points), points.shape[1])
    return SampleSimulation(garment, cycles, seed, cycle_frames, body, character, dressed.capsules, dressed.track, dressed.cut,
                            dressed.model, points, settling)


@dataclass
class ClipsSimulation:
    """simulate_clips_sample's result: the simulation (its character carries the Walking clip's channels),
    every clip's channels (the glTF's named animations, CLIP_NAMES order) and the timeline document."""

    simulation: SampleSimulation
    animations: dict[str, list]
    timeline: dict


def simulate_clips_sample(
    garment: str = "loose",
    sequence=DEFAULT_SEQUENCE,
    seed: int = 0,
    cycle_frames: int = DEFAULT_CYCLE_FRAMES,
    blend_frames: int = DEFAULT_BLEND_FRAMES,
    on_frame: Callable[[int], None] | None = None,
    cloth_rows: int | None = None,
    cloth_columns: int | None = None,
    build: Build = STANDARD,
) -> ClipsSimulation:
    """Simulate the garment once through a sequence of clips ((clip, repeats) pairs, see
    crowdbake.sample.clips), the body blending from clip to clip over blend_frames. The cut makes room
    for every clip's range of motion; cycle_frames is the walk's period (the idle's and the run's follow)."""
    spec = garment_spec(garment, cloth_rows, cloth_columns, build)
    periods = clip_periods(cycle_frames)
    strips, total = sequence_layout(sequence, periods, blend_frames)
    animations = clip_animations(cycle_frames, FPS, build)
    body = build_body(build)
    character = build_character(body, animations["Walking"], cycle_frames / FPS, texture=None)
    substeps = spec.params.substeps
    world = sequence_world_matrices(character, animations, strips, blend_frames, FPS, substeps, total * substeps)
    shaping = np.concatenate([
        joint_world_matrices(replace(character, channels=animations[clip]), np.arange(periods[clip]) / FPS)
        for clip in dict.fromkeys(s.clip for s in strips)
    ])
    dressed = dress(spec, body, character, world, shaping, seed)
    points = simulate(dressed.model, spec.params, dressed.initial, dressed.pin_track, dressed.track, dressed.capsules.radii,
                      total, FPS, on_frame)
    timeline = timeline_document(strips, total, FPS, blend_frames)
    for segment, gaps in zip(timeline["segments"], segment_cycle_gaps(points, timeline["segments"])):
        segment["cycle_gap_rms_m"] = gaps
    frame_skinning = (world[::substeps] @ character.inverse_bind_matrices.astype(np.float64)).astype(np.float32)
    simulation = SampleSimulation(garment, 1, seed, cycle_frames, body, character, dressed.capsules, dressed.track, dressed.cut,
                                  dressed.model, points, np.zeros(0), frame_skinning)
    logger.info("simulated %s through %s: %d frames of %d vertices", garment, " -> ".join(s.clip for s in strips), total, points.shape[1])
    return ClipsSimulation(simulation, animations, timeline)


def garment_spec(garment: str, rows: int | None = None, columns: int | None = None, build: Build = STANDARD) -> GarmentSpec:
    """The named garment's cut for a build, with its rings (rows) and vertices a ring (columns) replaced where given."""
    if garment not in GARMENT_SPECS:
        raise ValueError(f"unknown garment {garment!r}; choose one of {sorted(GARMENT_SPECS)}")
    spec = fitted_spec(GARMENT_SPECS[garment], build)
    if rows is not None or columns is not None:
        spec = replace(spec, rows=spec.rows if rows is None else rows, columns=spec.columns if columns is None else columns)
    return spec


@dataclass
class Dressed:
    """The garment on the moving body, ready to simulate: capsules and their track (K, C, 2, 3), the cut
    and its cloth model, the waistband's targets (K, P, 3) and the starting positions (V, 3)."""

    capsules: Capsules
    track: np.ndarray
    cut: Garment
    model: ClothModel
    pin_track: np.ndarray
    initial: np.ndarray


def dress(spec: GarmentSpec, body: BodyMesh, character: Character, world: np.ndarray, shaping_world: np.ndarray, seed: int) -> Dressed:
    """Fit the capsules, cut the garment around the limbs' range of motion and pin its waistband.

    world (K, J, 4, 4): joint world transforms at every substep the simulation steps through (frame 0 first);
    shaping_world (S, J, 4, 4): the poses the cut makes room for (every frame of every clip played)."""
    params = spec.params
    capsules = fit_capsules(body)
    track = capsule_track(capsules, world)

    # Cut the garment around the limbs' range of motion, seen from the pelvis.
    to_hips = _hips_frame(shaping_world, body.build)
    frames = capsule_track(capsules, shaping_world)
    local = np.einsum("kij,kcpj->kcpi", to_hips[:, :3, :3], frames) + to_hips[:, None, None, :3, 3]
    # Only the trunk and legs shape the cut: a skirt does not make room for swinging hands.
    shaping = np.array([name.startswith(("pelvis", "waist", "thigh", "shin")) for name in capsules.names])
    cut = build_garment(spec, local[:, shaping], capsules.radii[shaping], params.thickness, body.build)

    # Waistband targets: skinned with the torso's weights at the waistband height.
    model = build_cloth_model(cut.rest_positions, cut.faces, cut.pinned, params.tether_detour)
    pin_rest = cut.rest_positions[cut.pinned]
    pin_joints, pin_weights = torso_skin_weights(pin_rest[:, 1], body.build)
    skinning = (world @ character.inverse_bind_matrices.astype(np.float64)).astype(np.float32)
    pin_track, _ = skin(pin_rest, np.zeros_like(pin_rest), pin_joints, pin_weights, skinning)

    # Start from rest: the cut garment carried rigidly by the hips into the frame-0 pose.
    start = np.linalg.inv(_hips_frame(world[:1], body.build)[0])
    initial = cut.rest_positions @ start[:3, :3].T + start[:3, 3]
    rng = np.random.default_rng(seed)
    initial = initial + rng.normal(0.0, INITIAL_JITTER, size=initial.shape)
    return Dressed(capsules, track, cut, model, pin_track.astype(np.float64), initial)


def _png(image: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image), "RGBA").save(buffer, format="PNG", compress_level=6)
    return buffer.getvalue()


def _write_json(path: Path, document: dict) -> None:
    path.write_text(json.dumps(document, indent=2, sort_keys=False) + "\n", encoding="utf-8")


@dataclass
class SampleResult:
    """Paths written (name -> path) and the figures worth printing."""

    out_dir: Path
    files: dict[str, Path]
    settling: list[float]
    settled_cycle: int | None
    quality: dict


def generate_sample(
    out_dir: str | os.PathLike,
    garment: str = "loose",
    cycles: int = DEFAULT_CYCLES,
    seed: int = 0,
    cycle_frames: int = DEFAULT_CYCLE_FRAMES,
    texture_size: int = DEFAULT_TEXTURE_SIZE,
    on_frame: Callable[[int], None] | None = None,
    clips=None,
    blend_frames: int = DEFAULT_BLEND_FRAMES,
    cloth_rows: int | None = None,
    cloth_columns: int | None = None,
    build: str = "standard",
) -> SampleResult:
    """Simulate and write the whole sample into out_dir (created if needed); see the module docstring.

    clips: a sequence of (clip, repeats) (crowdbake.sample.clips) to simulate instead of `cycles` walk
    cycles: character.glb then holds the animations Idle, Walking and Running, and timeline.json says which
    plays at each cache frame. build: a name of crowdbake.sample.humanoid.BUILDS."""
    if build not in BUILDS:
        raise ValueError(f"unknown build {build!r}; choose one of {', '.join(BUILDS)}")
    body_build = BUILDS[build]
    out = Path(out_dir)
    (out / "textures").mkdir(parents=True, exist_ok=True)
    played = None
    if clips is None:
        simulation = simulate_sample(garment, cycles, seed, cycle_frames, on_frame, cloth_rows, cloth_columns, body_build)
    else:
        played = simulate_clips_sample(garment, clips, seed, cycle_frames, blend_frames, on_frame, cloth_rows, cloth_columns, body_build)
        simulation = played.simulation
    diffuse = diffuse_textures(texture_size, seed, VARIATION_COUNT)
    outfits = outfit_map(seed, OUTFIT_COUNT)
    files: dict[str, Path] = {}

    character = simulation.character
    character.texture = diffuse[0]
    files["character"] = out / "character.glb"
    write_character(files["character"], character, None if played is None else list(played.animations.items()))
    files["cloth_cache"] = out / "cloth.pc2"
    write_pc2(files["cloth_cache"], simulation.points, start_frame=0.0, sample_rate=1.0)
    files["cloth_mesh"] = out / "cloth.obj"
    cut = simulation.garment
    write_obj(
        files["cloth_mesh"],
        cut.rest_positions,
        cut.faces,
        cut.uvs,
        cut.uv_faces,
        comment=(
            f"crowdbake sample garment '{garment}' ({cut.spec.rows} rings x {cut.spec.columns}), rest shape, metres, Y up.\n"
            "Vertex k here is point k of cloth.pc2. UVs address the same texture as character.glb."
        ),
    )
    for index, image in enumerate(diffuse):
        files[f"diffuse_{index:02d}"] = out / "textures" / f"diffuse_{index:02d}.png"
        files[f"diffuse_{index:02d}"].write_bytes(_png(image))
    files["outfits"] = out / "textures" / "outfits.png"
    files["outfits"].write_bytes(_png(outfits))

    if played is not None:
        files["timeline"] = out / "timeline.json"
        _write_json(files["timeline"], played.timeline)
    settling = [round(float(v), 7) for v in simulation.settling]
    settled = settled_cycle(simulation.settling)
    files["settling"] = out / "settling.json"
    if played is None:
        _write_json(
            files["settling"],
            {
                "garment": garment,
                "cycles": cycles,
                "seed": seed,
                "cycle_frames": cycle_frames,
                "fps": FPS,
                "metric": "RMS over the frames t of cycle c and all cloth vertices of |x_t - x_(t - cycle_frames)|, metres",
                "cycle": list(range(1, cycles)),
                "rms_m": settling,
                "settled_threshold_m": SETTLED_RMS,
                "settled_cycle": settled,
                "settled_definition": "first cycle whose rms_m is under settled_threshold_m (null: none)",
            },
        )
    else:
        _write_json(files["settling"], {
            "garment": garment, "seed": seed, "fps": FPS,
            "metric": "per segment of timeline.json, RMS over its pure frames t of one cycle and all cloth vertices of "
                      "|x_t - x_(t - clip_frames)|, metres, one value per pair of consecutive cycles",
            "segments": [{"clip": seg["clip"], "first_frame": seg["first_frame"], "clip_frames": seg["clip_frames"],
                          "cycle_gap_rms_m": seg["cycle_gap_rms_m"]} for seg in played.timeline["segments"]],
        })
    quality = simulation.quality()
    files["sample"] = out / "sample.json"
    manifest_files = {name: path.relative_to(out).as_posix() for name, path in files.items()}
    manifest_files["sample"] = "sample.json"
    _write_json(
        files["sample"],
        {
            "garment": garment,
            "cycles": cycles if played is None else None,
            "seed": seed,
            "fps": FPS,
            "cycle_frames": cycle_frames,
            "frame_count": simulation.frame_count,
            "animation_duration_s": cycle_frames / FPS,
            **({} if played is None else {"clips": _clips_entry(played)}),
            **({} if body_build == STANDARD else {"build": asdict(body_build)}),
            "units": "metres, Y up, character faces +Z",
            "uv_convention": "glTF: (0, 0) is the top-left texel; cloth.obj stores v flipped as OBJ does",
            "texture_size": texture_size,
            "diffuse_variations": VARIATION_COUNT,
            "outfits": OUTFIT_COUNT,
            "region_alpha": "alpha = 17 * code",
            "regions": {str(code): name for code, name in regions.REGION_NAMES.items()},
            "body": {"vertices": int(len(simulation.body.positions)), "triangles": int(len(simulation.body.faces)), "joints": len(character.joint_names)},
            "cloth": {"vertices": int(simulation.points.shape[1]), "triangles": int(len(cut.faces)), "pinned": int(len(cut.pinned))},
            "quality": quality,
            "files": manifest_files,
        },
    )
    return SampleResult(out, files, settling, settled, quality)


def _clips_entry(played: ClipsSimulation) -> dict:
    """sample.json's `clips`: each animation's frames and seconds, the sequence played and the blend."""
    timeline = played.timeline
    return {
        "animations": {name: {"frames": len(channels[0].times) - 1, "seconds": round((len(channels[0].times) - 1) / FPS, 6)}
                       for name, channels in played.animations.items()},
        "sequence": [[seg["clip"], seg["repeats"]] for seg in timeline["segments"]],
        "blend_frames": timeline["blend_frames"],
        "timeline": "timeline.json",
    }
