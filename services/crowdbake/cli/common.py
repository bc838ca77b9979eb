"""Helpers shared by the subcommands: one-line errors and progress bars."""
from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager
from typing import Iterator

from tqdm import tqdm


class CommandError(Exception):
    """A user-facing failure: printed as one line, exits with `exit_code`."""

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code


def bars_enabled() -> bool:
    """Progress bars on stderr when it is a terminal, or when CROWDBAKE_PROGRESS=1."""
    return sys.stderr.isatty() or os.environ.get("CROWDBAKE_PROGRESS") == "1"


@contextmanager
def progress(total: int | None, description: str) -> Iterator[tqdm]:
    """A progress bar on stderr (total None: a count without one); silent unless bars_enabled()."""
    with tqdm(total=total, desc=description, file=sys.stderr, disable=not bars_enabled(), leave=False) as bar:
        yield bar


class StageLines:
    """Progress for a log rather than a terminal (a CI job's stderr): one line when a stage starts and one
    when it has done all its items, with the seconds since it started, so a long bake is never silent."""

    def __init__(self, command: str, stream=None):
        self.command = command
        self.stream = stream if stream is not None else sys.stderr
        self.started: dict[str, float] = {}
        self.finished: set[str] = set()

    def __call__(self, stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        if stage not in self.started:
            self.started[stage] = now
            print(f"{self.command}: {stage} started ({total} item{'s' if total != 1 else ''})", file=self.stream, flush=True)
        if done >= total and stage not in self.finished:
            self.finished.add(stage)
            print(f"{self.command}: {stage} done in {now - self.started[stage]:.1f} s", file=self.stream, flush=True)

    def close(self) -> None:
        """Nothing is held open (a progress bar's counterpart)."""
