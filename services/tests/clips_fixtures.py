"""The procedural sample's clips (Idle, Walking, Running simulated in one run, with its timeline), generated
and baked with `crowdbake bake --timeline` once per test session, shared by the modules that read them
(the sample's own checks, the service's fan-out of the clips' loops). Tests must treat the folders as
read-only (copy them to change them).
"""
from __future__ import annotations

import pytest

from crowdbake.sample.clips import DEFAULT_SEQUENCE

WALK_FRAMES = 16
# Tight skirt on the heavy build, a walk of 16 frames, a coarse 8 x 36 cloth: seconds to simulate.
SMALL_CLIPS = dict(garment="tight", seed=1, cycle_frames=WALK_FRAMES, texture_size=64, clips=DEFAULT_SEQUENCE, cloth_rows=8,
                   cloth_columns=36, build="heavy")
# What a small bake needs (as sample_fixtures.small_bake_params): seconds, not minutes. CLIPS_BAKE_PARAMS is
# the same as a REST bake's params; CLIPS_NAME and CLIPS_VERSION name the bundle.
SMALL_BAKE = ["--impostor-frames", "2", "--azimuths", "8", "--elevations", "0,30", "--tile-size", "64", "--lod-triangles", "1200",
              "--cycle-views", "3", "--candidates", "3", "--no-export"]
CLIPS_BAKE_PARAMS = {"impostor_frames": 2, "azimuths": 8, "elevations_deg": [0, 30], "tile_size": 64, "lod_triangles": 1200,
                     "cycle_views": 3, "candidates": 3, "export": False}
CLIPS_NAME, CLIPS_VERSION = "sample-clips", "1"


@pytest.fixture(scope="session")
def clips_sample(tmp_path_factory):
    from crowdbake.sample.generate import generate_sample

    folder = tmp_path_factory.mktemp("clips_sample")
    generate_sample(folder, **SMALL_CLIPS)
    return folder


@pytest.fixture(scope="session")
def clips_bake(clips_sample, tmp_path_factory):
    """(exit code, bundle folder) of `crowdbake bake --timeline` on the clips sample."""
    from crowdbake.cli import main

    out = tmp_path_factory.mktemp("clips_bake")
    s = clips_sample
    code = main(["bake", str(s / "character.glb"), "--cloth", str(s / "cloth.pc2"), "--cloth-mesh", str(s / "cloth.obj"),
                 "--textures", str(s / "textures"), "--timeline", str(s / "timeline.json"), "--name", CLIPS_NAME,
                 "--version", CLIPS_VERSION, "--out", str(out), *SMALL_BAKE])
    return code, out / CLIPS_NAME / CLIPS_VERSION
