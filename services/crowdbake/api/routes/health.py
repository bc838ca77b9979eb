"""Health (the process answers) and readiness (its database, blob store and broker are usable).

Both are `async` and touch no thread of the request pool: liveness must hold while every worker thread is
stuck on a dependency, and readiness bounds its own wait (crowdbake.api.readiness). Readiness reports a
short state per dependency, never host names, ports, paths or credentials (it needs no key); the
details go to the log."""
from __future__ import annotations

import logging
import os
import tempfile

from fastapi import APIRouter, Request
from sqlalchemy import text

from crowdbake import __version__
from crowdbake.api.deps import AppServices
from crowdbake.api.problems import Problem
from crowdbake.api.readiness import ReadinessProbe
from crowdbake.api.schemas import HealthPublic, ReadinessPublic, problem_responses
from crowdbake.jobs.celery_app import broker_reachable
from crowdbake.storage.db import is_migrated

logger = logging.getLogger(__name__)
router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthPublic, summary="Liveness: the process answers")
async def health() -> HealthPublic:
    return HealthPublic(status="ok", version=__version__)


def _writable(folder) -> str:
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".ready-"):
            pass
    except OSError as error:
        logger.warning("readiness: %s is not writable: %s", folder, error)
        return "not writable"
    return "ok"


def _database_state(services: AppServices) -> str:
    try:
        engine = services.sessions.kw["bind"]
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        return "ok" if is_migrated(engine) else "not migrated to the newest schema"
    except Exception as error:  # any driver error means "not ready"
        logger.warning("readiness: database unreachable: %s", error)
        return f"unreachable: {type(error).__name__}"


def _broker_state(services: AppServices) -> str:
    error = broker_reachable(services.celery)
    if error is not None:
        logger.warning("readiness: broker unreachable: %s", error)
    return "ok" if error is None else f"unreachable: {error}"


def _bucket_state(store) -> str:
    """An object store's bucket answers (HEAD bucket) with this process's credentials."""
    try:
        store.client.head_bucket(Bucket=store.bucket)
    except Exception as error:  # any client error means "not ready"; the log has the details
        logger.warning("readiness: bucket %s unusable: %s", store.bucket, error)
        return f"unreachable: {type(error).__name__}"
    return "ok"


def readiness_probe(services: AppServices) -> ReadinessProbe:
    """The app's dependency checks (built once per app, see crowdbake.api.readiness)."""
    bundles = services.settings.bundles_dir
    checks = {
        "database": lambda: _database_state(services),
        # Uploads are staged on local disk whichever store keeps them.
        "blob_store": lambda: _writable(services.blobs.staging_dir),
        "bundles": lambda: _writable(bundles) if os.path.isdir(bundles) else "missing",
        "broker": lambda: _broker_state(services),
    }
    if services.settings.store == "s3":
        checks["bundles"] = lambda: _bucket_state(services.bundles)
    return ReadinessProbe(checks)


@router.get("/ready", response_model=ReadinessPublic, responses=problem_responses(503), summary="Readiness: dependencies usable")
async def ready(request: Request) -> ReadinessPublic:
    checks = await request.app.state.readiness.states()
    failing = {name: state for name, state in checks.items() if state != "ok"}
    if failing:
        raise Problem("not-ready", "not ready: " + "; ".join(f"{name} {state}" for name, state in failing.items()),
                      [{"field": name, "message": state} for name, state in failing.items()])
    return ReadinessPublic(status="ready", checks=checks)
