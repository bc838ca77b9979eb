"""Prometheus metrics of the service: what the database says about bakes, and what this API process saw.

Two sources, because the work happens in other processes:

- **Bake figures are read from the database at scrape time** (`DatabaseCollector`). Workers run in
  other processes, often on other machines, and the database is already the truth about every bake:
  each stage row records its state, its start and end times and the seconds its work took
  (crowdbake.storage.records). Reading them when Prometheus asks needs no shared metrics directory, no
  push gateway and no hooks in the workers, and every API replica reports the same numbers.
- **HTTP figures are counted in the API process** (`HttpMetrics`, an ASGI middleware): request
  latency by route template, and the bytes of upload bodies received.

The bake figures are gauges and histograms of the records *as they are now*: a retried bake starts its
stage records afresh (records.reset_for_retry), so a failure that was retried leaves
`crowdbake_stage_failures` and a duration histogram can lose an observation. That is the database's
view, which is the one the API serves too; alert on rates of the HTTP counters and on the levels of
the bake gauges.

With several API processes behind one port (uvicorn --workers N), set PROMETHEUS_MULTIPROC_DIR to an
empty folder shared by them (prometheus_client's multiprocess mode): `/metrics` then sums every
process's HTTP figures. The database figures need nothing of the sort.
"""
from __future__ import annotations

import logging
import os
import time
from collections import Counter
from dataclasses import dataclass
from typing import Iterable, Sequence

from prometheus_client import CollectorRegistry, Histogram, ProcessCollector, generate_latest
from prometheus_client import Counter as PromCounter
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from crowdbake.stages import STAGES
from crowdbake.storage.models import BAKE_STATES, FINAL_BAKE_STATES, STAGE_STATES, Asset, Bake, BakePart, BakeStage

logger = logging.getLogger(__name__)

# Bakes and stages last seconds (a small sample) to hours (a 1024² texture set with 64 azimuths):
# bucket edges in seconds, roughly x2.5 apart.
DURATION_BUCKETS_S = (1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0, 7200.0)
# HTTP latency: prometheus_client's defaults (5 ms .. 10 s) and two longer edges for large uploads.
HTTP_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 120.0)
# Label of requests that matched no route (404s of unknown paths): one value, so scanners probing
# random paths cannot blow up the number of series.
UNMATCHED_ROUTE = "<unmatched>"
UPLOAD_PREFIX = "/v1/assets/"
UPLOAD_KINDS = {"characters": "character", "cloth": "cloth", "textures": "texture", "cycles": "cycle"}
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


# ------------------------------------------------------------------------------------ pure helpers


def cumulative_buckets(values: Iterable[float], edges: Sequence[float]) -> list[tuple[str, int]]:
    """Prometheus histogram buckets of `values`: [(upper edge as text, count <= edge), ..., ("+Inf", n)].

    edges: increasing upper bounds in the values' unit. Counts are cumulative, as the exposition
    format requires.
    """
    values = list(values)
    if any(b <= a for a, b in zip(edges, edges[1:])):
        raise ValueError(f"cumulative_buckets: edges must increase, got {edges}")
    buckets = [(_edge_text(edge), sum(1 for value in values if value <= edge)) for edge in edges]
    buckets.append(("+Inf", len(values)))
    return buckets


def _edge_text(edge: float) -> str:
    # The exposition format's `le` values as prometheus_client writes them ("1.0", "2.5", "60.0").
    return repr(float(edge))


def seconds_between(start, end) -> float | None:
    """Seconds from `start` to `end` (datetimes; either may be None or naive UTC, as SQLite returns them)."""
    if start is None or end is None:
        return None
    if (start.tzinfo is None) != (end.tzinfo is None):
        start, end = start.replace(tzinfo=None), end.replace(tzinfo=None)
    return max((end - start).total_seconds(), 0.0)


# ----------------------------------------------------------------------------- database collector


@dataclass
class BakeFigures:
    """What one scrape read from the database (plain data, so the exposition is easy to test)."""

    bakes_by_state: dict[str, int]
    stages_by_state: dict[tuple[str, str], int]
    stage_seconds: dict[str, list[float]]  # succeeded stages: the work's seconds, per stage
    stage_retries: dict[str, int]
    failures: dict[tuple[str, str], int]  # (stage, error type) -> failed bakes
    bake_seconds: dict[str, list[float]]  # final state -> started .. finished of each bake
    queue_wait_seconds: list[float]  # created .. started of each bake that started
    impostor_tasks_pending: int
    asset_bytes: dict[str, int]
    asset_count: dict[str, int]


def read_bake_figures(session: Session) -> BakeFigures:
    """Read the bake, stage, part and asset records once (a handful of grouped queries)."""
    bakes_by_state = dict.fromkeys(BAKE_STATES, 0)
    bakes_by_state.update({state: count for state, count in session.execute(select(Bake.state, func.count()).group_by(Bake.state))})

    stages_by_state = {(stage, state): 0 for stage in STAGES for state in STAGE_STATES}
    stage_retries = dict.fromkeys(STAGES, 0)
    for stage, state, count, retries in session.execute(
        select(BakeStage.stage, BakeStage.state, func.count(), func.coalesce(func.sum(BakeStage.retries), 0)).group_by(BakeStage.stage, BakeStage.state)
    ):
        stages_by_state[(stage, state)] = count
        stage_retries[stage] = stage_retries.get(stage, 0) + int(retries)

    stage_seconds: dict[str, list[float]] = {stage: [] for stage in STAGES}
    for stage, seconds in session.execute(
        select(BakeStage.stage, BakeStage.seconds).where(BakeStage.state == "succeeded", BakeStage.seconds.is_not(None))
    ):
        stage_seconds.setdefault(stage, []).append(float(seconds))

    failures: Counter[tuple[str, str]] = Counter()
    for (error,) in session.execute(select(Bake.error).where(Bake.state == "failed")):
        error = error or {}
        failures[(str(error.get("stage") or "unknown"), str(error.get("type") or "unknown"))] += 1

    bake_seconds: dict[str, list[float]] = {state: [] for state in sorted(FINAL_BAKE_STATES)}
    queue_wait: list[float] = []
    for state, created, started, finished in session.execute(select(Bake.state, Bake.created_at, Bake.started_at, Bake.finished_at)):
        wait = seconds_between(created, started)
        if wait is not None:
            queue_wait.append(wait)
        if state in FINAL_BAKE_STATES:
            took = seconds_between(started, finished)
            if took is not None:
                bake_seconds[state].append(took)

    pending_parts = session.scalar(
        select(func.count()).select_from(BakePart).join(Bake, Bake.id == BakePart.bake_id)
        .where(BakePart.stage == "impostors", BakePart.done.is_(False), Bake.state.in_(("queued", "running")))
    )
    asset_bytes, asset_count = {}, {}
    for kind, size, count in session.execute(select(Asset.kind, func.coalesce(func.sum(Asset.size), 0), func.count()).group_by(Asset.kind)):
        asset_bytes[kind], asset_count[kind] = int(size), int(count)
    return BakeFigures(bakes_by_state, stages_by_state, stage_seconds, stage_retries, dict(failures), bake_seconds, queue_wait,
                       int(pending_parts or 0), asset_bytes, asset_count)


def _histogram(name: str, documentation: str, label: str | None, series: dict[str, list[float]] | list[float]) -> HistogramMetricFamily:
    family = HistogramMetricFamily(name, documentation, labels=[label] if label else None)
    groups = series.items() if isinstance(series, dict) else [(None, series)]
    for key, values in groups:
        family.add_metric([key] if label else [], cumulative_buckets(values, DURATION_BUCKETS_S), sum_value=float(sum(values)))
    return family


def figures_to_metrics(figures: BakeFigures) -> list[Metric]:
    """The exposition of one database read (names prefixed crowdbake_)."""
    bakes = GaugeMetricFamily("crowdbake_bakes", "Bakes by state, as recorded in the database (queued ones are the queue depth).", labels=["state"])
    for state, count in figures.bakes_by_state.items():
        bakes.add_metric([state], count)
    stages = GaugeMetricFamily("crowdbake_bake_stages", "Stage records of all bakes by stage and state.", labels=["stage", "state"])
    for (stage, state), count in sorted(figures.stages_by_state.items()):
        stages.add_metric([stage, state], count)
    retries = GaugeMetricFamily("crowdbake_stage_retries", "Retries after transient errors, summed over the stage records.", labels=["stage"])
    for stage, count in figures.stage_retries.items():
        retries.add_metric([stage], count)
    failures = GaugeMetricFamily("crowdbake_stage_failures", "Failed bakes by the stage that failed and the error type.", labels=["stage", "type"])
    for stage in STAGES:  # every stage present, so a dashboard shows zero rather than no data
        if not any(key[0] == stage for key in figures.failures):
            failures.add_metric([stage, "none"], 0)
    for (stage, kind), count in sorted(figures.failures.items()):
        failures.add_metric([stage, kind], count)
    pending = GaugeMetricFamily("crowdbake_impostor_tasks_pending", "Impostor-view tasks of queued or running bakes not yet done.",
                                value=figures.impostor_tasks_pending)
    asset_bytes = GaugeMetricFamily("crowdbake_asset_bytes", "Bytes of validated uploads stored, by asset kind.", labels=["kind"])
    asset_count = GaugeMetricFamily("crowdbake_assets", "Validated uploads stored, by asset kind.", labels=["kind"])
    for kind in ("character", "cloth", "texture", "cycle"):
        asset_bytes.add_metric([kind], figures.asset_bytes.get(kind, 0))
        asset_count.add_metric([kind], figures.asset_count.get(kind, 0))
    return [
        bakes, stages, retries, failures, pending, asset_bytes, asset_count,
        _histogram("crowdbake_stage_duration_seconds", "Seconds of work of each succeeded stage record (impostors: summed over its tasks).",
                   "stage", figures.stage_seconds),
        _histogram("crowdbake_bake_duration_seconds", "Seconds from a bake's start to its end, by final state.", "state", figures.bake_seconds),
        _histogram("crowdbake_bake_queue_wait_seconds", "Seconds from a bake's creation to its first stage starting.", None,
                   figures.queue_wait_seconds),
    ]


class DatabaseCollector(Collector):
    """Reads the bake records at every scrape (registered in a CollectorRegistry)."""

    def __init__(self, sessions: sessionmaker[Session]):
        self.sessions = sessions

    def collect(self) -> Iterable[Metric]:
        started = time.perf_counter()
        up = 1
        try:
            with self.sessions() as session:
                metrics = figures_to_metrics(read_bake_figures(session))
        except Exception:  # a scrape must still answer, saying the database could not be read
            logger.exception("metrics: could not read the bake records")
            metrics, up = [], 0
        yield from metrics
        yield GaugeMetricFamily("crowdbake_database_up", "1 when the last scrape could read the bake records.", value=up)
        yield GaugeMetricFamily("crowdbake_metrics_scrape_seconds", "Seconds this scrape spent reading the database.",
                                value=time.perf_counter() - started)


# ------------------------------------------------------------------------------ HTTP, this process


class HttpMetrics:
    """This process's HTTP figures, and the registry `/metrics` exposes.

    One instance per app (tests build several apps in one process, and a registry refuses a second
    metric of the same name).
    """

    def __init__(self, sessions: sessionmaker[Session]):
        self.multiprocess_dir = os.environ.get("PROMETHEUS_MULTIPROC_DIR") or None
        # In multiprocess mode the values live in files; the metrics need no registry of their own.
        own = None if self.multiprocess_dir else CollectorRegistry()
        self.registry = own
        self.database = DatabaseCollector(sessions)
        self.request_seconds = Histogram(
            "crowdbake_http_request_duration_seconds", "Seconds from request to the end of the response, by route template.",
            ["method", "route", "status"], buckets=HTTP_BUCKETS_S, registry=own,
        )
        self.upload_bytes = PromCounter(
            "crowdbake_upload_bytes", "Bytes of upload request bodies received, by asset kind and outcome (stored or refused).",
            ["kind", "outcome"], registry=own,
        )
        if own is not None:
            own.register(self.database)
            ProcessCollector(registry=own)

    def exposition(self) -> bytes:
        """The text exposition of everything: this process (or all processes sharing the multiprocess
        folder) and the database."""
        if self.multiprocess_dir is None:
            return generate_latest(self.registry)
        from prometheus_client import multiprocess

        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry, path=self.multiprocess_dir)
        registry.register(self.database)
        return generate_latest(registry)


# HTTP methods recorded by name; any other (clients may send made-up ones) is counted as "OTHER", so the
# label set, and /metrics with it, stays bounded whatever arrives.
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


def method_label(method: str) -> str:
    return method if method in KNOWN_METHODS else "OTHER"


def route_template(scope: dict) -> str:
    """The matched route's path template (/v1/bakes/{bake_id}), never the raw path (unbounded labels)."""
    route = scope.get("route")
    path = getattr(route, "path_format", None) or getattr(route, "path", None)
    return path or UNMATCHED_ROUTE


def upload_kind(method: str, path: str) -> str | None:
    """The asset kind an upload request posts, or None when the request is no upload."""
    if method != "POST" or not path.startswith(UPLOAD_PREFIX):
        return None
    return UPLOAD_KINDS.get(path[len(UPLOAD_PREFIX):].strip("/"), "other")


class MetricsMiddleware:
    """Pure ASGI middleware: times each HTTP request and counts the bytes of upload bodies.

    (Not BaseHTTPMiddleware: that would buffer streamed responses such as bundle files.)
    """

    def __init__(self, app, metrics: HttpMetrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = {"code": 500}
        kind = upload_kind(scope["method"], scope["path"])
        received = {"bytes": 0}

        async def counting_receive():
            message = await receive()
            if message["type"] == "http.request":
                received["bytes"] += len(message.get("body", b""))
            return message

        async def recording_send(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, counting_receive if kind else receive, recording_send)
        finally:
            route = route_template(scope)
            self.metrics.request_seconds.labels(method_label(scope["method"]), route, str(status["code"])).observe(time.perf_counter() - started)
            if kind:
                outcome = "stored" if status["code"] < 300 else "refused"
                self.metrics.upload_bytes.labels(kind, outcome).inc(received["bytes"])
