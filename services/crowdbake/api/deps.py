"""Dependencies of the routes, as named Annotated types: settings, a database session, the blob and
bundle stores, the Celery app that enqueues stages, and the API key with the scopes an operation needs."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Callable, Iterator

from celery import Celery
from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker

from crowdbake.api.problems import Problem
from crowdbake.settings import Settings
from crowdbake.storage.blobs import BlobStore
from crowdbake.storage.bundle_store import BundleStore
from crowdbake.storage.exports import ExportStore
from crowdbake.storage.keys import verify_api_key
from crowdbake.storage.models import ApiKey


@dataclass
class AppServices:
    """Everything the app holds for its lifetime (built once by create_app)."""

    settings: Settings
    sessions: sessionmaker[Session]
    blobs: BlobStore
    bundles: BundleStore
    exports: ExportStore
    celery: Celery


async def get_services(request: Request) -> AppServices:
    # async: resolved on the event loop, so routes that need nothing else (health, readiness) never wait
    # for a thread of the request pool.
    return request.app.state.services


ServicesDep = Annotated[AppServices, Depends(get_services)]


def get_settings_dep(services: ServicesDep) -> Settings:
    return services.settings


def get_session(services: ServicesDep) -> Iterator[Session]:
    session = services.sessions()
    session.info["settings"] = services.settings  # for helpers that only get the session (path redaction)
    try:
        yield session
    finally:
        session.close()


def get_blobs(services: ServicesDep) -> BlobStore:
    return services.blobs


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
SessionDep = Annotated[Session, Depends(get_session)]
BlobsDep = Annotated[BlobStore, Depends(get_blobs)]

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="An API key (crowdbake keys create).")
_bearer = HTTPBearer(auto_error=False, description="An API key as a bearer token.")


ADMIN_SCOPE = "admin"


@dataclass(frozen=True)
class Principal:
    """Who is calling: a key id and its scopes, or anonymous (key_id None, no scopes).

    Ownership: a key sees and changes only the assets, bakes (with their logs) and bundles it created,
    plus public bundles for reading. `sees_all` lifts that for a key with the admin scope, or for every
    key when the service runs as one shared workspace (CROWDBAKE_SHARED_WORKSPACE); the scopes still
    decide which operations a key may call.
    """

    key_id: str | None
    scopes: frozenset[str]
    sees_all: bool = False

    def has_any(self, *scopes: str) -> bool:
        return bool(self.scopes & set(scopes))

    def owns(self, created_by: str | None) -> bool:
        """Whether a resource recorded as created by `created_by` is this caller's to see and change."""
        return self.sees_all or (self.key_id is not None and created_by == self.key_id)

    def only_own(self, query, created_by_column):
        """`query` restricted to rows this caller owns (unchanged for an admin or a shared workspace)."""
        return query if self.sees_all else query.where(created_by_column == self.key_id)


ANONYMOUS = Principal(None, frozenset())


def get_principal(
    session: SessionDep, services: ServicesDep,
    header_key: Annotated[str | None, Security(_api_key_header)] = None,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)] = None,
) -> Principal:
    """The caller's key, if one was sent; a key that was sent but does not verify is a 401."""
    raw = header_key or (bearer.credentials if bearer else None)
    if not raw:
        return ANONYMOUS
    record: ApiKey | None = verify_api_key(session, raw)
    if record is None:
        raise Problem("unauthorized", "the API key is unknown or revoked", headers={"WWW-Authenticate": "Bearer"})
    scopes = record.scope_set
    return Principal(record.id, scopes, sees_all=ADMIN_SCOPE in scopes or services.settings.shared_workspace)


PrincipalDep = Annotated[Principal, Depends(get_principal)]


def require_scope(*scopes: str) -> Callable[[Principal], Principal]:
    """A dependency that admits keys holding any of `scopes` (401 without a key, 403 without the scope)."""

    def dependency(principal: PrincipalDep) -> Principal:
        if principal.key_id is None:
            raise Problem("unauthorized", f"this operation needs an API key with the {' or '.join(scopes)} scope", headers={"WWW-Authenticate": "Bearer"})
        if not principal.has_any(*scopes):
            raise Problem("forbidden", f"the API key lacks the {' or '.join(scopes)} scope")
        return principal

    return dependency


UploadKey = Annotated[Principal, Depends(require_scope("upload"))]
AssetReadKey = Annotated[Principal, Depends(require_scope("upload", "bake"))]
BakeKey = Annotated[Principal, Depends(require_scope("bake"))]
PublishKey = Annotated[Principal, Depends(require_scope("publish"))]
