"""A garment simulated on another character is refused before it is baked.

CesiumMan's long skirt (../shared/assets/long_skirt) on RiggedFigure baked with one log warning: both
figures are about 1.45 m tall and walk in place, so the first-frame placement check (up axis, units,
overlap) passed, and the skirts hung crumpled and off-centre in the crowd because the skirt follows
legs that RiggedFigure does not swing the same way. The validate stage now poses the character at
each frame's time and measures how much of the cloth hangs far from its body over the whole cache
(crowdbake.bake.garment_fit); the real pairs pass, the mismatched one is refused with the figure and
the flag that bakes it anyway.
"""
from __future__ import annotations

import logging

import numpy as np
import pytest

from crowdbake.bake.garment_fit import FAR_FROM_BODY, MAX_FAR_FRACTION, measure_garment_fit
from crowdbake.errors import InputError
from crowdbake.formats.gltf import load_character
from crowdbake.ingest.garment import check_garment_fit, read_cloth
from crowdbake.params import BakeParams
from crowdbake.stages.validate import BakeInputs, stage_validate
from repo_paths import SHARED_ASSETS

SKIRT = SHARED_ASSETS / "long_skirt"
needs_assets = pytest.mark.skipif(not (SKIRT / "long_skirt.pc2").exists() or not (SHARED_ASSETS / "RiggedFigure.glb").exists(),
                                  reason=f"the shared assets (long_skirt/, CesiumMan.glb, RiggedFigure.glb) are not in {SHARED_ASSETS}")
logger = logging.getLogger(__name__)


def _fit(character_file, cache):
    return check_garment_fit(load_character(character_file), cache, cache.fps or 24.0)


def test_a_cloth_that_stays_on_its_body_is_measured_as_fitting_and_one_beside_it_is_not():
    """Known by construction: a box body 1 m tall; cloth points on its surface fit, the same points
    moved 0.5 m (half its height, beyond FAR_FROM_BODY) sideways in every frame do not."""
    corners = np.array([[x, y, z] for x in (0, 0.2) for y in (0, 1) for z in (0, 0.2)], np.float64)
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    body = np.repeat(corners[None], 4, axis=0)
    cloth = np.repeat(np.array([[0.1, 0.5, 0.0], [0.2, 0.3, 0.1], [0.0, 0.8, 0.1]])[None], 4, axis=0)
    assert measure_garment_fit(cloth, body, faces).far_fraction == 0.0
    away = measure_garment_fit(cloth + [0.5 + 0.2, 0, 0], body, faces)
    assert away.far_fraction == 1.0 and not away.ok and away.height == pytest.approx(1.0)


@needs_assets
def test_cesium_mans_own_long_skirt_fits_him():
    fit = _fit(SHARED_ASSETS / "CesiumMan.glb", read_cloth(SKIRT / "long_skirt.pc2", SKIRT / "long_skirt.obj"))
    logger.warning("CesiumMan + long_skirt: far_fraction %.3f (worst frame %d: %.3f)", fit.far_fraction, fit.worst_frame, fit.worst_far_fraction)
    assert fit.ok and fit.far_fraction < MAX_FAR_FRACTION * 0.75


def test_the_samples_garment_fits_its_character(small_sample):
    fit = _fit(small_sample / "character.glb", read_cloth(small_sample / "cloth.pc2", small_sample / "cloth.obj"))
    logger.warning("sample: far_fraction %.3f", fit.far_fraction)
    assert fit.ok and fit.far_fraction < MAX_FAR_FRACTION / 3


@needs_assets
def test_cesium_mans_skirt_on_rigged_figure_is_refused_naming_how_far_off_and_the_override(tmp_path):
    inputs = dict(character=SHARED_ASSETS / "RiggedFigure.glb", cloth=SKIRT / "long_skirt.pc2", cloth_mesh=SKIRT / "long_skirt.obj",
                  textures=None, cycle=None, name="figure", version="1.0")
    with pytest.raises(InputError) as caught:
        stage_validate(BakeInputs(**inputs, params=BakeParams()), tmp_path / "work")
    message = caught.value.message
    logger.warning("RiggedFigure + long_skirt: %s", message)
    assert caught.value.field == "cloth"
    assert "does not fit the character" in message and f"{FAR_FROM_BODY:.0%} of its" in message
    assert "--no-fit" in message and "params.fit = false" in message
    share = float(message.split("over the cache ")[1].split("%")[0]) / 100
    assert share > MAX_FAR_FRACTION
    # The override bakes it anyway: validation goes past the check.
    record = stage_validate(BakeInputs(**inputs, params=BakeParams(fit=False)), tmp_path / "work2").record
    assert record.garment_vertices == 4032 and record.params["fit"] is False



@needs_assets
def test_a_misfit_on_a_character_of_several_clips_names_the_timeline_first():
    """A cache simulated across several clips and baked without its timeline poses the body with one clip
    over all of it, and the cloth does not follow: the refusal said only "does not fit", which sent users
    to re-simulate. On a character of several animations it now names the timeline first. (RiggedFigure
    under CesiumMan's skirt is a known misfit; its one walk is given two names, as a clip file has.)"""
    import dataclasses

    figure = dataclasses.replace(load_character(SHARED_ASSETS / "RiggedFigure.glb"), animation_names=["Idle", "Walk"])
    cache = read_cloth(SKIRT / "long_skirt.pc2", SKIRT / "long_skirt.obj")
    with pytest.raises(InputError) as caught:
        check_garment_fit(figure, cache, cache.fps or 24.0)
    message = caught.value.message
    assert "does not fit the character" in message and "2 animations ('Idle', 'Walk')" in message
    assert message.index("give its timeline (--timeline") < message.index("--no-fit")
    # One animation: no timeline to give, so none is named.
    with pytest.raises(InputError) as single:
        _fit(SHARED_ASSETS / "RiggedFigure.glb", cache)
    assert "timeline" not in single.value.message


@needs_assets
def test_crowdbake_cycle_refuses_the_misfit_in_one_line_unless_told_not_to_check(tmp_path, capsys):
    """`crowdbake cycle` searched CesiumMan's skirt on RiggedFigure without a word, while `crowdbake bake`
    refused it: the cycle command checks the fit too, with the same --no-fit."""
    from crowdbake.cli import main

    args = ["cycle", str(SKIRT / "long_skirt.pc2"), "--mesh", str(SKIRT / "long_skirt.obj"), "--character", str(SHARED_ASSETS / "RiggedFigure.glb"),
            "--no-edge-pass", "--out", str(tmp_path / "out")]
    assert main(args) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("crowdbake cycle: error: the garment does not fit the character") and "--no-fit" in lines[0]
    assert not (tmp_path / "out" / "cycle.json").exists()
    assert main([*args, "--no-fit"]) == 0
    assert (tmp_path / "out" / "cycle.json").is_file()
