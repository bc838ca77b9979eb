"""Where the repository, its vectors and the shared third-party assets are (importable by any test module;
`conftest` is not, since services/tests and tests each have one)."""
from __future__ import annotations

import json
import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_ASSETS = Path(os.environ.get("CROWDBAKE_SHARED_ASSETS", REPO_ROOT.parent / "shared" / "assets"))
VECTORS = REPO_ROOT / "shared_formats" / "vectors"

# Vectors are never edited, so an expectation a newer reader no longer meets is restated here (SPEC.md,
# "Vectors"): vectors/v1/bad/future_format_version says format_version 2, the future when it was written; a
# reader of v2 reads it as a v2 manifest holding v1's `cycle` and no clips, which is manifest_invalid.
# vectors/v2/bad/future_format_version says 3: a reader of v3 reads it as a v3 bundle holding version-1
# pose caches, invalid_data at the first (SPEC.md "Version 3").
# vectors/v3/bad/future_format_version says 4: v3's good bundle read as v4, which holds such a bundle
# (SPEC.md "Version 4"), so a reader of v4 reads it whole ({"error": None}).
SUPERSEDED_EXPECTATIONS = {"v1/bad/future_format_version": {"error": "manifest_invalid", "file": "manifest.json"},
                           "v2/bad/future_format_version": {"error": "invalid_data", "file": "poses/body_lod0.cbpc"},
                           "v3/bad/future_format_version": {"error": None, "file": None}}


def vector_expectation(case: Path) -> dict:
    """The {error, file} a reader of the newest format gives for the bad vector folder `case`."""
    key = case.resolve().relative_to(VECTORS.resolve()).as_posix()
    return SUPERSEDED_EXPECTATIONS.get(key) or json.loads((case / "expect.json").read_text())
