"""Impostor atlases: one frame's views as a grid of tiles (SPEC.md, "Impostor maps").

Column a holds azimuth azimuths_deg[a], row e elevation elevations_deg[e]. Every view is rendered as a
square tile of tile_size² texels framing the bounds sphere; the atlas stores of each tile only its crop, one
rectangle (x, y, width, height) shared by every view and frame that holds everything the character covers
in any of them (silhouette_crop). Stored cell (a, e) covers atlas texels [a·width, (a+1)·width) ×
[e·height, (e+1)·height) and holds the tile's texels [x, x+width) × [y, y+height); tile texels outside the
crop are not covered. Without a crop the cell is the whole tile. A tall, thin figure covers little of its
square tile, so the crop about halves the maps' memory at no cost in fidelity. Each map kind (normal, uv,
detail, surface) gets one atlas per baked frame, and the frames become the layers of one CBTX texture
array. Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AtlasLayout:
    """The view grid of the impostor atlases: tile size in texels, azimuths and elevations in degrees, and
    the crop (x, y, width, height) in tile texels every stored cell holds (None: the whole tile)."""

    tile_size: int
    azimuths_deg: tuple[float, ...]
    elevations_deg: tuple[float, ...]
    crop: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        if self.tile_size < 4 or self.tile_size % 4:
            raise ValueError(f"tile_size must be a positive multiple of 4 (block compression), got {self.tile_size}")
        if self.crop is not None:
            x, y, width, height = self.crop
            if min(self.crop) < 0 or width < 4 or height < 4 or x + width > self.tile_size or y + height > self.tile_size:
                raise ValueError(f"crop {self.crop} is not a rectangle of at least 4x4 texels inside the {self.tile_size}² tile")
            if any(value % 4 for value in self.crop):
                raise ValueError(f"crop {self.crop} must lie on 4-texel blocks (block compression)")
        if not self.azimuths_deg or not self.elevations_deg:
            raise ValueError("an atlas needs at least one azimuth and one elevation")
        if any(not 0.0 <= a < 360.0 for a in self.azimuths_deg):
            raise ValueError(f"azimuths must lie in [0, 360), got {self.azimuths_deg}")
        if any(not -90.0 <= e <= 90.0 for e in self.elevations_deg):
            raise ValueError(f"elevations must lie in [-90, 90], got {self.elevations_deg}")

    @classmethod
    def rings(cls, tile_size: int, azimuth_count: int, elevations_deg: tuple[float, ...]) -> "AtlasLayout":
        """`azimuth_count` evenly spaced azimuths from 0 (the character's front) at each elevation."""
        if azimuth_count < 1:
            raise ValueError(f"azimuth_count must be at least 1, got {azimuth_count}")
        azimuths = tuple(360.0 * a / azimuth_count for a in range(azimuth_count))
        return cls(int(tile_size), azimuths, tuple(float(e) for e in elevations_deg))

    @classmethod
    def from_manifest(cls, impostor: dict) -> "AtlasLayout":
        """The layout of a manifest's `impostor` section (or a record's AtlasLayout.to_manifest())."""
        crop = impostor.get("crop")
        box = None if crop is None else (int(crop["x"]), int(crop["y"]), int(crop["width"]), int(crop["height"]))
        return cls(int(impostor["tile_size"]), tuple(impostor["azimuths_deg"]), tuple(impostor["elevations_deg"]), box)

    @property
    def crop_box(self) -> tuple[int, int, int, int]:
        """(x, y, width, height) of the stored part of every tile: the crop, or the whole tile."""
        return self.crop if self.crop is not None else (0, 0, self.tile_size, self.tile_size)

    def crop_box_manifest(self) -> dict[str, int]:
        """crop_box as {"x", "y", "width", "height"}."""
        return dict(zip(("x", "y", "width", "height"), self.crop_box))

    @property
    def cell_width(self) -> int:
        return self.crop_box[2]

    @property
    def cell_height(self) -> int:
        return self.crop_box[3]

    @property
    def width(self) -> int:
        return self.cell_width * len(self.azimuths_deg)

    @property
    def height(self) -> int:
        return self.cell_height * len(self.elevations_deg)

    @property
    def views(self) -> list[tuple[int, int]]:
        """Every (azimuth index, elevation index), elevation-major (atlas rows top to bottom)."""
        return [(a, e) for e in range(len(self.elevations_deg)) for a in range(len(self.azimuths_deg))]

    def tile_slices(self, azimuth_index: int, elevation_index: int) -> tuple[slice, slice]:
        """(rows, columns) slices of the stored cell of view (a, e) in an (height, width, ...) atlas."""
        if not (0 <= azimuth_index < len(self.azimuths_deg) and 0 <= elevation_index < len(self.elevations_deg)):
            raise IndexError(f"tile ({azimuth_index}, {elevation_index}) is outside the {len(self.azimuths_deg)}x{len(self.elevations_deg)} grid")
        w, h = self.cell_width, self.cell_height
        return slice(elevation_index * h, (elevation_index + 1) * h), slice(azimuth_index * w, (azimuth_index + 1) * w)

    def to_manifest(self) -> dict:
        manifest = {
            "tile_size": self.tile_size,
            "azimuths_deg": list(self.azimuths_deg),
            "elevations_deg": list(self.elevations_deg),
        }
        if self.crop is not None:
            manifest["crop"] = self.crop_box_manifest()
        return manifest


def crop_tile(layout: AtlasLayout, tile: np.ndarray) -> np.ndarray:
    """The stored cell (height, width, ...) of a (tile, tile, ...) view: a view into it, not a copy."""
    x, y, width, height = layout.crop_box
    return tile[y:y + height, x:x + width]


def uncrop_tile(layout: AtlasLayout, cell: np.ndarray, edge: bool = False) -> np.ndarray:
    """The (tile, tile, ...) view from its stored cell: texels outside the crop are zero (not covered), or
    with `edge` repeat the cell's border (a map dilated into the background, read as a clamped sampler
    reads it)."""
    x, y, width, height = layout.crop_box
    if cell.shape[:2] != (height, width):
        raise ValueError(f"uncrop_tile: cell is {cell.shape[:2]}, the crop is {(height, width)}")
    pad = [(y, layout.tile_size - y - height), (x, layout.tile_size - x - width)] + [(0, 0)] * (cell.ndim - 2)
    return np.pad(cell, pad, mode="edge") if edge else np.pad(cell, pad)


def silhouette_crop(xy_min: np.ndarray, xy_max: np.ndarray, tile_size: int, margin: int = 0) -> tuple[int, int, int, int]:
    """The crop (x, y, width, height) in tile texels holding the box [xy_min, xy_max] (texel-space x right,
    y down, as crowdbake.bake.impostor_views.project gives them, over every view and frame) with `margin`
    texels around it, on 4-texel blocks, inside the tile.

    No margin by default: every reader clamps its reads to the cell (crowdview's bilinear reads to the
    cell's outer texel centres, which repeat the dilated background as a margin would; nearest reads test
    the crop), so texels of background beyond the box would only take memory from frames and views."""
    low = np.floor(np.asarray(xy_min, dtype=np.float64)) - margin
    high = np.ceil(np.asarray(xy_max, dtype=np.float64)) + margin
    x0, y0 = (int(max(0, (v // 4) * 4)) for v in low)
    x1, y1 = (int(min(tile_size, -(-v // 4) * 4)) for v in high)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return 0, 0, tile_size, tile_size
    return x0, y0, x1 - x0, y1 - y0


def assemble(layout: AtlasLayout, tiles: dict[tuple[int, int], np.ndarray]) -> np.ndarray:
    """One frame's atlas (height, width, C) from tiles {(a, e): (tile, tile, C)}, each cropped to its cell;
    every view must be given."""
    missing = [view for view in layout.views if view not in tiles]
    if missing:
        raise ValueError(f"assemble: {len(missing)} views have no tile, first {missing[0]}")
    first = tiles[layout.views[0]]
    t = layout.tile_size
    if first.ndim != 3 or first.shape[:2] != (t, t):
        raise ValueError(f"assemble: tiles must be ({t}, {t}, C), got {first.shape}")
    atlas = np.zeros((layout.height, layout.width, first.shape[2]), dtype=first.dtype)
    for (a, e), tile in tiles.items():
        if tile.shape != first.shape or tile.dtype != first.dtype:
            raise ValueError(f"assemble: tile ({a}, {e}) is {tile.shape} {tile.dtype}, expected {first.shape} {first.dtype}")
        rows, columns = layout.tile_slices(a, e)
        atlas[rows, columns] = crop_tile(layout, tile)
    return atlas


def tile_of(layout: AtlasLayout, atlas: np.ndarray, azimuth_index: int, elevation_index: int) -> np.ndarray:
    """The stored cell (height, width, C) of view (a, e) of an atlas (a view into it, not a copy)."""
    if atlas.shape[:2] != (layout.height, layout.width):
        raise ValueError(f"tile_of: atlas is {atlas.shape[:2]}, layout needs {(layout.height, layout.width)}")
    rows, columns = layout.tile_slices(azimuth_index, elevation_index)
    return atlas[rows, columns]


def view_tile(layout: AtlasLayout, atlas: np.ndarray, azimuth_index: int, elevation_index: int, edge: bool = False) -> np.ndarray:
    """The whole (tile, tile, C) view (a, e) of an atlas, outside its crop as uncrop_tile fills it (a copy)."""
    return uncrop_tile(layout, tile_of(layout, atlas, azimuth_index, elevation_index), edge)


def nearest_view(layout: AtlasLayout, azimuth_deg: float, elevation_deg: float) -> tuple[int, int]:
    """(a, e) of the baked view closest in angle to a viewing direction; ties go to the lower index.

    What a runtime shows between baked views: the nearest tile, unchanged.
    """
    def direction(azimuth: float, elevation: float) -> np.ndarray:
        az, el = np.radians(azimuth), np.radians(elevation)
        return np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])

    wanted = direction(azimuth_deg, elevation_deg)
    best, best_cos = (0, 0), -np.inf
    for a, e in sorted(layout.views, key=lambda view: (view[1], view[0])):
        cosine = float(direction(layout.azimuths_deg[a], layout.elevations_deg[e]) @ wanted)
        if cosine > best_cos + 1e-12:
            best, best_cos = (a, e), cosine
    return best
