"""Impostor atlases: one frame's views as a grid of tiles (SPEC.md, "Impostor maps").

Column a holds azimuth azimuths_deg[a], row e elevation elevations_deg[e]; tile (a, e) covers texels
[a·tile, (a+1)·tile) × [e·tile, (e+1)·tile). Each map kind (normal, uv, detail) gets one atlas per baked
frame, and the frames become the layers of one CBTX texture array. Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AtlasLayout:
    """The view grid of the impostor atlases: tile size in texels, azimuths and elevations in degrees."""

    tile_size: int
    azimuths_deg: tuple[float, ...]
    elevations_deg: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.tile_size < 4 or self.tile_size % 4:
            raise ValueError(f"tile_size must be a positive multiple of 4 (block compression), got {self.tile_size}")
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

    @property
    def width(self) -> int:
        return self.tile_size * len(self.azimuths_deg)

    @property
    def height(self) -> int:
        return self.tile_size * len(self.elevations_deg)

    @property
    def views(self) -> list[tuple[int, int]]:
        """Every (azimuth index, elevation index), elevation-major (atlas rows top to bottom)."""
        return [(a, e) for e in range(len(self.elevations_deg)) for a in range(len(self.azimuths_deg))]

    def tile_slices(self, azimuth_index: int, elevation_index: int) -> tuple[slice, slice]:
        """(rows, columns) slices of tile (a, e) in an (height, width, ...) atlas."""
        if not (0 <= azimuth_index < len(self.azimuths_deg) and 0 <= elevation_index < len(self.elevations_deg)):
            raise IndexError(f"tile ({azimuth_index}, {elevation_index}) is outside the {len(self.azimuths_deg)}x{len(self.elevations_deg)} grid")
        t = self.tile_size
        return slice(elevation_index * t, (elevation_index + 1) * t), slice(azimuth_index * t, (azimuth_index + 1) * t)

    def to_manifest(self) -> dict:
        return {
            "tile_size": self.tile_size,
            "azimuths_deg": list(self.azimuths_deg),
            "elevations_deg": list(self.elevations_deg),
        }


def assemble(layout: AtlasLayout, tiles: dict[tuple[int, int], np.ndarray]) -> np.ndarray:
    """One frame's atlas (height, width, C) from tiles {(a, e): (tile, tile, C)}; every view must be given."""
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
        atlas[rows, columns] = tile
    return atlas


def tile_of(layout: AtlasLayout, atlas: np.ndarray, azimuth_index: int, elevation_index: int) -> np.ndarray:
    """The (tile, tile, C) view (a, e) of an atlas (a view into it, not a copy)."""
    if atlas.shape[:2] != (layout.height, layout.width):
        raise ValueError(f"tile_of: atlas is {atlas.shape[:2]}, layout needs {(layout.height, layout.width)}")
    rows, columns = layout.tile_slices(azimuth_index, elevation_index)
    return atlas[rows, columns]


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
