"""Blender's `bpy` module imported without its NumPy 1.x warning.

bpy 5.0.1's own extension, bpy/__init__.so, links Blender's Python bindings that take NumPy arrays
(audaspace's `aud` sound data, Mantaflow's grids) built against the NumPy 1.x C API. Beside NumPy 2
(services/requirements-alembic.txt installs bpy with --no-deps), their `import_array()` fails as bpy
starts: NumPy's "A module that was compiled using NumPy 1.x cannot be run in NumPy 2..." and two
tracebacks go to stderr, then bpy carries on; nothing crowdbake calls in Blender uses those bindings.
Blender's C code prints them straight to file descriptor 2, so only redirecting that descriptor
around the import keeps them off the terminal.
"""
from __future__ import annotations

import os
import sys
import tempfile
from types import ModuleType

# The first and last lines NumPy and bpy print for the failed import_array(); what lies between is dropped.
NUMPY_ABI_FIRST_LINE = "A module that was compiled using NumPy 1.x cannot be run in"
NUMPY_ABI_LAST_LINE = "ImportError: numpy.core.multiarray failed to import"


def without_numpy_abi_warning(text: str) -> str:
    """`text` less the NumPy 1.x warning block (first line to last line, both included); unchanged when it
    holds no complete block."""
    start = text.find(NUMPY_ABI_FIRST_LINE)
    end = text.find(NUMPY_ABI_LAST_LINE, start)
    if start < 0 or end < 0:
        return text
    end = text.find("\n", end)
    return text[:start].rstrip("\n") + ("\n" if start else "") + (text[end + 1:] if end >= 0 else "")


def import_bpy() -> ModuleType:
    """The bpy module, imported with file descriptor 2 captured. On success, whatever else the import
    printed is passed on to stderr; a failed import raises ImportError holding all it printed."""
    sys.stderr.flush()
    saved = os.dup(2)
    failure: Exception | None = None
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            import bpy
        except Exception as error:  # a missing library, a crash in bpy's init: all of it is reported below
            failure = error
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        printed = captured.read().decode(errors="replace")
    if failure is not None:
        raise ImportError(f"import bpy failed: {failure}\n{printed}".rstrip()) from failure
    rest = without_numpy_abi_warning(printed)
    if rest.strip():
        sys.stderr.write(rest)
        sys.stderr.flush()
    return bpy
