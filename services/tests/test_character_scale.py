"""A character whose root node scales it to an implausible height is refused as a character.

A Mixamo-style export whose root node scaled it to 0.215 m tall was accepted, and only its garment was
refused, with a message blaming the garment ("the cloth cache looks like inches"). The sample's
character is wrapped here in a root node with a scale, as such exports are, and must be refused at
validation (the bake's validate stage and the REST upload check), naming the node's scale and saying
that no parameter scales a character.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from crowdbake.errors import InputError
from crowdbake.formats.gltf import load_character, parse_glb
from crowdbake.formats.gltf.document import CHUNK_BIN, CHUNK_JSON
from crowdbake.ingest.garment import CHARACTER_HEIGHT_RANGE_M, body_at_rest
from crowdbake.ingest.uploads import UploadRejected, check_character
from crowdbake.params import BakeParams
from crowdbake.stages.validate import BakeInputs, stage_validate

MIXAMO_HEIGHT_M = 0.215  # the export


def root_scaled(source: Path, out: Path, height_m: float) -> Path:
    """`source` GLB with its scene's nodes under a new root node 'Armature' scaling it to `height_m` tall."""
    document, binary = parse_glb(source.read_bytes(), str(source))
    height = float(np.ptp(body_at_rest(load_character(source))[:, 1]))
    scene = document["scenes"][document.get("scene", 0)]
    document["nodes"].append({"name": "Armature", "scale": [height_m / height] * 3, "children": scene["nodes"]})
    scene["nodes"] = [len(document["nodes"]) - 1]
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<II", len(text), CHUNK_JSON) + text + struct.pack("<II", len(binary), CHUNK_BIN) + binary
    out.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks)
    return out


def test_the_bake_refuses_a_character_scaled_to_a_toy_and_says_why(small_sample, tmp_path):
    character = root_scaled(small_sample / "character.glb", tmp_path / "mixamo.glb", MIXAMO_HEIGHT_M)
    inputs = BakeInputs(character=character, cloth=small_sample / "cloth.pc2", cloth_mesh=small_sample / "cloth.obj",
                        textures=small_sample / "textures", cycle=None, name="sample", version="1.0", params=BakeParams())
    with pytest.raises(InputError) as caught:
        stage_validate(inputs, tmp_path / "work")
    message = caught.value.message
    assert caught.value.field == "character", message
    assert "0.215 m tall" in message and "root joint 'hips' scales it by 0.126" in message, message
    assert "no parameter scales the character" in message and "cloth cache looks like" not in message, message


def test_the_upload_check_refuses_it_too(small_sample, tmp_path):
    character = root_scaled(small_sample / "character.glb", tmp_path / "mixamo.glb", MIXAMO_HEIGHT_M)
    with pytest.raises(UploadRejected) as caught:
        check_character(character, "mixamo.glb")
    assert "0.215 m tall" in caught.value.detail and caught.value.errors[0].field == "file", caught.value.detail


@pytest.mark.parametrize("height_m", [0.35, 1.75, 8.0])
def test_robots_and_mechs_within_the_range_pass(small_sample, tmp_path, height_m):
    """The range is wider than a human's 0.5-3 m: a 0.35 m robot and an 8 m mech are characters too."""
    low, high = CHARACTER_HEIGHT_RANGE_M
    assert low <= height_m <= high
    body = body_at_rest(load_character(root_scaled(small_sample / "character.glb", tmp_path / "c.glb", height_m)))
    assert float(np.ptp(body[:, 1])) == pytest.approx(height_m, rel=1e-3)
