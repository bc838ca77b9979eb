"""A bake whose loop breaks a quality bound fails in one line naming the clip, its cache frames, the
figure and its bound, unless the bake accepts it (accept_out_of_bounds), which the manifest records.

Such loops used to be published with a warning in the log: a bundle "verified" while its cycle.json said
`within_bounds: false`. The sample's loose skirt closed with hermite stretches its cloth past the bound
(docs/cycle.md): no candidate or width can help, as hermite spreads its correction over the whole loop.
"""
from __future__ import annotations

import json

import pytest

from clips_fixtures import SMALL_BAKE
from crowdbake.cli import main
from crowdbake.formats.bundle import verify_bundle


def bake_args(sample, out, *extra: str) -> list[str]:
    return ["bake", str(sample / "character.glb"), "--cloth", str(sample / "cloth.pc2"), "--cloth-mesh", str(sample / "cloth.obj"),
            "--textures", str(sample / "textures"), "--name", "bounds", "--version", "1", "--out", str(out),
            "--close", "hermite", *SMALL_BAKE, *extra]


def test_a_loop_out_of_bounds_fails_the_bake_in_one_line(small_sample, tmp_path, capsys):
    assert main(bake_args(small_sample, tmp_path / "bundles", "--work", str(tmp_path / "work"))) == 2
    # The stages' progress lines aside (stderr without a terminal), the error is one line.
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("crowdbake bake: error: ")]
    assert len(errors) == 1 and errors[0].startswith("crowdbake bake: error: the loop of clip 'cloth' (cache frames ["), errors
    assert "_ratio " in errors[0] and " > " in errors[0] and "--accept-out-of-bounds" in errors[0]
    assert not (tmp_path / "bundles" / "bounds").exists()
    # The work folder keeps the search's cycle.json, which lists every figure out of bounds.
    document = json.loads((tmp_path / "work" / "cycle" / "cycle.json").read_text())
    assert document["out_of_bounds"] and document["accept_out_of_bounds"] is False


def test_accepted_it_is_published_and_the_manifest_says_what_was_accepted(small_sample, tmp_path):
    assert main(bake_args(small_sample, tmp_path, "--accept-out-of-bounds")) == 0
    bundle = verify_bundle(tmp_path / "bounds" / "1")
    accepted = bundle.manifest["accepted_out_of_bounds"]
    assert accepted and {entry["figure"] for entry in accepted} <= {"stretch_ratio", "deviation_ratio", "seam_acceleration_ratio"}
    for entry in accepted:
        assert entry["where"].startswith("the loop of clip 'cloth' (cache frames [")
        assert entry["value"] > entry["bound"]
    published = json.loads((tmp_path / "bounds" / "1" / "cycle.json").read_text())
    assert published["out_of_bounds"] == accepted and published["accept_out_of_bounds"] is True


@pytest.mark.parametrize("field", ["where", "figure"])
def test_the_schema_refuses_an_accepted_entry_without_its_fields(field):
    from crowdbake.formats.bundle import _validator

    entry = {"where": "the loop of clip 'Idle' (cache frames [871, 951))", "cache_frames": [871, 951],
             "figure": "seam_acceleration_ratio", "value": 4.17, "bound": 1.5}
    schema_errors = lambda accepted: list(_validator().iter_errors({"accepted_out_of_bounds": accepted}))  # noqa: E731
    relevant = lambda errors: [e for e in errors if list(e.absolute_path)[:1] == ["accepted_out_of_bounds"]]  # noqa: E731
    assert not relevant(schema_errors([entry]))
    del entry[field]
    assert relevant(schema_errors([entry]))


def test_a_given_cycle_out_of_bounds_needs_the_bake_to_accept_it_too():
    """`crowdbake cycle --accept-out-of-bounds` wrote it: a bake of that cycle.json accepts it again, or fails."""
    from crowdbake.errors import InputError, OutOfBoundsError
    from crowdbake.stages.cycle import _check_given_bounds

    entry = {"where": "the loop of clip 'cloth' (cache frames [57, 77))", "cache_frames": [57, 77], "figure": "deviation_ratio",
             "value": 3.08, "bound": 1.5}
    with pytest.raises(OutOfBoundsError, match=r"^the given cycle: the loop of clip 'cloth' \(cache frames \[57, 77\)\): deviation_ratio 3.08 > 1.5"):
        _check_given_bounds({"out_of_bounds": [entry]}, accept=False)
    _check_given_bounds({"out_of_bounds": [entry]}, accept=True)
    _check_given_bounds({}, accept=False)  # a cycle.json from before the bounds were enforced
    with pytest.raises(InputError, match="out_of_bounds"):
        _check_given_bounds({"out_of_bounds": [{"where": "x"}]}, accept=False)
