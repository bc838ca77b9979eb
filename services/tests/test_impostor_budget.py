"""crowdbake.bake.impostor_budget: the crop any azimuths need, and the counts that fit a memory budget."""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake.impostor_budget import (
    AZIMUTH_FLOOR, FRAME_FLOOR, FrameExtents, baked_motion, budget_document, bytes_per_texel, clip_bytes, crop_for, fit_budget,
    fit_budget_per_clip, frame_extents, frames_for_motion, map_formats,
)
from crowdbake.params import BakeParams
from crowdbake.bake.impostor_views import ortho_view, project
from crowdbake.bake.poses import impostor_frame_indices

ELEVATIONS = (0.0, 20.0, 40.0)


def walker(frames: int = 12) -> tuple[np.ndarray, np.ndarray, float]:
    """(F, V, 3) a tall, thin figure whose arm swings out over the cycle; its bounds centre and radius."""
    rng = np.random.default_rng(5)
    body = rng.uniform([-0.2, 0.0, -0.12], [0.2, 1.8, 0.12], (400, 3))
    positions = np.repeat(body[None], frames, axis=0)
    swing = 0.5 * np.sin(np.linspace(0, 2 * np.pi, frames, endpoint=False))
    positions[:, :20, 2] += swing[:, None]  # an arm forwards and back
    low, high = positions.reshape(-1, 3).min(axis=0), positions.reshape(-1, 3).max(axis=0)
    return positions, 0.5 * (low + high), 0.5 * float(np.linalg.norm(high - low))


@pytest.mark.parametrize("azimuths", [7, 16, 32])
def test_the_crop_holds_every_vertex_of_every_view_whatever_the_azimuths(azimuths):
    positions, center, radius = walker()
    extents = frame_extents(positions, center, ELEVATIONS)
    frames = impostor_frame_indices(len(positions), 5)
    x, y, width, height = crop_for(extents, frames, radius, 64)
    for k in frames:
        for elevation in ELEVATIONS:
            for a in range(azimuths):
                xy, _ = project(ortho_view(center, radius, 360.0 * a / azimuths + 3.0, elevation, 64), positions[k])
                assert xy[:, 0].min() >= x and xy[:, 0].max() <= x + width and xy[:, 1].min() >= y and xy[:, 1].max() <= y + height
    assert width < 64  # a tall, thin figure leaves the sides of its square tile empty


def test_the_crop_follows_the_frames_baked():
    positions, center, radius = walker()
    extents = frame_extents(positions, center, ELEVATIONS)
    # Frames 0 and 6: the arm at the body (sin 0 = 0, sin pi = 0); frame 3: swung a full 0.5 m out.
    still, swung = crop_for(extents, [0, 6], radius, 128), crop_for(extents, [0, 3, 6], radius, 128)
    assert still[2] < swung[2]


def test_the_budget_takes_azimuths_first_then_frames_and_keeps_the_floors():
    positions, center, radius = walker()
    extents = frame_extents(positions, center, ELEVATIONS)
    per_texel = bytes_per_texel(map_formats(True, "uvblock", False))
    assert per_texel == 3.5  # BC5 1 + uvblock 1.5 + BC2 1 (depth, motion and coverage)
    asked = fit_budget(extents, radius, 128, 32, 3, 10, len(positions), per_texel, None)
    assert (asked.azimuths, asked.frames, asked.fits) == (32, 10, True) and len(asked.steps) == 1
    assert asked.bytes == clip_bytes(32, 3, 10, asked.crop, per_texel)
    # Room for 20 azimuths at 10 frames: azimuths alone fall.
    room = clip_bytes(20, 3, 10, asked.crop, per_texel)
    chosen = fit_budget(extents, radius, 128, 32, 3, 10, len(positions), per_texel, room)
    assert (chosen.azimuths, chosen.frames, chosen.fits) == (20, 10, True) and chosen.bytes <= room
    assert [step[0] for step in chosen.steps] == [32, 28, 24, 20]
    # Less than 16 azimuths at 10 frames: frames fall too, to the floor, and then it does not fit.
    tight = fit_budget(extents, radius, 128, 32, 3, 10, len(positions), per_texel, 1000)
    assert (tight.azimuths, tight.frames, tight.fits) == (AZIMUTH_FLOOR, FRAME_FLOOR, False)
    # Counts asked below the floors are kept.
    few = fit_budget(extents, radius, 128, 8, 3, 4, len(positions), per_texel, 1000)
    assert (few.azimuths, few.frames) == (8, 4)


def test_detail_maps_and_formats_count_in_the_bytes():
    assert bytes_per_texel(map_formats(True, "uvblock", True)) == 4.5
    assert bytes_per_texel(map_formats(False, "uv32", False)) == 4 + 4 + 4


def swinger(frames: int, amplitude: float) -> np.ndarray:
    """(F, 100, 3) a still body and a hem point swinging `amplitude` metres sideways round the cycle."""
    positions = np.zeros((frames, 100, 3))
    positions[:, :, 1] = np.linspace(0.0, 1.8, 100)
    positions[:, 90:, 0] = amplitude * np.sin(2 * np.pi * np.arange(frames) / frames)[:, None]  # 10 % of the vertices swing
    return positions


def test_the_motion_between_baked_frames_is_the_swing_of_the_fastest_pair():
    positions = swinger(24, 1.0)
    # 4 frames: 0, 6, 12, 18, a quarter turn apart; the swinging tenth moves sin 90° = 1 m each step (and back).
    assert baked_motion(positions, [0, 6, 12, 18]) == pytest.approx(1.0)
    # A 95th percentile: the swinging tenth of the vertices sets it; 4 % of them would not.
    few = positions.copy()
    few[:, :96, 0] = 0.0
    assert baked_motion(few, [0, 6, 12, 18]) == 0.0
    assert baked_motion(positions, [0]) == 0.0


@pytest.mark.parametrize("amplitude, texels, expected", [(0.05, 10.0, 6), (1.0, None, 20)])
def test_frames_follow_the_motion_and_keep_the_bounds(amplitude, texels, expected):
    # Little motion: the floor; no limit (None): the frames asked.
    assert frames_for_motion(swinger(48, amplitude), 100.0, texels, 20) == expected


def test_more_motion_or_finer_texels_need_more_frames_up_to_the_most():
    positions = swinger(48, 0.3)
    counts = [frames_for_motion(positions, 100.0, limit, 48) for limit in (20.0, 10.0, 5.0)]
    assert counts == sorted(counts) and counts[0] < counts[-1]
    # Each count is the fewest whose baked frames keep the motion within the limit.
    for limit, count in zip((20.0, 10.0, 5.0), counts):
        assert baked_motion(positions, impostor_frame_indices(48, count)) * 100.0 <= limit
        if count > FRAME_FLOOR:
            assert baked_motion(positions, impostor_frame_indices(48, count - 1)) * 100.0 > limit
    # Texels are the tile's: finer tiles (more texels a metre) need more frames.
    assert frames_for_motion(positions, 200.0, 10.0, 48) >= counts[1]
    # Never more than asked, nor more than the cycle has.
    assert frames_for_motion(positions, 100.0, 0.001, 30) == 30 and frames_for_motion(positions[:12], 100.0, 0.001, 30) == 12


def test_per_clip_frames_and_the_budget_account_of_the_motion():
    reach = np.full(24, 0.3)
    extents = FrameExtents(reach, np.full((24, 1), -0.9), np.full((24, 1), 0.9))
    choices = fit_budget_per_clip(extents, 1.0, 64, 16, 1, [10, 4], [(0, 12), (12, 12)], 1.5, None)
    assert [c.frames for c in choices] == [10, 4] and {c.azimuths for c in choices} == {16}
    with pytest.raises(ValueError, match="3 frame counts for 2 clips"):
        fit_budget_per_clip(extents, 1.0, 64, 16, 1, [10, 4, 2], [(0, 12), (12, 12)], 1.5, None)
    document = budget_document(choices[1], BakeParams())
    assert document["motion"] == {"max_texels": BakeParams().impostor_motion_texels, "frames": 4}
    assert document["asked"]["frames"] == BakeParams().impostor_frames and "texels" in document["rule"]
