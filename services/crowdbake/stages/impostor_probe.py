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
from dataclasses import replace
from typing import Callable

import numpy as np

from crowdbake.bake import fidelity, impostor_allocation, surface_maps, view_blend
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.formats.binary import decode_texture_array, encode_texture_array
from crowdbake.formats.ranges import Clip, Ranges
from crowdbake.render.runtime_shader import RuntimeAtlas
from crowdbake.stages.impostors import Scene, mesh_references, render_task, spread_gaps
from crowdbake.stages.pack import encode_frame
from crowdbake.stages.records import ImpostorPlan, ImpostorTask
from crowdbake.stages.runtime_fidelity import picture_at

# Views a probe draws (azimuths spread round the middle ring) and gaps it scores per (range, count): a
# probe's cost is about PROBE_AZIMUTHS x (2 PROBE_GAPS frames' maps + PROBE_GAPS references).
PROBE_AZIMUTHS = 4
PROBE_GAPS = 4


def probe_layout(layout: AtlasLayout) -> AtlasLayout:
    """The views probes draw: PROBE_AZIMUTHS of the layout's azimuths spread round its middle ring, with
    the layout's tile and crop."""
    azimuths = tuple(layout.azimuths_deg[i] for i in spread_gaps(len(layout.azimuths_deg), PROBE_AZIMUTHS))
    ring = layout.elevations_deg[len(layout.elevations_deg) // 2]
    return AtlasLayout(layout.tile_size, azimuths, (ring,), layout.crop)


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
        self.views = [[a, 0] for a in range(len(self.layout.azimuths_deg))]
        self.seconds = 0.0
        self._references: dict[int, np.ndarray] = {}

    def references(self, frame: int) -> np.ndarray:
        """The mesh at pose frame `frame` from every probe view: (A, S, S, 3); a frame shared by probes is drawn once."""
        if frame not in self._references:
            angles = [(a, self.layout.elevations_deg[0]) for a in self.layout.azimuths_deg]
            self._references[frame] = mesh_references(self.scene_at(frame), self.plan, angles)
        return self._references[frame]

    def layer(self, item, frames: list[int], frame: int) -> dict[str, bytes]:
        """One baked frame's probe maps, encoded as the bundle stores them: {kind: layer bytes}."""
        scene = self.scene_at(frame)
        sides = motion_neighbours(item, frames, frame)
        previous, following = (None if side is None else self.scene_at(side).positions for side in sides)
        next_positions = surface_maps.motion_positions(scene.positions, previous, following)
        task = ImpostorTask(id=f"probe-{frame}", frame=frame, elevation=0, views=self.views, references=False)
        part = render_task(scene, self.plan, task, {"render": 0.0, "maps": 0.0, "references": 0.0}, next_positions)
        layers, *_ = encode_frame(self.layout, [part], self.formats, False)
        return layers

    def score(self, index: int, count: int) -> float:
        """Mean SSIM of crowdview's impostor between baked frames of range `index` (ranges.all() order) baked
        at `count` frames, against the mesh (module docstring)."""
        started = time.perf_counter()
        item = self.ranges.all()[index]
        frames = impostor_allocation.frames_at(self.ranges, index, count)
        gaps = impostor_allocation.gaps_to_score(item, frames, PROBE_GAPS)
        needed = sorted({f for gap in gaps for f in (gap.first, gap.second)})
        layers = [self.layer(item, frames, f) for f in needed]
        maps = {kind: decode_texture_array(encode_texture_array(self.layout.width, self.layout.height, fmt, [layer[kind] for layer in layers]),
                                           f"probe {kind} map")
                for kind, fmt in self.formats.items()}
        scene = self.scene_at(frames[0])
        atlas = RuntimeAtlas(self.layout.tile_size, tuple(self.layout.azimuths_deg), tuple(self.layout.elevations_deg),
                             np.asarray(self.plan.center, dtype=np.float64), float(self.plan.radius), maps["uv"], maps["normal"],
                             maps["surface"], list(scene.diffuse_runtime), self.has_regions, scene.outfit_row,
                             self.layout.crop_box)
        pictures, references = [], []
        for gap in gaps:
            blend = view_blend.FrameWeights((needed.index(gap.first), needed.index(gap.second)), gap.weight)
            pictures.extend(picture_at(self.layout, azimuth, self.layout.elevations_deg[0], blend) for azimuth in self.layout.azimuths_deg)
            references.extend(self.references(gap.between))
        from crowdbake.render.impostor import shared_renderer

        drawn = shared_renderer(self.layout.tile_size).runtime_impostors(atlas, pictures)
        scores = [fidelity.compare(reference, picture.astype(np.float64))["ssim"] for reference, picture in zip(references, drawn)]
        self.seconds += time.perf_counter() - started
        return float(np.mean(scores))

    def table(self, most: int) -> list[dict[int, float]]:
        """Per range (ranges.all() order) {count: score} over its ladder (impostor_allocation.ladder, at most
        `most` frames)."""
        return [self.range_table(index, counts) for index, counts in enumerate(impostor_allocation.ladders(self.ranges, most))]

    def range_table(self, index: int, counts: list[int]) -> dict[int, float]:
        """{count: score} of one range: its ladder's top, then counts from the bottom up to the first within
        impostor_allocation.TOLERANCE of the best so far. The allocation never bakes more than that count
        (it is step 1's choice), so the counts above it are not probed."""
        table = {counts[-1]: self.score(index, counts[-1])}
        best = float("-inf")
        for count in counts[:-1]:
            table[count] = self.score(index, count)
            best = max(best, table[count])
            if best >= max(table.values()) - impostor_allocation.TOLERANCE:
                break
        return table
