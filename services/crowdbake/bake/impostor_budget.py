"""How much of a character's impostor a clip can hold: the crop every view needs, and the view and frame
counts that fit a memory budget.

A bake's impostor holds, per baked frame and view, one cell of the crop's width × height texels in every
stored map (SPEC.md "Impostor maps"). The crop depends on where the character's vertices go, not on
which azimuths are baked: a point at distance ρ from the vertical axis through the bounds centre is seen
at every sideways offset in [-ρ, ρ] as the camera circles it, and at elevation e its height on the view
is (y - y_centre)·cos e ± ρ·sin e. `frame_extents` measures those per frame once; any choice of azimuths
and frames then has its crop, and so its bytes, without projecting again.

`fit_budget` picks the counts: azimuths first fall (in steps of 4, to AZIMUTH_FLOOR), then frames (to
FRAME_FLOOR), until the maps fit. Fewer frames cost CesiumMan's long skirt most of its fidelity between
views and frames, its cloth moving further between baked frames than any view step reveals; the robot
loses more to fewer views (services/benchmarks/bench_impostor_budget.py, docs/bake.md "Memory"). Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.atlas import silhouette_crop
from crowdbake.bake.poses import impostor_frame_indices
from crowdbake.formats.binary import layer_size

AZIMUTH_STEP = 4
AZIMUTH_FLOOR = 12
FRAME_FLOOR = 6
MOTION_PERCENTILE = 95.0


DETAIL_FORMATS = {True: "bc2", False: "rgba8"}  # compressed or not


def map_formats(compress: bool, uv_format: str, detail_map: bool = True) -> dict[str, str]:
    """Pixel formats of the impostor maps the bundle stores, when compressing: DXT3 detail (paper section 5),
    only with `detail_map`; BC5 normals, two components in each tile's view at 1 byte a texel, where the
    paper's DXT1 (0.5 byte) costs the impostor 0.016 SSIM against the mesh (docs/bake.md); DXT3 for the
    surface map: smooth depth and motion, and the 4-bit alpha of the character's share of each texel
    (SPEC.md "Impostor maps"), which draws anti-aliased silhouettes."""
    formats = {"normal": "bc5" if compress else "rgba8", "uv": uv_format, "detail": DETAIL_FORMATS[compress],
               "surface": "bc2" if compress else "rgba8"}
    if not detail_map:
        del formats["detail"]
    return formats


def bytes_per_texel(formats: dict[str, str]) -> float:
    """Bytes a texel of every stored map together (a block-compressed format's block over its 16 texels)."""
    return sum(layer_size(pixel_format, 4, 4) / 16 for pixel_format in formats.values())


@dataclass(frozen=True)
class FrameExtents:
    """Per cycle frame, metres from the bounds centre: `reach` (F,) the largest distance of a vertex from
    the vertical axis; `low`, `high` (F, E) the lowest and highest a vertex can appear on a view of each
    elevation ring, over every azimuth."""

    reach: np.ndarray
    low: np.ndarray
    high: np.ndarray


def frame_extents(positions: np.ndarray, center, elevations_deg) -> FrameExtents:
    """FrameExtents of (F, V, 3) model-space vertex positions (metres) for views framed on `center` (3,)."""
    offset = np.asarray(positions, dtype=np.float64) - np.asarray(center, dtype=np.float64)
    rho = np.hypot(offset[..., 0], offset[..., 2])  # (F, V)
    e = np.radians(np.asarray(elevations_deg, dtype=np.float64))
    height = offset[..., 1, None] * np.cos(e) # (F, V, E)
    swing = rho[..., None] * np.abs(np.sin(e))
    return FrameExtents(rho.max(axis=1), (height - swing).min(axis=1), (height + swing).max(axis=1))


def crop_for(extents: FrameExtents, frames: list[int], radius: float, tile_size: int) -> tuple[int, int, int, int]:
    """The crop (x, y, width, height) in tile texels holding the character in every view of `frames` (cycle
    frame indices), for tiles of `tile_size` texels framing the sphere of `radius` metres."""
    scale = tile_size / (2.0 * radius)
    reach = float(extents.reach[frames].max())
    top, bottom = float(extents.high[frames].max()), float(extents.low[frames].min())
    # Tile texels: x = (right + r)·scale, y = (r - up)·scale (crowdbake.bake.impostor_views.project).
    xy_min = np.array([(radius - reach) * scale, (radius - top) * scale])
    xy_max = np.array([(radius + reach) * scale, (radius - bottom) * scale])
    return silhouette_crop(xy_min, xy_max, tile_size)


@dataclass(frozen=True)
class BudgetChoice:
    """What `fit_budget` chose: the counts, the crop, the bytes of one clip's maps, and the steps it took
    from the counts asked for (each (azimuths, frames, bytes)), the first being what was asked."""

    azimuths: int
    frames: int
    crop: tuple[int, int, int, int]
    bytes: int
    fits: bool
    steps: list[tuple[int, int, int]]


def clip_bytes(azimuths: int, rings: int, frame_count: int, crop: tuple[int, int, int, int], bytes_per_texel: float) -> int:
    """Bytes of one clip's stored impostor maps: a crop-sized cell per view and baked frame."""
    return int(round(azimuths * rings * frame_count * crop[2] * crop[3] * bytes_per_texel))


def fit_budget(extents: FrameExtents, radius: float, tile_size: int, azimuths: int, rings: int, frames: int, cycle_frames: int,
               bytes_per_texel: float, budget_bytes: float | None) -> BudgetChoice:
    """The azimuth and frame counts within `budget_bytes` (None: as asked): azimuths fall by AZIMUTH_STEP to
    AZIMUTH_FLOOR, then frames by one to FRAME_FLOOR, never below what was asked for either floor. `fits`
    is False where even the floors are over the budget (the floors are kept)."""
    def measure(a: int, f: int) -> tuple[tuple[int, int, int, int], int]:
        crop = crop_for(extents, impostor_frame_indices(cycle_frames, f), radius, tile_size)
        return crop, clip_bytes(a, rings, len(impostor_frame_indices(cycle_frames, f)), crop, bytes_per_texel)

    a, f = azimuths, frames
    crop, size = measure(a, f)
    steps = [(a, f, size)]
    if budget_bytes is not None:
        while size > budget_bytes and a - AZIMUTH_STEP >= min(AZIMUTH_FLOOR, azimuths):
            a -= AZIMUTH_STEP
            crop, size = measure(a, f)
            steps.append((a, f, size))
        while size > budget_bytes and f - 1 >= min(FRAME_FLOOR, frames):
            f -= 1
            crop, size = measure(a, f)
            steps.append((a, f, size))
    return BudgetChoice(a, f, crop, size, budget_bytes is None or size <= budget_bytes, steps)


def baked_motion(positions: np.ndarray, frames: list[int]) -> float:
    """Metres the character moves between consecutive baked frames (the last to the first too: the cycle
    loops): per pair of baked frames the MOTION_PERCENTILE of its vertices' displacements, the largest pair.
    positions (F, V, 3) metres; frames ascending cycle frame indices. A percentile, not the maximum, so that
    a few stray vertices (a seam, a fold that snaps) do not set the count. The displacement is in 3D, an
    upper bound on what any view sees move."""
    points = np.asarray(positions, dtype=np.float64)
    if len(frames) < 2:
        return 0.0
    here, there = points[frames], points[list(frames[1:]) + [frames[0]]]
    step = np.linalg.norm(there - here, axis=-1)  # (K, V)
    return float(np.percentile(step, MOTION_PERCENTILE, axis=1).max())


def frames_for_motion(positions: np.ndarray, texels_per_metre: float, max_texels: float | None, most: int) -> int:
    """The fewest baked frames, from min(FRAME_FLOOR, most) to `most`, between which the character moves at
    most `max_texels` tile texels (baked_motion × texels_per_metre); `most` where none does or `max_texels`
    is None. positions (F, V, 3) metres over the cycle. Cloth that swings far needs more frames: halfway
    between two baked frames the runtime blends two pictures that differ by that motion (docs/bake.md
    "Memory")."""
    cycle_frames = len(positions)
    most = min(most, cycle_frames)
    if max_texels is None:
        return most
    for count in range(min(FRAME_FLOOR, most), most + 1):
        if baked_motion(positions, impostor_frame_indices(cycle_frames, count)) * texels_per_metre <= max_texels:
            return count
    return most


def extents_of(extents: FrameExtents, first: int, frames: int) -> FrameExtents:
    """The FrameExtents of frames first .. first + frames - 1 (one clip's range of a bundle's pose frames)."""
    rows = slice(first, first + frames)
    return FrameExtents(extents.reach[rows], extents.low[rows], extents.high[rows])


def fit_budget_per_clip(extents: FrameExtents, radius: float, tile_size: int, azimuths: int, rings: int, frames: int | list[int],
                        clips: list[tuple[int, int]], bytes_per_texel: float, budget_bytes: float | None) -> list[BudgetChoice]:
    """fit_budget for each clip of a bundle of several (clips: (first pose frame, frames) each; frames: the
    count asked for every clip, or one per clip, as frames_for_motion gives them): the budget holds per
    clip, as a runtime holds the maps of the clips its characters play. All clips share one atlas layout,
    so one azimuth count: the fewest any clip needs; each clip then keeps the frames that fit at it.
    extents: FrameExtents over every pose frame."""
    if not clips:
        raise ValueError("fit_budget_per_clip: no clips")
    asked = [frames] * len(clips) if isinstance(frames, int) else list(frames)
    if len(asked) != len(clips):
        raise ValueError(f"fit_budget_per_clip: {len(asked)} frame counts for {len(clips)} clips")
    first_pass = [fit_budget(extents_of(extents, first, n), radius, tile_size, azimuths, rings, f, n, bytes_per_texel, budget_bytes)
                  for (first, n), f in zip(clips, asked)]
    shared = min(choice.azimuths for choice in first_pass)
    if shared == azimuths:
        return first_pass
    return [fit_budget(extents_of(extents, first, n), radius, tile_size, shared, rings, f, n, bytes_per_texel, budget_bytes)
            for (first, n), f in zip(clips, asked)]


def budget_document(choice: BudgetChoice, params) -> dict:
    """texture_memory.json's account of the budget (params: BakeParams): what was asked, what was chosen,
    and the bytes of every step between, in MiB."""
    mib = 1024.0 * 1024.0
    return {
        "budget_mib": params.impostor_budget_mib,
        "asked": {"azimuths": params.azimuths, "frames": params.impostor_frames},
        # The frames the character's motion needs (frames_for_motion), before the budget: the first step.
        "motion": {"max_texels": params.impostor_motion_texels, "frames": choice.steps[0][1]},
        "chosen": {"azimuths": choice.azimuths, "frames": choice.frames},
        "fits": choice.fits,
        "steps": [{"azimuths": a, "frames": f, "mib": size / mib} for a, f, size in choice.steps],
        "rule": (f"frames: the fewest (at most the frames asked) between which {MOTION_PERCENTILE:g} % of the vertices move at most "
                 f"motion.max_texels tile texels; then azimuths fall by {AZIMUTH_STEP} to {AZIMUTH_FLOOR}, then frames by 1 to "
                 f"{FRAME_FLOOR}, until the maps fit"),
    }
