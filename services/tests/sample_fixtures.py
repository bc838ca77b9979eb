"""The procedural sample, generated once per test session and shared by every module that bakes it.

Simulating the sample's cloth takes most of a small bake's time; a module that needs a sample takes the
`small_sample` fixture instead of generating its own. Tests must treat the folder as read-only (copy it
to change it). services/tests/conftest.py and tests/conftest.py both import the fixture from here.
"""
from __future__ import annotations

from pathlib import Path

import pytest

# 3 walk cycles of 24 frames (two cycles for the search, one to settle), 64² textures: seconds to bake.
SMALL_SAMPLE = dict(garment="loose", cycles=3, seed=1, cycle_frames=24, texture_size=64)


@pytest.fixture(scope="session")
def small_sample(tmp_path_factory) -> Path:
    """A folder with the sample (crowdbake.sample.generate, SMALL_SAMPLE): character.glb, cloth.pc2,
    cloth.obj, textures/ (8 diffuse variations and outfits.png)."""
    from crowdbake.sample.generate import generate_sample

    folder = tmp_path_factory.mktemp("small_sample")
    generate_sample(folder, **SMALL_SAMPLE)
    return folder


@pytest.fixture(scope="session")
def small_bake(small_sample, tmp_path_factory) -> tuple[Path, Path]:
    """(bundle folder, work folder) of the small sample baked with SMALL_BAKE_PARAMS (no export): shared
    by the modules that read a bake's maps and pictures; read-only."""
    from crowdbake.stages.runner import run_bake
    from crowdbake.stages.validate import BakeInputs

    root = tmp_path_factory.mktemp("small_bake")
    summary = run_bake(BakeInputs(character=small_sample / "character.glb", cloth=small_sample / "cloth.pc2",
                                  cloth_mesh=small_sample / "cloth.obj", textures=small_sample / "textures", cycle=None,
                                  name="sample", version="1.0", params=small_bake_params()), root / "bundles", work=root / "work")
    return summary.bundle, root / "work"


def small_bake_params():
    """Eight azimuths, two rings, two baked frames of 64² texels: every kind of impostor blend, in seconds."""
    from crowdbake.params import BakeParams

    return BakeParams(impostor_frames=2, azimuths=8, elevations_deg=(0.0, 30.0), tile_size=64, lod_triangles=1200, cycle_views=3,
                      candidates=3, export=False)
