"""crowdview's choice of what to blend (runtime/README.md, "Impostor blending", rules 2 to 5;
runtime/src/view_blend.cpp): the four baked views around a camera (bilinear over azimuth × elevation,
azimuth wrapping, elevation clamped) and the two baked frames either side of a cycle frame (linear).

The bake hands these to crowdview's own shader when it scores what the runtime draws
(crowdbake.stages.runtime_fidelity); crowdview's tests read the same vectors
(runtime/tests/data/view_blend_vectors.json, read by test_impostor_blend.py and the view_blend ctest).
Pure numpy; angles in degrees.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

@dataclass(frozen=True)
class ViewWeights:
    """Four atlas tiles (azimuth + elevation · azimuth_count) and their weights (sum 1; unused: 0)."""

    tiles: tuple[int, int, int, int]
    weights: tuple[float, float, float, float]


@dataclass(frozen=True)
class FrameWeights:
    """Two atlas layers (indices into frame_indices); layer 0 gets 1 - weight, layer 1 weight."""

    layers: tuple[int, int]
    weight: float


def view_angles_deg(to_camera: np.ndarray, heading: float = 0.0) -> tuple[float, float]:
    """(azimuth, elevation) in degrees of the (3,) direction from the bounds centre to the camera, in the
    frame of a character turned by `heading` radians about +Y (view_blend.cpp view_angles_deg)."""
    d = np.asarray(to_camera, dtype=np.float64).reshape(3)
    c, s = np.cos(heading), np.sin(heading)
    local = np.array([c * d[0] - s * d[2], d[1], s * d[0] + c * d[2]])
    length = np.linalg.norm(local)
    local = local / length if length > 0 else np.array([0.0, 0.0, 1.0])
    return float(np.degrees(np.arctan2(local[0], local[2]))), float(np.degrees(np.arcsin(np.clip(local[1], -1.0, 1.0))))


def _ccw_gap(start: float, end: float) -> float:
    """Degrees from `start` to `end` going the positive way round, in [0, 360)."""
    gap = float(np.fmod(end - start, 360.0))
    if gap < 0:
        gap += 360.0
    return 0.0 if gap >= 360.0 else gap


def blend_view_weights(azimuth_deg: float, elevation_deg: float, azimuths_deg, elevations_deg) -> ViewWeights:
    """The four views crowdview blends for a camera at (azimuth, elevation), README rules 2 to 4.

    azimuths_deg, elevations_deg: the bundle's baked angles (any order, not empty).
    """
    azimuths = [float(a) for a in azimuths_deg]
    elevations = [float(e) for e in elevations_deg]
    if not azimuths or not elevations:
        raise ValueError("blend_view_weights: azimuths and elevations must not be empty")
    columns = len(azimuths)
    before = [_ccw_gap(a, azimuth_deg) for a in azimuths]
    a0 = int(np.argmin(before))  # first minimum, as the C++ loop's strict '<'
    after = [_ccw_gap(azimuth_deg, a) if index != a0 else np.inf for index, a in enumerate(azimuths)]
    a1 = int(np.argmin(after)) if columns > 1 else a0
    wa = 0.0
    if columns > 1 and before[a0] + after[a1] > 0:
        wa = before[a0] / (before[a0] + after[a1])
    lowest, highest = min(elevations), max(elevations)
    elevation = min(max(elevation_deg, lowest), highest)
    e0, e1 = elevations.index(lowest), elevations.index(highest)
    for index, value in enumerate(elevations):
        if elevation >= value > elevations[e0]:
            e0 = index
        if elevation <= value < elevations[e1]:
            e1 = index
    span = elevations[e1] - elevations[e0]
    we = (elevation - elevations[e0]) / span if span > 0 else 0.0
    return ViewWeights(
        (a0 + e0 * columns, a1 + e0 * columns, a0 + e1 * columns, a1 + e1 * columns),
        ((1 - wa) * (1 - we), wa * (1 - we), (1 - wa) * we, wa * we),
    )


def blend_frame_weights(frame: int, frame_indices, frame_count: int) -> FrameWeights:
    """The two baked frames crowdview blends at integer cycle frame `frame` (README rule 5).

    frame_indices: ascending baked cycle frames, each < frame_count.
    """
    indices = [int(f) for f in frame_indices]
    count = len(indices)
    if count < 2 or frame_count <= 0:
        return FrameWeights((0, 0), 0.0)
    k = count - 1
    for index, baked in enumerate(indices):
        if baked <= frame:
            k = index
    following = (k + 1) % count
    start, end = indices[k], indices[following]
    span = end - start if following > k else end + frame_count - start
    offset = frame - start if frame >= start else frame + frame_count - start
    return FrameWeights((k, following), offset / span if span > 0 else 0.0)


def cycle_frame(seconds: float, phase: float, frames_per_second: float, frame_count: int) -> int:
    """The cycle frame the mesh shows at time `seconds` (plus a character's phase): floor((t + phase)·fps) mod frames."""
    return int(np.floor((seconds + phase) * frames_per_second)) % int(frame_count)
