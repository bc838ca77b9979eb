"""The FastAPI application: `create_app(settings)` builds it (uvicorn: --factory crowdbake.api.app:create_app).

Building the app prepares its state once: folders, the database (migrated to the newest schema), the
bootstrap key if one is configured, the blob and bundle stores (crowdbake.storage.store) and the Celery app used to enqueue stages.
The OpenAPI document is at /openapi.json, interactive docs at /docs and /redoc: Swagger UI and ReDoc
served from the files the fastapi-offline package ships, so they work with no internet. Each operation's
id is `<tag>-<function>` (`assets-upload_character`), the names generated clients give their methods.
"""
from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from importlib.resources import files

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from pydantic import ValidationError

from crowdbake import __version__
from crowdbake.api import problems
from crowdbake.api.deps import AppServices
from crowdbake.api.problems import PROBLEM_TYPES, Problem, problem_type_uri
from crowdbake.api.request_bodies import BodyGate
from crowdbake.api.slow_clients import MinimumBodyRate
from crowdbake.api.schemas import Problem as ProblemDocument
from crowdbake.api.routes import assets, bake_check, bakes, bundles, exports, health, metrics, params, web
from crowdbake.jobs.celery_app import make_celery
from crowdbake.jobs.sweeper import Dispatcher, Sweeper
from crowdbake.metrics import HttpMetrics, MetricsMiddleware
from crowdbake.settings import Settings, get_settings, redact_url
from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
from crowdbake.storage.keys import ensure_bootstrap_key
from crowdbake.storage.store import open_store

logger = logging.getLogger(__name__)

DESCRIPTION = """Bakes clothed characters into crowd bundles (Dobbyn et al. 2006: cyclical cloth, poses with two
LODs, UV-mapped impostors) and serves the published bundles.

Upload assets, start a bake, follow it, then fetch `/v1/bundles/{name}/{version}/manifest.json` and its files.
Authenticate with `Authorization: Bearer <key>` (or `X-API-Key`); keys carry the scopes upload, bake, publish, read.
Errors are RFC 9457 problem documents (`application/problem+json`)."""


def build_services(settings: Settings) -> AppServices:
    """Folders, migrated database, bootstrap key, blob and bundle stores and Celery app for `settings`."""
    settings.ensure_dirs()
    engine = make_engine(settings.database_url)
    if settings.migrate_on_start:
        migrate(engine)
    sessions = make_sessionmaker(engine)
    if settings.bootstrap_key is not None:
        with session_scope(sessions) as session:
            ensure_bootstrap_key(session, settings.bootstrap_key.get_secret_value())
    stores = open_store(settings)
    return AppServices(settings=settings, sessions=sessions, blobs=stores.blobs, bundles=stores.bundles, exports=stores.exports, celery=make_celery(settings))


# Swagger UI and ReDoc bundles as a pip package ships them (fastapi-offline, pinned in requirements.txt).
DOCS_ASSETS_DIR = files("fastapi_offline") / "static"
DOCS_ASSETS_URL = "/docs/assets"


def operation_id(route: APIRoute) -> str:
    """`<first tag>-<route function>`, e.g. `assets-upload_character`: short, stable, unique per route
    (tests/test_api_docs.py checks), and what generated clients name their methods after."""
    return f"{route.tags[0]}-{route.name}" if route.tags else route.name


def add_docs_routes(app: FastAPI) -> None:
    """/docs (Swagger UI) and /redoc (ReDoc) from packaged files: nothing is loaded from another host."""
    app.mount(DOCS_ASSETS_URL, StaticFiles(directory=str(DOCS_ASSETS_DIR)), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        # validatorUrl null: Swagger UI would otherwise send the document to an online validator.
        return get_swagger_ui_html(openapi_url=app.openapi_url, title=f"{app.title} API", swagger_js_url=f"{DOCS_ASSETS_URL}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{DOCS_ASSETS_URL}/swagger-ui.css", swagger_favicon_url=f"{DOCS_ASSETS_URL}/favicon.png",
                                   swagger_ui_parameters={"validatorUrl": None})

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url=app.openapi_url, title=f"{app.title} API", redoc_js_url=f"{DOCS_ASSETS_URL}/redoc.standalone.js",
                              redoc_favicon_url=f"{DOCS_ASSETS_URL}/favicon.png", with_google_fonts=False)


@asynccontextmanager
async def lifespan(app: FastAPI):
    """The sweeper (crowdbake.jobs.sweeper) runs while the server serves."""
    services = app.state.services
    sweeper = Sweeper(services.sessions, services.celery, services.settings).start()
    try:
        yield
    finally:
        sweeper.stop()


def create_app(settings: Settings | None = None) -> FastAPI:
    if settings is None:
        try:
            settings = get_settings()
        except ValidationError as error:
            # A default or missing secret, a malformed number: say which, and do not start.
            reasons = "; ".join(f"{'.'.join(map(str, item['loc'])) or 'settings'}: {item['msg']}" for item in error.errors())
            raise SystemExit(f"crowdbake: refusing to start: {reasons}") from None
    app = FastAPI(
        title="crowdbake",
        version=__version__,
        description=DESCRIPTION,
        docs_url=None,  # add_docs_routes serves them from packaged files instead of a CDN
        redoc_url=None,
        generate_unique_id_function=operation_id,
        lifespan=lifespan,
        openapi_tags=[
            {"name": "assets", "description": "Upload characters, cloth caches and textures (validated, deduplicated by sha256)."},
            {"name": "bakes", "description": "Bake jobs: state and progress per stage, errors, log, cancel, retry."},
            {"name": "bundles", "description": "Published bundles: manifests and files with strong ETags and Range support."},
            {"name": "health", "description": "Liveness, readiness and Prometheus metrics."},
        ],
    )
    app.state.services = build_services(settings)
    app.state.readiness = health.readiness_probe(app.state.services)
    app.state.dispatcher = Dispatcher(app.state.services.sessions, app.state.services.celery, settings)
    problems.install(app)
    add_docs_routes(app)
    for module in (assets, bake_check, bakes, bundles, exports, health, metrics, params):
        app.include_router(module.router)
    for router in web.routers:  # the web page, the cycle report and atlas previews it shows
        app.include_router(router)
    app.include_router(exports.preview_router)  # the three.js crowd preview the page links to
    # Each body gets its route's limit, and is read only once its key verifies (crowdbake.api.request_bodies).
    app.add_middleware(BodyGate, sessions=app.state.services.sessions, upload_prefix=assets.router.prefix, max_upload_bytes=settings.max_upload_bytes)
    app.state.metrics = HttpMetrics(app.state.services.sessions)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    # Outermost: every read of a request body has a deadline (crowdbake.api.slow_clients).
    app.add_middleware(MinimumBodyRate, min_bytes_per_s=settings.body_min_bytes_per_s, grace_s=settings.body_grace_s, max_s=settings.body_max_seconds)

    @app.get("/problems/{slug}", tags=["health"], summary="What a problem type means",
             responses={404: {"model": ProblemDocument, "content": {"application/problem+json": {}}, "description": "No such problem type"}})
    def describe_problem(slug: str) -> dict:
        if slug not in PROBLEM_TYPES:
            raise Problem("not-found", f"no problem type {slug!r}")
        status, title, description = PROBLEM_TYPES[slug]
        return {"type": problem_type_uri(slug), "title": title, "status": status, "description": description}

    where = (f"s3 bucket {settings.s3_bucket} prefix {settings.s3_prefix!r}" if settings.store == "s3"
             else f"blobs {settings.blob_dir}, bundles {settings.bundles_dir}")
    logger.info("crowdbake API ready: database %s, %s, broker %s", redact_url(settings.database_url), where, redact_url(settings.broker_url))
    return app
