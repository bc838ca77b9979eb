"""The --help of `crowdbake bake` and of the CI client (`crowdbake-submit`) is generated from the one
parameter table (crowdbake.params.PARAMS). Two bugs a new user met there:

- `--no-compress  block-compress normal maps … false: rgba8` described the parameter, which the flag
  turns *off*: the help of a `--no-X` flag must say what giving it does;
- "(default: the character's animation) (default the server's)": the table's help carried its own default
  and the CLI appended another, so a line said "default" twice.

The help is read as a user reads it: the real command's output, wrapped at 80 columns, one entry per option."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from crowdbake.params import PARAMS

COMMANDS = {
    "crowdbake bake": [sys.executable, "-m", "crowdbake", "bake", "--help"],
    "crowdbake-submit": [sys.executable, "-m", "crowdbake.client.submit", "--help"],
}


def help_entries(command: list[str]) -> dict[str, str]:
    """Option flags (as printed, e.g. "--frames N, --impostor-frames N") -> the option's help, its wrapped
    lines joined, from the command's --help at 80 columns."""
    output = subprocess.run(command, env={**os.environ, "COLUMNS": "80"}, capture_output=True, text=True, check=True).stdout
    entries: dict[str, list[str]] = {}
    current = None
    for line in output.splitlines():
        start = re.match(r"^  (-\S.*?)(?:\s{2,}(.*))?$", line)
        if start:
            current = start.group(1)
            entries[current] = [start.group(2) or ""]
        elif current is not None and line.startswith(" " * 8) and line.strip():
            entries[current].append(line.strip())
        else:
            current = None  # a blank line or a group heading ends the entry
    return {flags: " ".join(part for part in parts if part) for flags, parts in entries.items()}


@pytest.fixture(scope="module", params=sorted(COMMANDS))
def entries(request) -> dict[str, str]:
    return help_entries(COMMANDS[request.param])


def test_every_no_flag_says_it_turns_its_thing_off(entries):
    no_flags = {flags: text for flags, text in entries.items() if flags.startswith("--no-")}
    assert {"--no-compress", "--no-export"} <= set(no_flags)  # both commands carry the table's flags
    for flags, text in no_flags.items():
        thing = flags.split()[0].removeprefix("--no-")
        assert text.startswith("do not "), f"{flags}: {text!r} does not say what giving the flag turns off"
        assert thing in text.split(":")[0], f"{flags}: {text!r} does not name what it turns off ({thing})"
        assert "false:" not in text, f"{flags}: {text!r} describes the parameter's values, not the flag"


def test_no_option_says_default_twice(entries):
    assert entries, "no options parsed from --help"
    for flags, text in entries.items():
        assert len(re.findall(r"\bdefault\b", text, re.IGNORECASE)) <= 1, f"{flags}: {text!r}"


def test_every_valued_parameter_shows_its_default_once(entries):
    """The table's default (or what a derived default is) appears in the option's help."""
    by_flag = {flags.split()[0].rstrip(","): text for flags, text in entries.items()}
    for spec in PARAMS:
        if spec.kind == "bool":
            continue
        text = by_flag[spec.flag]
        assert "default" in text.lower(), f"{spec.flag}: {text!r}"
        expected = spec.derived if spec.default is None else (
            ",".join(f"{v:g}" for v in spec.default) if spec.kind == "floats" else str(spec.default))
        assert expected in text, f"{spec.flag}: {text!r} lacks the default {expected!r}"


def test_bool_parameters_have_help_for_their_flag():
    """A default-on parameter has a --no-X flag, a default-off one an --x flag; either says what giving it does."""
    for spec in PARAMS:
        if spec.kind == "bool":
            flag = f"--no-{spec.name}" if spec.default else f"--{spec.name.replace('_', '-')}"
            assert spec.flag == flag and spec.off_help, spec.name
