"""The measurements behind one impostor budget per character of several clips (crowdbake.bake.
impostor_allocation): per clip and transition, and per frame count on its ladder, how crowdview's
impostor looks between two baked frames.

A probe bakes the range at that count as the bake would (the same map shader, each baked frame's
surface-map motion towards its neighbours at that count, the bundle's block compression), but only at a
few views: PROBE_AZIMUTHS spread round the middle elevation ring. At up to PROBE_GAPS gaps between baked
frames, spread along the range, crowdview's shader (crowdbake.render.runtime_shader) draws the blend of
the two frames at the pose frame halfway, and it is compared (SSIM, crowdbake.bake.fidelity) with the
mesh drawn there as the fidelity references are. The score of a (range, count) is the mean over those
views and gaps: the error the frame count adds, since at the baked views the view blend adds nothing.

Runs in the impostor plan, before any impostor task: the plan's frames are what it chooses.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import replace
from typing import Callable

import numpy as np

from crowdbake.bake import fidelity, impostor_allocation, surface_maps, view_blend
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.formats.binary import decode_texture_array, encode_texture_array
from crowdbake.formats.ranges import Clip, Ranges
from crowdbake.render.runtime_shader import RuntimeAtlas
from crowdbake.stages.impostors import Scene, mesh_footprints, mesh_references, render_task, spread_gaps
from crowdbake.stages.pack import encode_frame
from crowdbake.stages.records import ImpostorPlan, ImpostorTask
from crowdbake.stages.runtime_fidelity import picture_at

# Views a probe draws (azimuths spread round the middle ring) and gaps it scores per (range, count): a
# probe's cost is about PROBE_AZIMUTHS x (2 PROBE_GAPS frames' maps + PROBE_GAPS references).
PROBE_AZIMUTHS = 4
PROBE_GAPS = 4
# The probe views' meshes a Prober keeps for reuse (Prober.mesh): about 540 frames at 88², 16 at 512².
MESH_CACHE_BYTES = 256 * 1024 * 1024


def probe_layout(layout: AtlasLayout) -> AtlasLayout:
    """The views probes draw: PROBE_AZIMUTHS of the layout's azimuths spread round its middle ring, with
    the layout's tile and crop."""
    azimuths = tuple(layout.azimuths_deg[i] for i in spread_gaps(len(layout.azimuths_deg), PROBE_AZIMUTHS))
    ring = layout.elevations_deg[len(layout.elevations_deg) // 2]
    return AtlasLayout(layout.tile_size, azimuths, (ring,), layout.crop)


def at_views_probe(layout: AtlasLayout) -> tuple[AtlasLayout, list[tuple[float, float]]]:
    """The probe layout (probe_layout) and its own views as cameras: where the impostor is sharpest."""
    probe = probe_layout(layout)
    return probe, [(azimuth, probe.elevations_deg[0]) for azimuth in probe.azimuths_deg]


def azimuth_gap_probe(tile: int, count: int, elevation: float, crop) -> tuple[AtlasLayout, list[tuple[float, float]]]:
    """A layout of `count` azimuths (as AtlasLayout.rings) at one ring, holding only the two azimuths either
    side of PROBE_AZIMUTHS gaps spread round it, and the cameras halfway across those gaps."""
    azimuths = [360.0 * a / count for a in range(count)]
    if count < 2:
        return AtlasLayout(tile, tuple(azimuths), (elevation,), crop), [((azimuths[0] + 180.0) % 360.0, elevation)]
    gaps = spread_gaps(count, PROBE_AZIMUTHS)
    held = sorted({azimuths[g] for g in gaps} | {azimuths[(g + 1) % count] for g in gaps})
    cameras = [(((azimuths[g] + (azimuths[g + 1] if g + 1 < count else 360.0)) / 2.0) % 360.0, elevation) for g in gaps]
    return AtlasLayout(tile, tuple(held), (elevation,), crop), cameras


def elevation_gap_probe(layout: AtlasLayout) -> tuple[AtlasLayout, list[tuple[float, float]]] | None:
    """The probe layout's azimuths at the two rings either side of the middle ring's lower gap, and the
    cameras halfway between them; None for one ring."""
    rings = sorted(layout.elevations_deg)
    if len(rings) < 2:
        return None
    upper = max(1, len(rings) // 2)
    pair = (rings[upper - 1], rings[upper])
    azimuths = probe_layout(layout).azimuths_deg
    return (AtlasLayout(layout.tile_size, azimuths, pair, layout.crop),
            [(azimuth, (pair[0] + pair[1]) / 2.0) for azimuth in azimuths])


def motion_neighbours(item, frames: list[int], frame: int) -> tuple[int | None, int | None]:
    """The baked frames (previous, following) the surface map's motion at `frame` is taken between, when
    the range bakes `frames` (as crowdbake.stages.impostors.previous_baked_frame / next_baked_frame: a
    clip wraps, a transition's ends lead to themselves)."""
    k = frames.index(frame)
    if isinstance(item, Clip):
        previous, following = frames[k - 1], frames[(k + 1) % len(frames)]
    else:
        previous, following = frames[max(k - 1, 0)], frames[min(k + 1, len(frames) - 1)]
    return surface_maps.motion_sides(frame, previous, following)


def draw(atlas: RuntimeAtlas, pictures: list) -> np.ndarray:
    """crowdview's shader drawing `pictures` of `atlas`: (P, S, S, 3)."""
    from crowdbake.render.impostor import shared_renderer

    return shared_renderer(atlas.tile_size).runtime_impostors(atlas, pictures)


def mean_ssim(references: list[np.ndarray], drawn: np.ndarray) -> float:
    """Mean SSIM (crowdbake.bake.fidelity) of each drawn picture against its reference."""
    return float(np.mean([fidelity.compare(reference, picture.astype(np.float64))["ssim"] for reference, picture in zip(references, drawn)]))


class Prober:
    """Scores (range, count) pairs of one character. scene_at(frame) -> Scene: the high LOD at any pose
    frame with its textures (diffuse as given and as the runtime samples it); plan: the impostor plan's
    framing (its layout sets the tile and crop); formats: the bundle's impostor map formats."""

    def __init__(self, ranges: Ranges, plan: ImpostorPlan, scene_at: Callable[[int], Scene], formats: dict[str, str],
                 has_regions: list[bool]):
        self.ranges = ranges
        self.has_regions = list(has_regions)
        self.layout = probe_layout(AtlasLayout.from_manifest(plan.layout))
        self.plan = replace(plan, layout=self.layout.to_manifest())
        self.scene_at = scene_at
        self.formats = {kind: formats[kind] for kind in ("normal", "uv", "surface")}
        self.seconds = 0.0
        self._meshes: OrderedDict[int, np.ndarray] = OrderedDict()

    def mesh(self, frame: int) -> np.ndarray:
        """The mesh at pose frame `frame` from every probe view: (A, S, S, 7), its reference (RGB), then its
        texels' footprints (mesh_footprints: mean normal, share). A frame is drawn once for every count that
        bakes it or scores a gap at it (while MESH_CACHE_BYTES hold it)."""
        if frame in self._meshes:
            self._meshes.move_to_end(frame)
            return self._meshes[frame]
        angles = [(a, self.layout.elevations_deg[0]) for a in self.layout.azimuths_deg]
        scene = self.scene_at(frame)
        drawn = np.concatenate([mesh_references(scene, self.plan, angles), mesh_footprints(scene, self.plan, angles)], axis=-1)
        self._meshes[frame] = drawn
        while len(self._meshes) > 1 and sum(held.nbytes for held in self._meshes.values()) > MESH_CACHE_BYTES:
            self._meshes.popitem(last=False)  # the least recently used: a long range at a large tile
        return drawn

    def references(self, frame: int) -> np.ndarray:
        """The mesh at pose frame `frame` from every probe view: (A, S, S, 3)."""
        return self.mesh(frame)[..., :3]

    def layer(self, item, frames: list[int], frame: int, layout: AtlasLayout | None = None) -> dict[str, bytes]:
        """One baked frame's probe maps of `layout` (None: the probe layout), encoded as the bundle stores
        them: {kind: layer bytes}."""
        footprints = self.mesh(frame)[..., 3:] if layout is None else None
        layout = self.layout if layout is None else layout
        scene = self.scene_at(frame)
        sides = motion_neighbours(item, frames, frame)
        previous, following = (None if side is None else self.scene_at(side).positions for side in sides)
        next_positions = surface_maps.motion_positions(scene.positions, previous, following)
        task = ImpostorTask(id=f"probe-{frame}", frame=frame, elevation=0, views=[list(view) for view in layout.views], references=False)
        part = render_task(scene, replace(self.plan, layout=layout.to_manifest()), task, {"render": 0.0, "maps": 0.0, "references": 0.0},
                           next_positions, footprints)
        layers, *_ = encode_frame(layout, [part], self.formats, False)
        return layers

    def between_score(self, index: int, frames: list[int], tile: int, azimuth_count: int, elevations: tuple[float, ...], crop) -> float:
        """Mean SSIM of crowdview's impostor of range `index` baked at `frames` with `azimuth_count` azimuths
        a ring at `elevations` and `tile`² tiles (crop: in tile texels), where it blends most: halfway
        between two baked azimuths, two rings and two baked frames, as fidelity.json's between_views. At
        most PROBE_GAPS frame gaps spread along the range, each seen across one azimuth gap of those
        spread round the ring, between the middle ring and the one below; each probe atlas holds only the
        four views its camera blends."""
        started = time.perf_counter()
        item = self.ranges.all()[index]
        gaps = impostor_allocation.gaps_to_score(item, frames, PROBE_GAPS)
        azimuths = [360.0 * a / azimuth_count for a in range(azimuth_count)]
        rings = sorted(elevations)
        upper = max(1, len(rings) // 2) if len(rings) > 1 else 0
        pair = (rings[upper - 1], rings[upper]) if len(rings) > 1 else (rings[0],)
        elevation = sum(pair) / len(pair)
        azimuth_gaps = spread_gaps(azimuth_count, len(gaps))
        scores = []
        for k, gap in enumerate(gaps):
            g = azimuth_gaps[k % len(azimuth_gaps)]
            held = sorted({azimuths[g], azimuths[(g + 1) % azimuth_count]})
            following = azimuths[g + 1] if g + 1 < azimuth_count else 360.0 + azimuths[0]
            camera = (((azimuths[g] + following) / 2.0) % 360.0 if azimuth_count > 1 else (azimuths[0] + 180.0) % 360.0, elevation)
            layout = AtlasLayout(tile, tuple(held), pair, crop)
            needed = sorted({gap.first, gap.second})
            layers = [self.layer(item, frames, f, layout) for f in needed]
            blend = view_blend.FrameWeights((needed.index(gap.first), needed.index(gap.second)), gap.weight)
            drawn = draw(self.atlas(layout, layers, self.scene_at(frames[0])), [picture_at(layout, *camera, blend)])
            plan = replace(self.plan, layout=layout.to_manifest())
            scores.append(mean_ssim(list(mesh_references(self.scene_at(gap.between), plan, [camera])), drawn))
        self.seconds += time.perf_counter() - started
        return float(np.mean(scores))

    def score(self, index: int, count: int) -> float:
        """Mean SSIM of crowdview's impostor between baked frames of range `index` (ranges.all() order) baked
        at `count` frames, against the mesh (module docstring)."""
        started = time.perf_counter()
        item = self.ranges.all()[index]
        frames = impostor_allocation.frames_at(self.ranges, index, count)
        gaps = impostor_allocation.gaps_to_score(item, frames, PROBE_GAPS)
        needed = sorted({f for gap in gaps for f in (gap.first, gap.second)})
        layers = [self.layer(item, frames, f) for f in needed]
        atlas = self.atlas(self.layout, layers, self.scene_at(frames[0]))
        pictures, references = [], []
        for gap in gaps:
            blend = view_blend.FrameWeights((needed.index(gap.first), needed.index(gap.second)), gap.weight)
            pictures.extend(picture_at(self.layout, azimuth, self.layout.elevations_deg[0], blend) for azimuth in self.layout.azimuths_deg)
            references.extend(self.references(gap.between))
        score = mean_ssim(references, draw(atlas, pictures))
        self.seconds += time.perf_counter() - started
        return score

    def atlas(self, layout: AtlasLayout, layers: list[dict[str, bytes]], scene: Scene) -> RuntimeAtlas:
        """The probe's baked layers ({kind: layer bytes} per baked frame) as crowdview samples them."""
        maps = {kind: decode_texture_array(encode_texture_array(layout.width, layout.height, fmt, [layer[kind] for layer in layers]),
                                           f"probe {kind} map")
                for kind, fmt in self.formats.items()}
        return RuntimeAtlas(layout.tile_size, tuple(layout.azimuths_deg), tuple(layout.elevations_deg),
                            np.asarray(self.plan.center, dtype=np.float64), float(self.plan.radius), maps["uv"], maps["normal"],
                            maps["surface"], list(scene.diffuse_runtime), self.has_regions, scene.outfit_row, layout.crop_box)

    def views_score(self, layout: AtlasLayout, frame: int, cameras: list[tuple[float, float]]) -> float:
        """Mean SSIM of crowdview's impostor of `layout` (its tile, azimuths, rings and crop) baked at pose
        frame `frame` alone, from each (azimuth, elevation) camera in degrees, against the mesh there: what
        the tile and the views cost, with no frame blend. Every view of the layout is drawn, so a probe
        layout holds only the views its cameras blend (the runtime's blend finds neighbours among any
        azimuths: crowdbake.bake.view_blend)."""
        started = time.perf_counter()
        plan = replace(self.plan, layout=layout.to_manifest())
        scene = self.scene_at(frame)
        task = ImpostorTask(id=f"probe-views-{frame}", frame=frame, elevation=0, views=[list(view) for view in layout.views], references=False)
        part = render_task(scene, plan, task, {"render": 0.0, "maps": 0.0, "references": 0.0})
        layers, *_ = encode_frame(layout, [part], self.formats, False)
        still = view_blend.FrameWeights((0, 0), 0.0)
        pictures = [picture_at(layout, azimuth, elevation, still) for azimuth, elevation in cameras]
        score = mean_ssim(list(mesh_references(scene, plan, cameras)), draw(self.atlas(layout, [layers], scene), pictures))
        self.seconds += time.perf_counter() - started
        return score

    def table(self, most: int) -> list[dict[int, float]]:
        """Per range (ranges.all() order) {count: score} over its ladder (impostor_allocation.ladder, at most
        `most` frames)."""
        return [self.range_table(index, counts) for index, counts in enumerate(impostor_allocation.ladders(self.ranges, most))]

    def range_table(self, index: int, counts: list[int]) -> dict[int, float]:
        """{count: score} of one range, as probed: its ladder's top, then every other count from the bottom
        up to the first within impostor_allocation.TOLERANCE of the best so far. The allocation never bakes
        more than that count (it is step 1's choice), so the counts above it are not probed; the counts
        skipped between are interpolated (impostor_allocation.interpolated)."""
        table = {counts[-1]: self.score(index, counts[-1])}
        best = float("-inf")
        for count in impostor_allocation.probed_counts(counts)[:-1]:
            table[count] = self.score(index, count)
            best = max(best, table[count])
            if best >= max(table.values()) - impostor_allocation.TOLERANCE:
                break
        return table
