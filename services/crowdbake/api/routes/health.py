"""Health (the process answers) and readiness (its database, blob store and broker are usable)."""
from __future__ import annotations

import os
import tempfile

from fastapi import APIRouter
from sqlalchemy import text

from crowdbake import __version__
from crowdbake.api.deps import ServicesDep
from crowdbake.api.problems import Problem
from crowdbake.api.schemas import HealthPublic, ReadinessPublic, problem_responses
from crowdbake.jobs.celery_app import broker_reachable
from crowdbake.storage.db import is_migrated

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthPublic, summary="Liveness: the process answers")
def health() -> HealthPublic:
    return HealthPublic(status="ok", version=__version__)


def _writable(folder) -> str:
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".ready-"):
            pass
    except OSError as error:
        return f"not writable: {error}"
    return "ok"


@router.get("/ready", response_model=ReadinessPublic, responses=problem_responses(503), summary="Readiness: dependencies usable")
def ready(services: ServicesDep) -> ReadinessPublic:
    checks: dict[str, str] = {}
    try:
        engine = services.sessions.kw["bind"]
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        checks["database"] = "ok" if is_migrated(engine) else "not migrated to the newest schema"
    except Exception as error:  # any driver error means "not ready"
        checks["database"] = f"unreachable: {type(error).__name__}: {error}"
    checks["blob_store"] = _writable(services.blobs.staging_dir)
    checks["bundles"] = _writable(services.settings.bundles_dir) if os.path.isdir(services.settings.bundles_dir) else "missing"
    broker_error = broker_reachable(services.celery)
    checks["broker"] = "ok" if broker_error is None else f"unreachable: {broker_error}"
    failing = {name: state for name, state in checks.items() if state != "ok"}
    if failing:
        raise Problem("not-ready", "not ready: " + "; ".join(f"{name} {state}" for name, state in failing.items()),
                      [{"field": name, "message": state} for name, state in failing.items()])
    return ReadinessPublic(status="ready", checks=checks)
