"""Progress of a bake as a person reads it: it only moves forward.

The server reports each stage's `done/total` as the stage goes through its own steps (the cycle search
counts its candidates, then its report: 5/5, then 1/1), and a retried stage starts again from zero.
Shown as they come, those numbers go backwards. Here every stage keeps the largest fraction seen and
the bake the largest overall fraction, so the bar and the lines never move back; a retry of the whole
bake (a new attempt) starts a new record.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any

FINAL_STATES = frozenset({"succeeded", "failed", "cancelled"})
ACTIVE_STAGE_STATES = frozenset({"running", "retrying"})
# A terminal bar without a rate: bake stages are not iterations, "it/s" means nothing.
BAR_FORMAT = "{desc} {percentage:3.0f}%|{bar}| {elapsed}"


@dataclass
class ForwardProgress:
    """The largest fractions seen so far, per stage and overall, for one attempt of one bake."""

    attempt: int = -1
    overall: float = 0.0
    stages: dict[str, float] = field(default_factory=dict)
    finished: set[str] = field(default_factory=set)


def stage_fraction(stage: dict[str, Any]) -> float:
    """0..1 of one stage record (state, done, total) of GET /v1/bakes/{id}."""
    if stage["state"] in ("succeeded", "skipped"):
        return 1.0
    if stage["total"] > 0:
        return min(max(stage["done"] / stage["total"], 0.0), 1.0)
    return 0.0


def advance(previous: ForwardProgress, bake: dict[str, Any]) -> ForwardProgress:
    """The progress after `bake` (a GET /v1/bakes/{id} answer): never below `previous` unless the bake
    started a new attempt."""
    if bake.get("attempt", 0) != previous.attempt:
        previous = ForwardProgress(attempt=bake.get("attempt", 0))
    stages = dict(previous.stages)
    finished = set(previous.finished)
    for stage in bake["stages"]:
        stages[stage["stage"]] = max(stages.get(stage["stage"], 0.0), stage_fraction(stage))
        if stage["state"] in ("succeeded", "skipped"):
            finished.add(stage["stage"])
    overall = 1.0 if bake["state"] == "succeeded" else max(previous.overall, float(bake.get("progress", 0.0)))
    return ForwardProgress(attempt=previous.attempt, overall=overall, stages=stages, finished=finished)


def describe(bake: dict[str, Any], progress: ForwardProgress) -> str:
    """`bake ID: STATE NN% (stage NN%, ...)`: the overall percentage and each running stage's."""
    running = [stage["stage"] for stage in bake["stages"] if stage["state"] in ACTIVE_STAGE_STATES]
    where = ", ".join(f"{name} {progress.stages.get(name, 0.0) * 100:.0f}%" for name in running)
    return f"bake {bake['id']}: {bake['state']} {progress.overall * 100:.0f}%{' (' + where + ')' if where else ''}"


class Reporter:
    """Shows progress on stderr: a bar on a terminal, else one plain line per change; nothing when quiet."""

    def __init__(self, bake_id: str, quiet: bool = False, stream=None):
        self.stream = stream or sys.stderr
        self.quiet = quiet
        self.progress = ForwardProgress()
        self.last_line = ""
        self.bar = None
        if not quiet and self.stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=100, desc=f"bake {bake_id}", file=self.stream, bar_format=BAR_FORMAT, leave=False)

    def show(self, bake: dict[str, Any]) -> ForwardProgress:
        self.progress = advance(self.progress, bake)
        line = describe(bake, self.progress)
        if self.bar is not None:
            self.bar.set_description_str(line.split(": ", 1)[1] if ": " in line else line, refresh=False)
            self.bar.n = round(self.progress.overall * 100)
            self.bar.refresh()
        elif not self.quiet and line != self.last_line:
            print(line, file=self.stream, flush=True)
        self.last_line = line
        return self.progress

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
