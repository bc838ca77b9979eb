"""One table of bake parameters (crowdbake.params.PARAMS): the REST request model, the `crowdbake bake`
options and BakeParams must agree on every name, default, bound and choice, because all three are
derived from it. Walks the table; a parameter added to one place only fails here."""
from __future__ import annotations

import argparse
import dataclasses

import pytest
from pydantic import ValidationError

from crowdbake.api.schemas import BakeParamsIn
from crowdbake.cli import build_parser
from crowdbake.errors import InputError
from crowdbake.params import PARAMS, BakeParams, params_from_args


def bake_parser() -> argparse.ArgumentParser:
    parser = build_parser()
    subparsers = next(action for action in parser._actions if isinstance(action, argparse._SubParsersAction))
    return subparsers.choices["bake"]


def bake_options() -> dict[str, argparse.Action]:
    return {action.dest: action for action in bake_parser()._actions}


REQUIRED = ["CHAR.glb", "--cloth", "c.pc2", "--cloth-mesh", "c.obj", "--name", "n", "--version", "1", "--out", "o"]


def parse(*extra: str) -> dict:
    return params_from_args(bake_parser().parse_args([*REQUIRED, *extra]))


def test_every_parameter_is_a_cli_option_a_rest_field_and_a_bakeparams_field():
    names = [spec.name for spec in PARAMS]
    assert names == [f.name for f in dataclasses.fields(BakeParams)]
    assert set(names) == set(BakeParamsIn.model_fields)
    assert set(names) <= set(bake_options())


def test_defaults_agree():
    """No option given: the CLI, the REST model and BakeParams give the same parameters."""
    rest = BakeParamsIn().model_dump()
    cli = parse()
    ours = BakeParams().to_dict()
    for spec in PARAMS:
        expected = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        assert rest[spec.name] == cli[spec.name] == ours[spec.name] == expected, spec.name


def test_choices_agree():
    options = bake_options()
    for spec in PARAMS:
        if spec.choices is None:
            continue
        assert list(options[spec.name].choices) == list(spec.choices), spec.name
        schema = BakeParamsIn.model_json_schema()["properties"][spec.name]
        enums = [schema.get("enum")] + [branch.get("enum") for branch in schema.get("anyOf", [])]  # optional: anyOf [enum, null]
        assert set(spec.choices) in [set(e) for e in enums if e], spec.name
        with pytest.raises(ValidationError):
            BakeParamsIn(**{spec.name: "not-a-choice"})


def _edges(spec):
    """(accepted, refused) values at the spec's bounds."""
    if spec.kind == "floats":
        return [[spec.minimum], [spec.maximum]], [[spec.minimum - 1], [spec.maximum + 1], [], [0.0] * (spec.max_items + 1)]
    step = 1 if spec.kind == "int" else 1e-6
    accepted, refused = [], []
    if spec.above_zero:
        accepted.append(step)
        refused.append(0)
    elif spec.minimum is not None:
        accepted.append(spec.minimum)
        refused.append(spec.minimum - step)
    if spec.maximum is not None:
        accepted.append(spec.maximum)
        refused.append(spec.maximum + (spec.multiple_of or step))
    if spec.multiple_of:
        refused.append(spec.minimum + spec.multiple_of // 2)
    return accepted, refused


def _cli_text(spec, value) -> str:
    return ",".join(str(v) for v in value) if spec.kind == "floats" else str(value)


# The other impostor parameters at their least while one is at its bound: the product of all four is
# capped (MAX_IMPOSTOR_TEXELS) below the product of their single bounds.
SMALL_IMPOSTOR = {"impostor_frames": 1, "azimuths": 1, "elevations_deg": [0.0], "tile_size": 4}


@pytest.mark.parametrize("spec", [spec for spec in PARAMS if spec.kind in ("int", "float", "floats")], ids=lambda spec: spec.name)
def test_bounds_agree(spec):
    """A value at a bound is accepted by all three; one step past it is refused by all three."""
    accepted, refused = _edges(spec)
    assert accepted and refused
    small = {name: value for name, value in SMALL_IMPOSTOR.items() if name != spec.name}
    for value in accepted:
        assert getattr(BakeParamsIn(**small, **{spec.name: value}), spec.name) == value
        BakeParams.from_dict({**small, spec.name: value})
        assert parse(spec.flag, _cli_text(spec, value))[spec.name] == value
    for value in refused:
        with pytest.raises(ValidationError):
            BakeParamsIn(**small, **{spec.name: value})
        with pytest.raises(InputError) as caught:
            BakeParams.from_dict({**small, spec.name: value})
        assert caught.value.field == spec.name
        if spec.kind != "floats" or value:
            with pytest.raises(InputError):
                BakeParams.from_dict(parse(spec.flag, _cli_text(spec, value)))


def test_flags_and_aliases_reach_the_same_parameter():
    """The submit command's older spellings (--impostor-frames, --tile-size) name the same parameters."""
    assert parse("--impostor-frames", "3")["impostor_frames"] == parse("--frames", "3")["impostor_frames"] == 3
    assert parse("--tile-size", "64")["tile_size"] == 64
    assert parse("--no-compress")["compress"] is False
    assert parse("--uv-format", "rgba16")["uv_format"] == "rgba16"


def test_lod_ratio_and_lod_triangles_exclude_each_other_everywhere():
    with pytest.raises(ValidationError):
        BakeParamsIn(lod_ratio=0.5, lod_triangles=100)
    with pytest.raises(InputError):
        BakeParams(lod_ratio=0.5, lod_triangles=100).validate()
    with pytest.raises(SystemExit):
        bake_parser().parse_args([*REQUIRED, "--lod-ratio", "0.5", "--lod-triangles", "100"])


def test_the_closing_choices_are_the_loop_closings_own():
    """The parameter table names the closings without importing numpy; it must list exactly the ones
    crowdbake.bake.loop_closing implements, with the same default."""
    from crowdbake.bake import loop_closing
    from crowdbake.params import CLOSE_METHODS, DEFAULT_CLOSE

    assert set(CLOSE_METHODS) == set(loop_closing.CLOSE_METHODS)
    assert DEFAULT_CLOSE == loop_closing.DEFAULT_CLOSE_METHOD == "crossfade"


def test_the_frame_choices_are_placements_own():
    """up and units name exactly the frames crowdbake.bake.placement converts."""
    from crowdbake.bake import placement
    from crowdbake.params import UNIT_CHOICES, UP_AXES

    assert UP_AXES == placement.UP_AXES
    assert set(UNIT_CHOICES) == set(placement.UNITS)


def test_animation_is_a_name_or_an_index_everywhere():
    """Digits on the command line are an index; REST takes an integer index or a string name."""
    assert parse()["animation"] is None  # not given: crowdbake.ingest.clip_choice picks
    assert parse("--animation", "2")["animation"] == 2
    assert parse("--animation", "Walk")["animation"] == "Walk"
    assert BakeParamsIn(animation="Walk").animation == "Walk"
    assert BakeParamsIn(animation=1).animation == 1
    for bad in (-1, ""):
        with pytest.raises(ValidationError):
            BakeParamsIn(animation=bad)
        with pytest.raises(InputError) as caught:
            BakeParams.from_dict({"animation": bad})
        assert caught.value.field == "animation"


def test_none_on_the_command_line_turns_off_a_budget_on_by_default():
    values = parse("--impostor-archetype-budget", "none", "--frame-motion", "None", "--impostor-budget", "12")
    assert values["impostor_archetype_mib"] is None and values["impostor_motion_texels"] is None
    assert values["impostor_budget_mib"] == 12.0
    assert BakeParams.from_dict(values).impostor_archetype_mib is None
    assert parse()["impostor_archetype_mib"] == 32.0
    with pytest.raises(SystemExit):
        parse("--impostor-archetype-budget", "lots")
