"""Helpers shared by the subcommands: one-line errors and progress bars."""
from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator

from tqdm import tqdm


class CommandError(Exception):
    """A user-facing failure: printed as one line, exits with `exit_code`."""

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code


@contextmanager
def progress(total: int | None, description: str) -> Iterator[tqdm]:
    """A progress bar on stderr (total None: a count without one); silent when stderr is not a terminal
    unless CROWDBAKE_PROGRESS=1."""
    import os

    enabled = sys.stderr.isatty() or os.environ.get("CROWDBAKE_PROGRESS") == "1"
    with tqdm(total=total, desc=description, file=sys.stderr, disable=not enabled, leave=False) as bar:
        yield bar
