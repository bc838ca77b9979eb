"""The default closing and pass 2 on a real simulator's cache: Blender's long skirt on CesiumMan.

The cache is chaotic like real loose cloth (frames a cycle apart differ by 60-150 mm RMS) and its faces are
wound inward: the case the Hermite closing (stretch 9x the simulation's) and one-sided pass-2 lighting
got wrong. Skipped when the shared assets are absent.
"""
from __future__ import annotations

import numpy as np
import pytest

from crowdbake.bake import loop_closing
from crowdbake.bake.cycle import CycleParams, find_cycle


@pytest.fixture(scope="module")
def long_skirt(shared_asset):
    from crowdbake.stages.cycle_inputs import load_cycle_inputs

    return load_cycle_inputs(
        shared_asset("long_skirt/long_skirt.pc2"), shared_asset("long_skirt/long_skirt.obj"), character=shared_asset("CesiumMan.glb")
    )


@pytest.fixture(scope="module")
def searched(long_skirt):
    """Pass 1 + pass 2 (OSMesa pictures) with the default closing, as cut and with its winding reversed."""
    from crowdbake.render.cloth_views import ClothViewRenderer

    def run(faces):
        return find_cycle(
            long_skirt.cloth, faces, long_skirt.body, long_skirt.body_faces, long_skirt.cycle_frames, CycleParams(),
            ClothViewRenderer(faces, long_skirt.body_faces), body_normals=long_skirt.body_normals,
        )

    return run(long_skirt.cloth_faces), run(long_skirt.cloth_faces[:, ::-1])


def test_the_default_closing_stays_near_the_simulation(searched):
    result, _ = searched
    assert result.closing.method == loop_closing.DEFAULT_CLOSE_METHOD
    quality = result.closing.quality
    assert quality.within_bounds, quality
    assert quality.stretch_ratio <= 1.10 and quality.deviation_ratio <= 1.5 and quality.seam_acceleration_ratio <= 1.5
    assert result.to_dict()["closing"]["quality"]["within_bounds"] is True


def test_hermite_on_the_same_cycle_is_flagged(long_skirt, searched):
    result, _ = searched
    hermite = loop_closing.close_cycle(
        long_skirt.cloth, result.start_frame, result.cycle_frames, "hermite", cloth_faces=long_skirt.cloth_faces
    )
    assert "stretch_ratio" in hermite.quality.exceeded


def test_pass_2_picks_a_start_near_the_best_and_ignores_the_winding(searched):
    result, flipped = searched
    best = min(c.vertex_distance for c in result.candidates)
    chosen = result.candidates[result.chosen].vertex_distance
    assert chosen <= 2.0 * best
    chosen_flipped = flipped.candidates[flipped.chosen].vertex_distance
    assert flipped.start_frame == result.start_frame or abs(chosen_flipped - chosen) <= 0.1 * chosen
    np.testing.assert_allclose(
        [c.edge_distance for c in flipped.candidates], [c.edge_distance for c in result.candidates], rtol=0.02
    )
