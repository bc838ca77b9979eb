"""A glTF with two skins over one skeleton bakes every mesh.

RobotExpressive (../shared/assets/robot_clips/robot.glb) binds its left hand with a second skin whose
joints are the first skin's. The reader took skins[0] only and left the hand out with a warning, so the
crowd's robots had one hand. A second skin whose joints are all joints of the chosen skin is now read
into the same mesh (its joint indices remapped, its bind pose checked to agree).
"""
from __future__ import annotations

import logging

import numpy as np
import pygltflib
import pytest

from crowdbake.bake.skinning import pose_character
from crowdbake.formats.gltf import load_character
from repo_paths import SHARED_ASSETS

ROBOT = SHARED_ASSETS / "robot_clips" / "robot.glb"
needs_robot = pytest.mark.skipif(not ROBOT.exists(), reason=f"the shared robot (robot_clips/robot.glb) is not in {SHARED_ASSETS}")


def _vertex_count(document: pygltflib.GLTF2, mesh: int) -> int:
    return sum(document.accessors[p.attributes.POSITION].count for p in document.meshes[mesh].primitives)


@needs_robot
def test_the_robots_left_hand_of_the_second_skin_is_kept_and_follows_its_arm(caplog):
    document = pygltflib.GLTF2().load(str(ROBOT))
    left, right = (next(n.mesh for n in document.nodes if n.name == name) for name in ("Hand.L", "Hand.R"))
    with caplog.at_level(logging.WARNING):
        character = load_character(ROBOT, animation="Idle")
    assert not [r for r in caplog.records if "left out" in r.getMessage()]
    left_count, right_count = _vertex_count(document, left), _vertex_count(document, right)
    # The hands are the last two meshes in node order: Hand.R (skins[0]) then Hand.L (skins[1]).
    posed = pose_character(character, 24.0, 1)[0][0]
    left_hand = posed[-left_count:]
    right_hand = posed[-left_count - right_count:-left_count]
    # Idle stands symmetric: the left hand is the right one mirrored in x, at its height, beside the body.
    assert np.mean(left_hand[:, 0]) == pytest.approx(-np.mean(right_hand[:, 0]), abs=0.15)
    assert np.mean(left_hand[:, 1]) == pytest.approx(np.mean(right_hand[:, 1]), abs=0.15)
    assert abs(np.mean(left_hand[:, 0])) > 0.5
