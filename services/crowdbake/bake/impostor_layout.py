"""The impostor's tile size and azimuth count, chosen with its frames within one budget by measuring.

Three things spend an impostor's memory: texels a view (the tile), views a ring (the azimuths) and baked
frames. Each buys a different part of what crowdview draws: the tile its sharpness at a baked view,
the azimuths what the blend of two neighbouring views loses halfway between them, the frames what the
blend of two baked frames loses halfway between them. Which is worth its bytes depends on the character
(a wide cape needs texels, a swinging one frames, a thin robot views), so a fixed order of cuts (first
azimuths, then frames) served some characters and missed others. Measured instead, with crowdview's own
shader against the mesh (crowdbake.stages.impostor_probe):

- `at_views` {tile: SSIM} at baked views of one frame, per tile on `tile_ladder`;
- `azimuth_scores` {azimuths: SSIM} halfway between neighbouring azimuths, per count on `azimuth_ladder`,
  at the asked tile and a baked frame;
- `elevation_loss`: SSIM lost halfway between neighbouring rings (the rings are as asked);
- per range, {frames: SSIM} halfway between baked frames at baked views and the asked tile
  (crowdbake.bake.impostor_allocation).

Each loss adds to the others (a model: halfway between views and frames the runtime blends both ways),
so a range baked at (tile, azimuths, frames) is predicted to score
frames_score + (at_views[tile] - at_views[asked tile]) - azimuth_loss - elevation_loss between views and
frames, and at_views[tile] at baked views. `choose_layout` tries every (tile, azimuths) pair, splits the
budget's frames among the ranges at that pair's bytes a frame (impostor_allocation.allocate), and scores
the pair by its smaller margin over the impostor targets (AT_VIEWS_TARGET at baked views,
BETWEEN_TARGET between views and frames, the worst range's); of the pairs within `tolerance` of the best
margin it keeps the fewest bytes. fidelity.json then measures what the bake made.

Pure functions; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

from crowdbake.bake import impostor_allocation
from crowdbake.bake.impostor_budget import AZIMUTH_FLOOR, AZIMUTH_STEP
from crowdbake.formats.ranges import Ranges

# The impostor targets (docs/bake.md "Memory"): mean SSIM at baked views and halfway between views and
# frames, crowdview's shader against the mesh at 1:1.
AT_VIEWS_TARGET = 0.95
BETWEEN_TARGET = 0.90
# Tiles tried, as multiples of the asked tile (rounded to 4-texel blocks). Never fewer texels than asked:
# crowdview switches to the impostor where a character covers about a tile (1:1), so a smaller tile
# would move the switch further away and draw more meshes, a cost no fidelity probe sees.
TILE_STEPS = (1.0, 1.125, 1.25, 1.5)
# The fewest azimuths the measured choice tries, below the rule's AZIMUTH_FLOOR: where a budget holds
# several clips, frames can be worth more than views (the robot's and the clips sample's three clips and
# their transitions at 32 MiB score better in their worst range and on the mean at 8 azimuths than at 12).
# Offered 6 as well, both still choose 8: 6 loses too much between views (services/benchmarks/LOG.md
# "Eight azimuths").
MEASURED_AZIMUTH_FLOOR = 8


def tile_ladder(asked: int, most: int) -> list[int]:
    """Tile sizes tried, ascending: TILE_STEPS of the asked tile rounded to multiples of 4, at most `most`
    (the asked tile is always among them)."""
    tiles = {int(asked)}
    for step in TILE_STEPS:
        tile = 4 * int(round(asked * step / 4.0))
        if asked <= tile <= most:
            tiles.add(tile)
    return sorted(tiles)


def azimuth_ladder(asked: int) -> list[int]:
    """Azimuth counts tried, ascending: the asked count and every AZIMUTH_STEP below it down to
    AZIMUTH_FLOOR, then MEASURED_AZIMUTH_FLOOR (or only the asked count, when fewer)."""
    floor = min(AZIMUTH_FLOOR, asked)
    ladder = {int(asked), *range(asked - AZIMUTH_STEP, floor - 1, -AZIMUTH_STEP)} | {floor}
    return sorted(ladder | {min(MEASURED_AZIMUTH_FLOOR, asked)})


def probed_azimuths(asked: int) -> list[int]:
    """The counts of azimuth_ladder(asked) the layout probe draws: every other one from AZIMUTH_FLOOR up
    and the top (impostor_allocation.probed_counts), and MEASURED_AZIMUTH_FLOOR below them: a choice of 12
    or more azimuths rests on the same probes whether or not the ladder goes below AZIMUTH_FLOOR."""
    ladder = azimuth_ladder(asked)
    upper = [count for count in ladder if count >= min(AZIMUTH_FLOOR, asked)]
    return sorted(set(impostor_allocation.probed_counts(upper)) | {ladder[0]})


def rising(table: dict[int, float]) -> dict[int, float]:
    """{count: score} made non-decreasing in count: more texels or views never draw a worse impostor, so a
    lower probe at a larger count is noise (as impostor_allocation.envelope for frames)."""
    return impostor_allocation.envelope(table)


@dataclass(frozen=True)
class LayoutOption:
    """One (tile, azimuths) pair: the frames its budget allows (allocation), the predicted SSIM at baked
    views and, per range, between views and frames, and its margin over the targets."""

    tile: int
    azimuths: int
    allocation: impostor_allocation.Allocation
    at_views: float
    between: list[float]
    margin: float

    @property
    def bytes(self) -> int:
        return self.allocation.bytes


def predicted_tables(frame_tables: list[dict[int, float]], shift: float) -> list[dict[int, float]]:
    """Every range's {frames: SSIM} moved by `shift` (the tile's and azimuths' difference from where the
    frames were probed)."""
    return [{n: s + shift for n, s in table.items()} for table in frame_tables]


def options(ranges: Ranges, frame_tables: list[dict[int, float]], at_views: dict[int, float], azimuth_scores: dict[int, float],
            elevation_loss: float, asked_tile: int, frame_bytes: Callable[[int, int], float], budget_bytes: float | None,
            tolerance: float = impostor_allocation.TOLERANCE) -> list[LayoutOption]:
    """Every (tile of at_views, azimuths of azimuth_scores) with its frames and predicted scores (module
    docstring). frame_tables: per range (ranges.all() order) {frames: SSIM} probed at asked_tile and the
    asked azimuths' baked views; frame_bytes(tile, azimuths): one baked frame's maps; budget_bytes: None,
    no budget."""
    if asked_tile not in at_views:
        raise ValueError(f"options: the asked tile {asked_tile} was not probed at baked views")
    tiles, views = rising(at_views), rising(azimuth_scores)
    # Azimuth loss: what halfway between azimuths loses against a baked view (at the asked tile).
    base = tiles[asked_tile]
    out = []
    for tile, at in sorted(tiles.items()):
        for azimuths, between_views in sorted(views.items()):
            azimuth_loss = max(0.0, base - between_views)
            shift = (at - base) - azimuth_loss - max(0.0, elevation_loss)
            tables = predicted_tables(frame_tables, shift)
            allocation = impostor_allocation.allocate(ranges, tables, frame_bytes(tile, azimuths), budget_bytes, tolerance)
            between = list(allocation.scores)
            margin = min(at - AT_VIEWS_TARGET, min(between) - BETWEEN_TARGET)
            # Over the budget even at the frames' floors: never better than a pair that fits.
            if not allocation.fits:
                margin -= 1.0
            out.append(LayoutOption(tile, azimuths, allocation, at, between, margin))
    return out


def shortlist(candidates: list[LayoutOption], count: int, tolerance: float = impostor_allocation.TOLERANCE) -> list[LayoutOption]:
    """The `count` candidates to measure end to end: the best predicted margin first (the mark the others
    are held to), then those choose_layout would take in turn by their predictions (within `tolerance` of
    the best margin, fewest bytes first), then the rest by margin. Predicted margins a few ten-thousandths
    apart say nothing, so the cheap options near the best are measured rather than a larger tile that
    predicts a hair better."""
    by_margin = sorted(candidates, key=lambda option: (-option.margin, option.bytes))
    if not by_margin:
        return []
    best = by_margin[0]
    near = sorted((o for o in by_margin[1:] if o.margin >= best.margin - tolerance),
                  key=lambda option: (option.bytes, -option.margin, -option.tile, -option.azimuths))
    rest = [o for o in by_margin[1:] if o.margin < best.margin - tolerance]
    return ([best] + near + rest)[:count]


def measured(option: LayoutOption, between: float) -> LayoutOption:
    """`option` with its SSIM between views and frames as measured (not predicted), and its margin from it."""
    margin = min(option.at_views - AT_VIEWS_TARGET, between - BETWEEN_TARGET) - (0.0 if option.allocation.fits else 1.0)
    return replace(option, between=[float(between)], margin=margin)


def choose_layout(candidates: list[LayoutOption], tolerance: float = impostor_allocation.TOLERANCE) -> LayoutOption:
    """Of the candidates within `tolerance` of the best margin, the fewest bytes (then the better margin,
    then the larger tile and more azimuths)."""
    if not candidates:
        raise ValueError("choose_layout: no candidates")
    best = max(option.margin for option in candidates)
    near = [option for option in candidates if option.margin >= best - tolerance]
    return min(near, key=lambda option: (option.bytes, -option.margin, -option.tile, -option.azimuths))


def layout_document(candidates: list[LayoutOption], chosen: LayoutOption, at_views: dict[int, float],
                    azimuth_scores: dict[int, float], elevation_loss: float, checked: list[LayoutOption] | None = None) -> dict:
    """texture_memory.json's account of the choice: the probes, every pair tried (predicted), the ones
    measured end to end (`checked`, if any) and the one kept."""
    mib = 1024.0 * 1024.0

    def entry(o: LayoutOption) -> dict:
        return {"tile": o.tile, "azimuths": o.azimuths, "frames": len(o.allocation.frame_indices()), "mib": round(o.bytes / mib, 3),
                "at_views": round(o.at_views, 4), "between_worst": round(min(o.between), 4), "margin": round(o.margin, 4),
                "fits": o.allocation.fits}

    return {
        "rule": (f"every tile and azimuth count probed, the budget's frames split at each (impostor_allocation), predicted "
                 f"SSIM at baked views and between views and frames (worst range) against the targets {AT_VIEWS_TARGET:g} and "
                 f"{BETWEEN_TARGET:g}; of the pairs within {impostor_allocation.TOLERANCE:g} of the best margin, the fewest bytes"),
        "probed": {"at_views": {str(t): round(float(s), 4) for t, s in sorted(at_views.items())},
                   "between_azimuths": {str(a): round(float(s), 4) for a, s in sorted(azimuth_scores.items())},
                   "elevation_loss": round(float(elevation_loss), 4)},
        "options": [entry(o) for o in candidates],
        "measured": [entry(o) for o in checked or []],
        "chosen": entry(chosen),
    }
