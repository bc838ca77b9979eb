"""Bundles: names, versions, manifests and files, as the C++ runtime fetches them.

    GET /v1/bundles/{name}/{version}/manifest.json
    GET /v1/bundles/{name}/{version}/files/{path}

`version` may be `latest`, the newest version the caller may read: its manifest and files answer 307
(Temporary Redirect, `no-cache`) to the same path under the concrete version, so a client resolves
`latest` once and never mixes the files of two versions published while it downloads. A published
version never changes, so its responses carry a strong ETag (the sha256 the manifest lists; for the
manifest, its own sha256) and `Cache-Control: immutable`. Range requests (RFC 9110) are answered with
206, and If-None-Match with 304. A bundle is readable by anyone once marked public; a private one by a
key with the read scope that published it (or an admin key, or any key in a shared workspace). To every
other caller, with a key or without, a private bundle answers exactly as a missing one (404): its name
and versions are not revealed by the status.
"""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path as PathParam, Request
from fastapi.responses import FileResponse, Response
from sqlalchemy import or_, select

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
from crowdbake.storage.exports import ExportStore
from crowdbake.storage.models import Bake, Bundle

router = APIRouter(prefix="/v1/bundles", tags=["bundles"])

IMMUTABLE_SECONDS = 31_536_000  # one year, the longest max-age caches honour (RFC 9111 practice)
VERSION_OR_LATEST = r"^([0-9A-Za-z][0-9A-Za-z.+_-]{0,63})$"
NameParam = Annotated[str, PathParam(pattern=NAME_PATTERN)]
VersionParam = Annotated[str, PathParam(pattern=VERSION_OR_LATEST, description="A version, or `latest`.")]
FILE_RESPONSES = problem_responses(404, 416)


def _owner(session, bundle: Bundle) -> str | None:
    """The key that created the bake this bundle was published from (None for one registered by hand)."""
    bake = session.get(Bake, bundle.bake_id) if bundle.bake_id else None
    return bake.created_by if bake is not None else None


def _readable(session, principal: Principal, bundle: Bundle) -> bool:
    """Public bundles, for anyone; private ones, for a key with the read scope that owns them."""
    return bundle.public or (principal.has_any("read") and principal.owns(_owner(session, bundle)))


def _readable_bundles(principal: Principal, columns=(Bundle,)):
    """A select of the bundles `principal` may read (see _readable), as SQL."""
    query = select(*columns).outerjoin(Bake, Bake.id == Bundle.bake_id)
    if principal.has_any("read") and principal.sees_all:
        return query
    if principal.has_any("read") and principal.key_id is not None:
        return query.where(or_(Bundle.public.is_(True), Bake.created_by == principal.key_id))
    return query.where(Bundle.public.is_(True))


def _bundle_or_problem(session, principal: Principal, name: str, version: str) -> Bundle:
    """The bundle, if it exists and the caller may read it; 404 otherwise, the same answer for a private
    bundle as for a missing one. `latest` is the newest version the caller may read."""
    if version == LATEST:
        bundle = session.scalars(
            _readable_bundles(principal).where(Bundle.name == name).order_by(Bundle.published_at.desc(), Bundle.id.desc())
        ).first()
        if bundle is not None:
            return bundle
        raise _not_found(name, version)
    bundle = find_bundle(session, name, version)
    if bundle is None or not _readable(session, principal, bundle):
        raise _not_found(name, version)
    return bundle


def _not_found(name: str, version: str) -> Problem:
    return Problem("not-found", f"no bundle {name}/{version} that this caller may read")


def _latest_redirect(request: Request, bundle: Bundle) -> Response:
    """307 from .../<name>/latest/<rest> to .../<name>/<version>/<rest>.

    `latest` is resolved once, by the request that names it: a client that follows the redirect for the
    manifest and takes the files from the concrete version it landed on never mixes two versions,
    however many are published meanwhile.
    """
    prefix = f"/v1/bundles/{bundle.name}/{LATEST}/"
    location = f"/v1/bundles/{bundle.name}/{bundle.version}/" + request.url.path.split(prefix, 1)[-1]
    if request.url.query:
        location += f"?{request.url.query}"
    return Response(status_code=307, headers={"Location": location, "Content-Location": location, "Cache-Control": "no-cache"})


def _public(bundle: Bundle, exports: ExportStore) -> BundlePublic:
    has_export = exports.has(bundle.name, bundle.version)
    return BundlePublic(
        name=bundle.name, version=bundle.version, manifest_sha256=bundle.manifest_sha256, size=bundle.size,
        file_count=bundle.file_count, public=bundle.public, bake_id=bundle.bake_id,
        published_at=to_utc(bundle.published_at), manifest_url=f"/v1/bundles/{bundle.name}/{bundle.version}/manifest.json",
        export_url=f"/v1/bundles/{bundle.name}/{bundle.version}/export/" if has_export else None,
    )


def _etag_matches(header: str, etag: str) -> bool:
    candidates = [item.strip() for item in header.split(",")]
    return "*" in candidates or any(item.removeprefix("W/").strip('"') == etag for item in candidates)


def _file_headers(sha256: str, bundle: Bundle) -> dict[str, str]:
    """ETag, digest and cache headers of a published file of a concrete version (`latest` redirects
    before a file is served), the same from every store."""
    visibility = "public" if bundle.public else "private"
    return {"ETag": f'"{sha256}"', "X-Content-SHA256": sha256, "Cache-Control": f"{visibility}, max-age={IMMUTABLE_SECONDS}, immutable"}


def _serve_file(request: Request, services, bundle: Bundle, path: str, sha256: str, size: int, media_type: str) -> Response:
    """A file of a published bundle with ETag, cache headers, conditional and range handling: a 307 to
    a presigned URL when the store makes them (an object store: it then sends the bytes), else the bytes."""
    headers = _file_headers(sha256, bundle)
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
    query = _readable_bundles(principal, (Bundle.name,)).distinct().order_by(Bundle.name)
    return BundleNamesPublic(names=list(session.scalars(query).all()))


@router.get("/{name}", response_model=BundleVersionsPublic, responses=problem_responses(404))
def list_versions(name: NameParam, principal: PrincipalDep, services: ServicesDep, session: SessionDep) -> BundleVersionsPublic:
    query = _readable_bundles(principal).where(Bundle.name == name).order_by(Bundle.published_at.desc(), Bundle.id.desc())
    bundles = session.scalars(query).all()
    if not bundles:  # none, or only private ones of another workspace: the same answer
        raise Problem("not-found", f"no bundle named {name!r} that this caller may read")
    return BundleVersionsPublic(name=name, latest=bundles[0].version, versions=[_public(bundle, services.exports) for bundle in bundles])


@router.get("/{name}/{version}", response_model=BundlePublic, responses=problem_responses(404))
def get_bundle(name: NameParam, version: VersionParam, principal: PrincipalDep, services: ServicesDep, session: SessionDep) -> BundlePublic:
    return _public(_bundle_or_problem(session, principal, name, version), services.exports)


@router.patch("/{name}/{version}", response_model=BundlePublic, responses=problem_responses(400, 404), summary="Make a bundle public or private")
def update_bundle(name: NameParam, version: VersionParam, body: BundleUpdate, key: PublishKey, services: ServicesDep, session: SessionDep) -> BundlePublic:
    if version == LATEST:
        raise Problem("validation-error", "name a concrete version, not 'latest'", [{"field": "version", "message": "alias not allowed here"}])
    bundle = find_bundle(session, name, version)
    if bundle is None or not key.owns(_owner(session, bundle)):  # another key's bundle is not this key's to change
        raise Problem("not-found", f"no bundle {name}/{version}")
    bundle.public = body.public
    session.commit()
    return _public(bundle, services.exports)


def _manifest(services, bundle: Bundle) -> PublishedManifest:
    try:
        return services.bundles.manifest(bundle.name, bundle.version)
    except FileNotFoundError:
        raise Problem("internal-error", "the published bundle is missing from the bundle store", status=500) from None


@router.get("/{name}/{version}/manifest.json", responses=FILE_RESPONSES, response_class=FileResponse, summary="The bundle's manifest.json")
@router.head("/{name}/{version}/manifest.json", include_in_schema=False)
def get_manifest(name: NameParam, version: VersionParam, request: Request, principal: PrincipalDep, services: ServicesDep, session: SessionDep) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    if version == LATEST:
        return _latest_redirect(request, bundle)
    published = _manifest(services, bundle)
    return _serve_file(request, services, bundle, MANIFEST, published.sha256, len(published.data), "application/json")


@router.get("/{name}/{version}/files/{path:path}", responses=FILE_RESPONSES, response_class=FileResponse, summary="One file of the bundle, by its manifest path")
@router.head("/{name}/{version}/files/{path:path}", include_in_schema=False)
def get_file(name: NameParam, version: VersionParam, path: str, request: Request, principal: PrincipalDep, services: ServicesDep, session: SessionDep) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    try:
        check_path(path)
    except FormatError:
        raise Problem("not-found", f"{path!r} is not a bundle path") from None
    if version == LATEST:
        return _latest_redirect(request, bundle)
    published = _manifest(services, bundle)
    entry = published.files.get(path)
    if entry is None:
        raise Problem("not-found", f"{name}/{bundle.version} has no file {path!r}")
    return _serve_file(request, services, bundle, path, entry["sha256"], int(entry["size"]), entry["media_type"])
