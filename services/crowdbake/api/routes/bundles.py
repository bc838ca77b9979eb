"""Bundles: names, versions, manifests and files, as the C++ runtime fetches them.

    GET /v1/bundles/{name}/{version}/manifest.json
    GET /v1/bundles/{name}/{version}/files/{path}

`version` may be `latest`, the most recently published version. A published version never changes, so
its responses carry a strong ETag (the sha256 the manifest lists; for the manifest, its own sha256) and
`Cache-Control: immutable`; `latest` responses must be revalidated (`no-cache`) and name the concrete
version in Content-Location. Range requests (RFC 9110) are answered with 206, and If-None-Match with
304. A bundle is readable with a key that has the read scope, or by anyone once marked public.
"""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path as PathParam, Request
from fastapi.responses import FileResponse, Response
from sqlalchemy import select

from crowdbake.api.bundle_files import bundle_file_redirect, bundle_file_response
from crowdbake.api.deps import PrincipalDep, PublishKey, ServicesDep, SessionDep, Principal
from crowdbake.api.problems import Problem
from crowdbake.api.schemas import (
    NAME_PATTERN,
    BundleNamesPublic,
    BundlePublic,
    BundleUpdate,
    BundleVersionsPublic,
    problem_responses,
)
from crowdbake.formats.bundle import check_path
from crowdbake.formats.errors import FormatError
from crowdbake.storage.records import to_utc
from crowdbake.storage.bundle_store import MANIFEST
from crowdbake.storage.bundles import LATEST, PublishedManifest, find_bundle
from crowdbake.storage.models import Bundle

router = APIRouter(prefix="/v1/bundles", tags=["bundles"])

IMMUTABLE_SECONDS = 31_536_000  # one year, the longest max-age caches honour (RFC 9111 practice)
VERSION_OR_LATEST = r"^([0-9A-Za-z][0-9A-Za-z.+_-]{0,63})$"
NameParam = Annotated[str, PathParam(pattern=NAME_PATTERN)]
VersionParam = Annotated[str, PathParam(pattern=VERSION_OR_LATEST, description="A version, or `latest`.")]
FILE_RESPONSES = problem_responses(404, 416)


def _visible(principal: Principal, bundle: Bundle) -> bool:
    return bundle.public or principal.has_any("read")


def _bundle_or_problem(session, principal: Principal, name: str, version: str) -> Bundle:
    """The bundle, if it exists and the caller may read it (anonymous callers of a private bundle get
    401 so they know a key would help; keys without the read scope get 404, revealing nothing)."""
    bundle = find_bundle(session, name, version)
    if version == LATEST and bundle is not None and not _visible(principal, bundle):
        # 'latest' for an anonymous caller is the newest *public* version, if there is one.
        bundle = session.scalars(
            select(Bundle).where(Bundle.name == name, Bundle.public.is_(True)).order_by(Bundle.published_at.desc(), Bundle.id.desc())
        ).first() or bundle
    if bundle is None:
        raise Problem("not-found", f"no bundle {name}/{version}")
    if not _visible(principal, bundle):
        if principal.key_id is None:
            raise Problem("unauthorized", f"{name}/{version} is not public; send a key with the read scope", headers={"WWW-Authenticate": "Bearer"})
        raise Problem("not-found", f"no bundle {name}/{version}")
    return bundle


def _public(bundle: Bundle) -> BundlePublic:
    return BundlePublic(
        name=bundle.name, version=bundle.version, manifest_sha256=bundle.manifest_sha256, size=bundle.size,
        file_count=bundle.file_count, public=bundle.public, bake_id=bundle.bake_id,
        published_at=to_utc(bundle.published_at), manifest_url=f"/v1/bundles/{bundle.name}/{bundle.version}/manifest.json",
    )


def _etag_matches(header: str, etag: str) -> bool:
    candidates = [item.strip() for item in header.split(",")]
    return "*" in candidates or any(item.removeprefix("W/").strip('"') == etag for item in candidates)


def _file_headers(request: Request, sha256: str, bundle: Bundle, requested_version: str) -> dict[str, str]:
    """ETag, digest and cache headers of a published file (the same from every store)."""
    headers = {"ETag": f'"{sha256}"', "X-Content-SHA256": sha256}
    if requested_version == LATEST:
        headers["Cache-Control"] = "no-cache"
        prefix = f"/v1/bundles/{bundle.name}/{LATEST}/"
        headers["Content-Location"] = f"/v1/bundles/{bundle.name}/{bundle.version}/" + request.url.path.split(prefix, 1)[-1]
    else:
        visibility = "public" if bundle.public else "private"
        headers["Cache-Control"] = f"{visibility}, max-age={IMMUTABLE_SECONDS}, immutable"
    return headers


def _serve_file(request: Request, services, bundle: Bundle, path: str, sha256: str, size: int, media_type: str,
                requested_version: str) -> Response:
    """A file of a published bundle with ETag, cache headers, conditional and range handling: a 307 to
    a presigned URL when the store makes them (an object store: it then sends the bytes), else the bytes."""
    headers = _file_headers(request, sha256, bundle, requested_version)
    if_none_match = request.headers.get("if-none-match")
    if if_none_match and _etag_matches(if_none_match, sha256):
        return Response(status_code=304, headers=headers)
    store = services.bundles
    if services.settings.s3_redirect_downloads:
        redirect = bundle_file_redirect(store, bundle.name, bundle.version, path, media_type, headers, services.settings.s3_presign_seconds)
        if redirect is not None:
            return redirect
    return bundle_file_response(request, store, bundle.name, bundle.version, path, size, media_type, headers)


@router.get("", response_model=BundleNamesPublic, responses=problem_responses())
def list_bundle_names(principal: PrincipalDep, session: SessionDep) -> BundleNamesPublic:
    query = select(Bundle.name).distinct().order_by(Bundle.name)
    if not principal.has_any("read"):
        query = query.where(Bundle.public.is_(True))
    return BundleNamesPublic(names=list(session.scalars(query).all()))


@router.get("/{name}", response_model=BundleVersionsPublic, responses=problem_responses(404))
def list_versions(name: NameParam, principal: PrincipalDep, session: SessionDep) -> BundleVersionsPublic:
    query = select(Bundle).where(Bundle.name == name).order_by(Bundle.published_at.desc(), Bundle.id.desc())
    if not principal.has_any("read"):
        query = query.where(Bundle.public.is_(True))
    bundles = session.scalars(query).all()
    if not bundles:
        if principal.key_id is None and find_bundle(session, name, LATEST) is not None:
            raise Problem("unauthorized", f"bundle {name} is not public; send a key with the read scope", headers={"WWW-Authenticate": "Bearer"})
        raise Problem("not-found", f"no bundle named {name!r}")
    return BundleVersionsPublic(name=name, latest=bundles[0].version, versions=[_public(bundle) for bundle in bundles])


@router.get("/{name}/{version}", response_model=BundlePublic, responses=problem_responses(404))
def get_bundle(name: NameParam, version: VersionParam, principal: PrincipalDep, session: SessionDep) -> BundlePublic:
    return _public(_bundle_or_problem(session, principal, name, version))


@router.patch("/{name}/{version}", response_model=BundlePublic, responses=problem_responses(400, 404), summary="Make a bundle public or private")
def update_bundle(name: NameParam, version: VersionParam, body: BundleUpdate, key: PublishKey, session: SessionDep) -> BundlePublic:
    if version == LATEST:
        raise Problem("validation-error", "name a concrete version, not 'latest'", [{"field": "version", "message": "alias not allowed here"}])
    bundle = find_bundle(session, name, version)
    if bundle is None:
        raise Problem("not-found", f"no bundle {name}/{version}")
    bundle.public = body.public
    session.commit()
    return _public(bundle)


def _manifest(services, bundle: Bundle) -> PublishedManifest:
    try:
        return services.bundles.manifest(bundle.name, bundle.version)
    except FileNotFoundError:
        raise Problem("internal-error", "the published bundle is missing from the bundle store", status=500) from None


@router.get("/{name}/{version}/manifest.json", responses=FILE_RESPONSES, response_class=FileResponse, summary="The bundle's manifest.json")
@router.head("/{name}/{version}/manifest.json", include_in_schema=False)
def get_manifest(name: NameParam, version: VersionParam, request: Request, principal: PrincipalDep, services: ServicesDep, session: SessionDep) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    published = _manifest(services, bundle)
    return _serve_file(request, services, bundle, MANIFEST, published.sha256, len(published.data), "application/json", version)


@router.get("/{name}/{version}/files/{path:path}", responses=FILE_RESPONSES, response_class=FileResponse, summary="One file of the bundle, by its manifest path")
@router.head("/{name}/{version}/files/{path:path}", include_in_schema=False)
def get_file(name: NameParam, version: VersionParam, path: str, request: Request, principal: PrincipalDep, services: ServicesDep, session: SessionDep) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    try:
        check_path(path)
    except FormatError:
        raise Problem("not-found", f"{path!r} is not a bundle path") from None
    published = _manifest(services, bundle)
    entry = published.files.get(path)
    if entry is None:
        raise Problem("not-found", f"{name}/{bundle.version} has no file {path!r}")
    return _serve_file(request, services, bundle, path, entry["sha256"], int(entry["size"]), entry["media_type"], version)
