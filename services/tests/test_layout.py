"""The codebase's layout rules: modules small enough to read whole, and one bake request for CLI and REST.

* No Python module under services/crowdbake is over MAX_MODULE_LINES lines: a module that grows past it
  is split by job (as formats/gltf/ and bake/loop_closing.py were), so a newcomer finds things by name.
* Every `crowdbake bake` option that shapes the bundle is a field of the REST bake request (BakeCreate or
  its params), so a bundle baked on the command line can be baked by the service too. Options that do
  not shape the bundle are listed below with the reason.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import crowdbake
from crowdbake.api.schemas import BakeCreate, BakeParamsIn
from crowdbake.cli import build_parser

PACKAGE = Path(crowdbake.__file__).resolve().parent
MAX_MODULE_LINES = 600

# `crowdbake bake` options that decide where things go or how they are shown, not the bundle's bytes.
NOT_BUNDLE_SHAPING = {
    "out": "where the bundle is written (the service publishes it instead)",
    "work": "where intermediate files are kept; a rerun resumes from them and writes the same bytes",
    "figure4": "an extra plot beside the bundle, not in it",
    "json": "how the summary is printed",
}
# Options whose REST field has another name: the cloth asset is uploaded as its cache and mesh together.
REST_NAMES = {"bundle_version": "version", "cloth_mesh": "cloth"}
# Options that shape the bundle but have no REST field yet, with the reason (each is a known gap).
NOT_YET_REST: dict[str, str] = {}


def test_no_module_is_over_the_line_limit():
    lengths = {path.relative_to(PACKAGE).as_posix(): len(path.read_text(encoding="utf-8").splitlines())
               for path in sorted(PACKAGE.rglob("*.py"))}
    assert len(lengths) > 50  # the walk found the package, not an empty folder
    too_long = {name: lines for name, lines in lengths.items() if lines > MAX_MODULE_LINES}
    assert not too_long, f"modules over {MAX_MODULE_LINES} lines (split them by job): {too_long}"


def _bake_options() -> dict[str, str]:
    """dest -> the option's first flag (or metavar), for every option of `crowdbake bake` but --help."""
    parser = build_parser()
    commands = next(action for action in parser._actions if isinstance(action, argparse._SubParsersAction))
    bake = commands.choices["bake"]
    return {action.dest: (action.option_strings or [action.metavar or action.dest])[0]
            for action in bake._actions if not isinstance(action, argparse._HelpAction)}


def test_every_bake_option_that_shapes_the_bundle_is_a_rest_field():
    options = _bake_options()
    rest_fields = set(BakeCreate.model_fields) | set(BakeParamsIn.model_fields)
    missing = {
        flag for dest, flag in options.items()
        if dest not in NOT_BUNDLE_SHAPING and dest not in NOT_YET_REST and REST_NAMES.get(dest, dest) not in rest_fields
    }
    assert not missing, f"`crowdbake bake` options with no REST bake field: {sorted(missing)}"
    # The lists above name real options, so they cannot hide a renamed or removed one.
    stale = (set(NOT_BUNDLE_SHAPING) | set(REST_NAMES) | set(NOT_YET_REST)) - set(options)
    assert not stale, f"exceptions that are no longer options of `crowdbake bake`: {sorted(stale)}"
    assert {"created", "name", "character", "tile_size"} <= set(options)  # the walk saw the table's options too


def test_the_gaps_are_still_gaps():
    """When a REST field for a NOT_YET_REST option appears, it leaves that list."""
    rest_fields = set(BakeCreate.model_fields) | set(BakeParamsIn.model_fields)
    assert not set(NOT_YET_REST) & rest_fields
