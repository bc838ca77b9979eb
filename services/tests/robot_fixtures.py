"""The robot of robot_clips (Blender's cape across Idle -> Walking -> Running -> Walking) baked once per test
session to a format-v2 bundle, shared by every module that reads it (the bake's own checks, the export).

Small settings: one ring of 4 views, 32-texel tiles, 2 frames a clip, no detail map, no export. Tests must
treat the folders as read-only (copy them to change them).
"""
from __future__ import annotations

from pathlib import Path

import pytest

from repo_paths import SHARED_ASSETS

ROBOT = SHARED_ASSETS / "robot_clips"


@pytest.fixture(scope="session")
def robot_bake(tmp_path_factory) -> tuple[Path, Path]:
    """(bundle folder, work folder) of the robot baked once for the session; skips without ../shared."""
    from crowdbake.stages.runner import run_bake

    root = tmp_path_factory.mktemp("robot_clips")
    run_bake(robot_inputs(), root / "bundles", work=root / "work")
    return root / "bundles" / "robot" / "1", root / "work"


def robot_inputs():
    """The robot_bake fixture's inputs (small settings); skips without ../shared."""
    from crowdbake.params import BakeParams
    from crowdbake.stages.validate import BakeInputs

    names = ("robot.glb", "garment.pc2", "garment.obj", "timeline.json")
    missing = [name for name in names if not (ROBOT / name).is_file()]
    if missing:
        pytest.skip(f"third-party asset robot_clips/{missing[0]} not found under {SHARED_ASSETS} (set CROWDBAKE_SHARED_ASSETS)")
    params = BakeParams(impostor_frames=2, azimuths=4, elevations_deg=(0.0,), tile_size=32, lod_triangles=1200, cycle_views=3,
                        candidates=3, export=False)
    return BakeInputs(character=ROBOT / "robot.glb", cloth=ROBOT / "garment.pc2", cloth_mesh=ROBOT / "garment.obj", textures=None,
                      cycle=None, name="robot", version="1", params=params, timeline=ROBOT / "timeline.json")
