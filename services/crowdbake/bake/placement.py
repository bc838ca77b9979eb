"""Does the garment sit on the character? Up axis and units of a cloth cache, checked and converted.

Pure numpy, no I/O. Studios export caches Z-up (Blender, 3ds Max, Houdini by choice) or in
centimetres (Maya, Houdini) or millimetres; crowdbake works in glTF's frame: Y-up, metres. A cache in
the wrong frame bakes a skirt lying beside the body or a hundred times its size, so every entry point
(CLI, REST, bake) calls `check_placement` with the cloth's first frame and the character posed at
the same time, and either gets the conversion to apply or one line to show the user.

The test, in Y-up metres: at least MIN_INSIDE_FRACTION of the cloth's points lie inside the
character's bounding box grown sideways (x, z) by SIDE_MARGIN of its size (a flared skirt, a trailing
cape) but vertically only by UP_MARGIN (cloth hangs between the feet and the head: a Z-up cache
read as Y-up puts half the garment under the floor); the cloth's centre lies over the character's
footprint (a garment floating beside the body does not); and the cloth is neither more than
MAX_SIZE_RATIO times the character's size nor less than MIN_SIZE_RATIO of it. When the frame asked for fails, every other (up axis, unit) is tried: the one
that passes is named in the message with the flag that selects it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

UP_AXES = ("y", "z")
# Metres per unit of the cache.
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
UNIT_NAMES = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "in": "inches"}
# Grow the character's box sideways by this fraction of its largest side: the long skirt of
# ../shared/assets reaches 0.28 of CesiumMan's height beyond his box at rest.
SIDE_MARGIN = 0.35
# ...and vertically by this much: cloth does not hang far under the feet or over the head.
UP_MARGIN = 0.05
# The cloth's centre (x, z) must lie over the character's footprint grown by this fraction.
CENTRE_MARGIN = 0.05
# This share of the cloth's points must fall inside the grown box: a garment floating beside the body
# has almost none there.
MIN_INSIDE_FRACTION = 0.9
# A garment larger than twice the character, or smaller than a tenth of it (a glove is about 0.11 of
# a 1.8 m body), is in the wrong units: centimetres read as millimetres come out 0.1 times too small.
MAX_SIZE_RATIO = 2.0
MIN_SIZE_RATIO = 0.1


def to_y_up_metres(points: np.ndarray, up: str = "y", units: str = "m") -> np.ndarray:
    """Convert points (..., 3) from a cache's frame to Y-up metres -> (..., 3) float32.

    up "z": (x, y, z) -> (x, z, -y), the turn Blender's and glTF's exporters use between Z-up and Y-up.
    units: one of UNITS, scaled to metres."""
    if up not in UP_AXES:
        raise ValueError(f"up must be one of {UP_AXES}, got {up!r}")
    if units not in UNITS:
        raise ValueError(f"units must be one of {tuple(UNITS)}, got {units!r}")
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1:] != (3,):
        raise ValueError(f"points must be (..., 3), got {points.shape}")
    if up == "z":
        points = np.stack([points[..., 0], points[..., 2], -points[..., 1]], axis=-1)
    return (points * UNITS[units]).astype(np.float32)


@dataclass(frozen=True)
class Fit:
    """How cloth points (in Y-up metres) sit on a body: inside_fraction of points in the grown box,
    size_ratio of the cloth's largest side to the body's, centred: the cloth's centre over the footprint."""

    inside_fraction: float
    size_ratio: float
    centred: bool

    @property
    def ok(self) -> bool:
        return self.centred and self.inside_fraction >= MIN_INSIDE_FRACTION and MIN_SIZE_RATIO <= self.size_ratio <= MAX_SIZE_RATIO


def measure_fit(cloth: np.ndarray, body: np.ndarray) -> Fit:
    """cloth (P, 3), body (V, 3), both Y-up metres -> Fit."""
    cloth = np.asarray(cloth, dtype=np.float64).reshape(-1, 3)
    body = np.asarray(body, dtype=np.float64).reshape(-1, 3)
    if len(cloth) == 0 or len(body) == 0:
        raise ValueError("cloth and body need at least one point each")
    low, high = body.min(axis=0), body.max(axis=0)
    body_size = float((high - low).max())
    if body_size <= 0:
        raise ValueError("the character's points all coincide")
    margin = body_size * np.array([SIDE_MARGIN, UP_MARGIN, SIDE_MARGIN])
    inside = ((cloth >= low - margin) & (cloth <= high + margin)).all(axis=1)
    cloth_size = float(np.ptp(cloth, axis=0).max())
    centre = (cloth.min(axis=0) + cloth.max(axis=0)) / 2
    footprint = [0, 2]
    grown = CENTRE_MARGIN * body_size
    centred = bool(((centre[footprint] >= low[footprint] - grown) & (centre[footprint] <= high[footprint] + grown)).all())
    return Fit(float(inside.mean()), cloth_size / body_size, centred)


@dataclass(frozen=True)
class Placement:
    """The verdict. ok: the cloth fits in frame (up, units); message: "" when ok, else one line naming
    the problem and the flag that fixes it; suggested_up / suggested_units: the frame that fits, if any."""

    ok: bool
    up: str
    units: str
    message: str
    fit: Fit
    suggested_up: str | None = None
    suggested_units: str | None = None

    def apply(self, points: np.ndarray) -> np.ndarray:
        """points (..., 3) in the cache's frame -> Y-up metres (float32), the conversion this verdict names."""
        return to_y_up_metres(points, self.up, self.units)


def _bounds(points: np.ndarray) -> str:
    low, high = points.min(axis=0), points.max(axis=0)
    return "[" + ", ".join(f"{a:.3g}..{b:.3g}" for a, b in zip(low, high)) + "]"


def check_placement(cloth_points: np.ndarray, body_points: np.ndarray, up: str | None = None, units: str | None = None) -> Placement:
    """Check a cloth cache's first frame against the character at the same time.

    cloth_points (P, 3) in the cache's own frame; body_points (V, 3) Y-up metres (glTF's frame: pose the
    character, e.g. crowdbake.bake.skinning.pose_character(character, fps, 1)[0][0]); up "y" | "z" and
    units "m" | "cm" | "mm" | "in" as the user declared them (None: "y" and "m").
    Returns a Placement: ok with the conversion to apply, or a refusal whose message names the axis or
    unit problem and the flags that fix it (`--up z`, `--units cm`), or says the garment does not sit
    on the character at all.
    """
    asked_up, asked_units = up or "y", units or "m"
    cloth_points = np.asarray(cloth_points, dtype=np.float64)
    body_points = np.asarray(body_points, dtype=np.float64)
    fit = measure_fit(to_y_up_metres(cloth_points, asked_up, asked_units), body_points)
    if fit.ok:
        return Placement(True, asked_up, asked_units, "", fit)
    # Other frames: those the user left open first, the declared ones kept when declared.
    ups = [asked_up] if up is not None else list(UP_AXES)
    unit_names = [asked_units] if units is not None else list(UNITS)
    for candidate_up in ups:
        for candidate_units in unit_names:
            if (candidate_up, candidate_units) == (asked_up, asked_units):
                continue
            if measure_fit(to_y_up_metres(cloth_points, candidate_up, candidate_units), body_points).ok:
                return Placement(False, asked_up, asked_units, _suggestion(fit, asked_up, asked_units, candidate_up, candidate_units), fit,
                                 candidate_up, candidate_units)
    converted = to_y_up_metres(cloth_points, asked_up, asked_units)
    if fit.size_ratio > MAX_SIZE_RATIO:
        what = f"the cloth is {fit.size_ratio:.3g} times the character's size"
    elif fit.size_ratio < MIN_SIZE_RATIO:
        what = f"the cloth is only {fit.size_ratio:.2g} of the character's size"
    elif not fit.centred:
        what = "the cloth floats beside the character"
    else:
        what = f"only {fit.inside_fraction:.0%} of the cloth lies on the character"
    message = (f"{what} (cloth bounds {_bounds(converted)} m, character {_bounds(body_points)} m, read as {asked_up.upper()}-up "
               f"{UNIT_NAMES[asked_units]}); no up axis or unit fixes it: export the garment where it sits on the character")
    return Placement(False, asked_up, asked_units, message, fit)


def _suggestion(fit: Fit, up: str, units: str, good_up: str, good_units: str) -> str:
    problems, flags = [], []
    if good_up != up:
        problems.append(f"looks {good_up.upper()}-up (read as {up.upper()}-up only {fit.inside_fraction:.0%} of it lies on the character)")
        flags.append(f"--up {good_up}")
    if good_units != units:
        problems.append(f"looks like {UNIT_NAMES[good_units]} (read as {UNIT_NAMES[units]} it is {fit.size_ratio:.3g} times the character's size)")
        flags.append(f"--units {good_units}")
    return f"the cloth cache {' and '.join(problems)}: pass {' '.join(flags)}"
