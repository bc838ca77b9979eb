"""GET /metrics: Prometheus text exposition (crowdbake.metrics). No key: the figures are counts and
durations, never names or ids, and the scrape annotations of deploy/k8s/api.yaml point here."""
from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse, Response

from crowdbake.metrics import CONTENT_TYPE

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics: bakes by state, stage durations and failures, HTTP latency")
def metrics(request: Request) -> Response:
    return Response(request.app.state.metrics.exposition(), media_type=CONTENT_TYPE)
