"""Readiness checks that cannot take the API down with them.

A dependency that accepts connections but never answers (a stopped Redis, a stalled fsync, a network
partition) would block each `/ready` call in a thread of the request pool until that pool is empty;
then `/health` and every other route would stop answering too. Here each dependency is checked by at most
one thread at a time (single flight) from a small executor of its own, every caller waits at most
`deadline_s`, and a fresh answer is shared for `fresh_s` seconds, so any number of probes costs at most
one blocked thread per dependency and never a thread of the request pool.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
from dataclasses import dataclass, field
from typing import Callable

logger = logging.getLogger(__name__)

# Seconds a readiness caller waits for one dependency before reporting it as not answering: well under
# the probe timeouts of Kubernetes (1 s default, deploy/k8s sets 5 s) plus the transport's own timeouts.
READY_DEADLINE_S = 2.0
# Seconds an answer is reused: load balancers probe every few seconds, from many replicas.
READY_FRESH_S = 1.0

Check = Callable[[], str]  # returns "ok" or a short reason (no host names, paths or credentials)


@dataclass
class _Flight:
    future: concurrent.futures.Future | None = None
    answer: str | None = None
    answered_at: float = float("-inf")


@dataclass
class ReadinessProbe:
    """Named dependency checks, each run single-flight with a deadline (see the module doc)."""

    checks: dict[str, Check]
    deadline_s: float = READY_DEADLINE_S
    fresh_s: float = READY_FRESH_S
    _flights: dict[str, _Flight] = field(default_factory=dict)
    _executor: concurrent.futures.ThreadPoolExecutor | None = None

    def __post_init__(self) -> None:
        # One thread per dependency at most: a hung check holds its own thread, never another's.
        self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=max(1, len(self.checks)), thread_name_prefix="ready")
        self._flights = {name: _Flight() for name in self.checks}

    def _run(self, name: str) -> str:
        try:
            return self.checks[name]()
        except Exception as error:  # a check that raises reports why, it does not fail the probe
            logger.warning("readiness check %s failed: %s", name, error)
            return f"failed: {type(error).__name__}"

    def _settle(self, flight: _Flight) -> None:
        """Take a finished check's answer."""
        if flight.future is not None and flight.future.done():
            flight.answer, flight.answered_at = flight.future.result(), time.monotonic()
            flight.future = None

    async def states(self) -> dict[str, str]:
        """{dependency: "ok" or why not}; returns within about `deadline_s` whatever the dependencies do."""
        now = time.monotonic()
        waiting = []
        for name, flight in self._flights.items():
            self._settle(flight)
            if flight.future is None and now - flight.answered_at >= self.fresh_s:
                flight.future = self._executor.submit(self._run, name)
            if flight.future is not None:
                waiting.append(asyncio.wrap_future(flight.future))
        if waiting:
            await asyncio.wait(waiting, timeout=self.deadline_s)
        states: dict[str, str] = {}
        for name, flight in self._flights.items():
            self._settle(flight)
            # Still running past the deadline: whatever it said before, it does not answer now.
            states[name] = flight.answer if flight.future is None else f"no answer within {self.deadline_s:g} s"
        return states

    def close(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)
