"""Where the repository, its vectors and the shared third-party assets are (importable by any test module;
`conftest` is not, since services/tests and tests each have one)."""
from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_ASSETS = Path(os.environ.get("CROWDBAKE_SHARED_ASSETS", REPO_ROOT.parent / "shared" / "assets"))
VECTORS = REPO_ROOT / "shared_formats" / "vectors"
