"""The crowd description's JSON Schema (shared_formats/crowd.schema.json) against the shared vectors
(shared_formats/vectors/crowd-v1), which crowdview's parser reads too (runtime/tests/test_crowd_file.cpp):
the good files validate, each bad one is refused, and the runtime README's example is a valid description."""
from __future__ import annotations

import json
import re
from pathlib import Path

import jsonschema
import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared_formats"
VECTORS = SHARED / "vectors" / "crowd-v1"
README = Path(__file__).resolve().parents[2] / "runtime" / "README.md"


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft202012Validator:
    schema = json.loads((SHARED / "crowd.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


@pytest.mark.parametrize("path", sorted(VECTORS.glob("good/*.json")), ids=lambda p: p.stem)
def test_good_vectors_validate(validator, path):
    validator.validate(json.loads(path.read_text()))


def test_bad_vectors_are_refused(validator):
    expected = json.loads((VECTORS / "bad" / "expect.json").read_text())
    assert len(expected) >= 8
    for name in expected:
        errors = list(validator.iter_errors(json.loads((VECTORS / "bad" / f"{name}.json").read_text())))
        assert errors, f"{name}.json passes the schema"


def test_readme_example_is_a_valid_description(validator):
    section = README.read_text().split("## Crowds of several archetypes", 1)[1]
    example = re.search(r"```json\n(.*?)```", section, re.S).group(1)
    validator.validate(json.loads(example))
