"""The one description of a bake's inputs (crowdbake.ingest.input_modes): the five modes, the refusals
every boundary shares, and the shapes it writes (the bake record, the request body, the check's roles)."""
from __future__ import annotations

import pytest

from crowdbake.ingest.input_modes import BakeInputSet, InputConflict, InputMode


@pytest.mark.parametrize("inputs, cycle_frames, mode", [
    (BakeInputSet("char"), None, InputMode.BODY_ONLY),
    (BakeInputSet("char", cloth="cache"), 24, InputMode.CLOTH),
    (BakeInputSet("char", cloth="cache", cycle="cycle"), 24, InputMode.CYCLE),
    (BakeInputSet("char", cloth="cache", timeline="timeline"), None, InputMode.TIMELINE),
    (BakeInputSet("char", clip_cloth=[("Walk", "a"), ("Run", "b")]), None, InputMode.CLIP_CLOTH),
])
def test_each_set_of_inputs_has_its_mode(inputs, cycle_frames, mode):
    assert inputs.mode(cycle_frames) is mode


@pytest.mark.parametrize("inputs, cycle_frames, field, command_line", [
    (BakeInputSet("char", cloth="c", clip_cloth=[("Walk", "a")]), None, "cloth",
     "--clip-cloth: gives every clip its own cache (separate simulations): leave out --cloth"),
    (BakeInputSet("char", timeline="t", cycle="y", clip_cloth=[("Walk", "a")]), None, "timeline",
     "--clip-cloth: gives every clip its own cache (separate simulations): leave out --timeline"),
    (BakeInputSet("char", clip_cloth=[("Walk", "a")]), 24, "params.cycle_frames",
     "--clip-cloth: each clip's period is its animation's: drop --cycle-frames"),
    (BakeInputSet("char", timeline="t"), None, "cloth", "--timeline: a timeline says which clip plays at each frame of a cloth cache: give --cloth too"),
    (BakeInputSet("char", cloth="c", timeline="t", cycle="y"), None, "cycle",
     "--cycle: a cycle chooses one loop; --timeline asks for a loop per clip: give one of them"),
    (BakeInputSet("char", cloth="c", timeline="t"), 24, "params.cycle_frames", "--cycle-frames: the timeline gives each clip's period: drop cycle_frames"),
    (BakeInputSet("char", cycle="y"), 24, "cycle", "--cycle: a cycle chooses a loop of a cloth cache: give --cloth too"),
    (BakeInputSet("char"), 24, "params.cycle_frames", "--cycle-frames: without --cloth the cycle is the animation's own loop"),
])
def test_inputs_a_mode_does_not_take_are_refused_naming_the_field(inputs, cycle_frames, field, command_line):
    with pytest.raises(InputConflict) as refused:
        inputs.mode(cycle_frames)
    assert refused.value.field == field and refused.value.title and refused.value.message
    assert refused.value.command_line() == command_line


def test_textures_are_sorted_and_clips_keep_their_order():
    inputs = BakeInputSet("char", textures={"outfits.png": "o", "diffuse_b.png": "b", "diffuse_a.png": "a"},
                          clip_cloth=[("Run", "r"), ("Walk", "w")])
    assert [name for name, _ in inputs.textures] == ["diffuse_a.png", "diffuse_b.png", "outfits.png"]
    assert list(inputs.roles()) == ["character", "textures.diffuse_a.png", "textures.diffuse_b.png", "textures.outfits.png",
                                    "clip_cloth.0", "clip_cloth.1"]
    assert inputs.roles()["clip_cloth.0"] == "r"


def test_the_record_holds_only_the_inputs_given_and_reads_back():
    """A bake's record (and its input key's digests) names a role only when given, so the keys of bakes
    made before a role existed stay what they were."""
    body_only = BakeInputSet("char", textures={"diffuse_0.png": "d"})
    assert body_only.record() == {"character": "char", "textures": {"diffuse_0.png": "d"}}
    clips = BakeInputSet("char", clip_cloth=[("Walk", "a"), ("Run", "b")])
    assert clips.record() == {"character": "char", "textures": {}, "clip_cloth": [["Walk", "a"], ["Run", "b"]]}
    for inputs in (body_only, clips, BakeInputSet("char", cloth="c", cycle="y"), BakeInputSet("char", cloth="c", timeline="t")):
        assert BakeInputSet.from_record({**inputs.record(), "created": "2006-09-04T12:00:00Z"}) == inputs


def test_map_converts_every_input_in_one_order():
    inputs = BakeInputSet("char", cloth="c", cycle="y", textures={"diffuse_0.png": "d"})
    seen = []
    converted = inputs.map(lambda role, ref: seen.append(role) or ref.upper())
    assert seen == ["character", "cloth", "textures.diffuse_0.png", "cycle"]
    assert converted.request_fields() == {"character": "CHAR", "cloth": "C", "textures": {"diffuse_0.png": "D"}, "cycle": "Y"}
