"""Wall, CPU and OpenGL seconds of a local bake, per stage and per item, and its timeline.

An item's figures come from `measured` (in whichever process ran it); the runner adds them to its
stage (Meter.account). A stage's wall is the time during which at least one of its items ran (items
of one stage overlap in the pool), so the stages' walls may add up to more than the bake's.
"""
from __future__ import annotations

import os
import resource
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from crowdbake.render.offscreen import render_timings
from crowdbake.stages import STAGES
from crowdbake.stages.worker_pool import cpu_seconds


@dataclass
class StageFigures:
    """One stage's wall, CPU and OpenGL seconds, and its renders."""

    wall_s: float = 0.0
    cpu_s: float = 0.0
    render_s: float = 0.0
    renders: int = 0


def measured(body: Callable[[], Any]) -> dict[str, Any]:
    """Run body; its result and the wall, CPU (this process, every thread) and GL seconds it took, with this
    process's figures: id, high-water mark (MiB) and CPU seconds so far, and the item's span (epoch seconds)."""
    gl, wall, cpu, began = render_timings(), time.perf_counter(), time.process_time(), time.time()
    result = body()
    gl = render_timings().minus(gl)
    return {"result": result, "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
            "render_s": gl.seconds, "renders": gl.renders, "pid": os.getpid(), "span": (began, time.time()),
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "process_cpu_s": cpu_seconds()}


def covered_seconds(spans: list[tuple[float, float]]) -> float:
    """Seconds covered by at least one of the (start, end) spans."""
    total, reach = 0.0, float("-inf")
    for start, end in sorted(spans):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


class Meter:
    """Every item's figures, by stage, and the timeline of the bake."""

    def __init__(self) -> None:
        self.stages: dict[str, StageFigures] = {stage: StageFigures() for stage in STAGES}
        self.epoch = time.time()
        self.timeline: list[dict[str, Any]] = []
        self._spans: dict[str, list[tuple[float, float]]] = {stage: [] for stage in STAGES}
        self.worker_peak_rss_mib: float | None = None
        self.worker_cpu_s: dict[int, float] = {}  # per worker process, its CPU seconds at its last item

    def account(self, stage: str, item: str, figures: dict[str, Any], in_worker: bool) -> None:
        began, ended = figures["span"]
        span = {"item": item, "pid": figures["pid"], "start_s": began - self.epoch, "end_s": ended - self.epoch, "cpu_s": figures["cpu_s"]}
        if in_worker:
            span["process_peak_rss_mib"] = figures["peak_rss_mib"]
            self.worker_peak_rss_mib = max(self.worker_peak_rss_mib or 0.0, figures["peak_rss_mib"])
            self.worker_cpu_s[figures["pid"]] = max(self.worker_cpu_s.get(figures["pid"], 0.0), figures["process_cpu_s"])
        self.timeline.append(span)
        self._spans[stage].append((began, ended))
        totals = self.stages[stage]
        totals.cpu_s += figures["cpu_s"]
        totals.render_s += figures["render_s"]
        totals.renders += int(figures["renders"])
        totals.wall_s = covered_seconds(self._spans[stage])

    def covered(self, *stages: str) -> float:
        return covered_seconds([span for stage in stages for span in self._spans[stage]])


class Background:
    """Callables run one after another in a thread from start() on; result() waits and re-raises their
    error. Their CPU seconds (time.thread_time) are added to `figures`."""

    def __init__(self, name: str, calls: list[Callable[[], None]], figures: StageFigures):
        self._calls, self._figures, self._error = calls, figures, None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread (once; a second call does nothing)."""
        if self._thread.ident is None:
            self._thread.start()

    def _run(self) -> None:
        started = time.thread_time()
        try:
            for call in self._calls:
                call()
        except BaseException as error:  # noqa: BLE001 - handed to the caller by result()
            self._error = error
        self._figures.cpu_s += time.thread_time() - started

    def result(self) -> None:
        self.start()  # where nothing started it (an error before its moment)
        self._thread.join()
        if self._error is not None:
            raise self._error
