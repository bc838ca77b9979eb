"""Published exports (crowdbake.storage.exports) over REST, and the three.js crowd preview page:

    GET /v1/bundles/{name}/{version}/export/{path}   one file of the bundle's engine export
    GET /v1/bundles/{name}/{version}/export.zip      the whole export in one zip
    GET /ui/preview/{file}                           the preview page, its scripts and the three.js
                                                     and ktx-parse files they import, nothing else

Export files follow the bundle's rules: readable with a key that has the read scope or by anyone once
the bundle is public, a strong ETag (the file's sha256 from the export's index.json), `immutable`
caching, Range and If-None-Match; `latest` answers 307 to the concrete version, as for bundle files. A bundle baked with `export: false` has no export: 404 saying so.
"""
from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, Response

from crowdbake.api.deps import PrincipalDep, ServicesDep, SessionDep
from crowdbake.api.problems import Problem
from crowdbake.api.bundle_files import bundle_file_redirect, bundle_file_response
from crowdbake.api.routes.bundles import FILE_RESPONSES, NameParam, VersionParam, _bundle_or_problem, _etag_matches, _file_headers, _latest_redirect
from crowdbake.storage.bundles import LATEST
from crowdbake.storage.exports import FILES_FOLDER, ZIP_NAME
from crowdbake.storage.models import Bundle

router = APIRouter(prefix="/v1/bundles", tags=["bundles"])
preview_router = APIRouter(include_in_schema=False)

PREVIEW_DIR = Path(__file__).resolve().parent.parent / "static" / "preview"
# The page, its two modules, and exactly the files of its npm packages that they import (through the
# page's import map): three's module build, GLTFLoader and the two utils it imports, ktx-parse.
# services/tests/test_export_rest.py walks the imports and checks this list is complete.
PREVIEW_FILES = {
    "index.html": "text/html; charset=utf-8",
    "preview.js": "text/javascript",
    "crowd-materials.js": "text/javascript",
    "node_modules/three/build/three.module.js": "text/javascript",
    "node_modules/three/build/three.core.js": "text/javascript",
    "node_modules/three/examples/jsm/loaders/GLTFLoader.js": "text/javascript",
    "node_modules/three/examples/jsm/utils/BufferGeometryUtils.js": "text/javascript",
    "node_modules/three/examples/jsm/utils/SkeletonUtils.js": "text/javascript",
    "node_modules/ktx-parse/dist/index.mjs": "text/javascript",
    "node_modules/three/examples/jsm/libs/zstddec.module.js": "text/javascript",
}


def _import_map_hash() -> str:
    """CSP source for the page's inline import map (its sha256), so no other inline script runs."""
    html = (PREVIEW_DIR / "index.html").read_text()
    match = re.search(r'<script type="importmap">(.*?)</script>', html, re.S)
    digest = hashlib.sha256(match.group(1).encode()).digest() if match else b""
    return f"'sha256-{base64.b64encode(digest).decode()}'"


# The page runs its own modules and import map, talks only to this server, and the glTF loader decodes
# the embedded PNGs through blob: URLs; three.js's zstd decoder for the KTX2 levels is WebAssembly.
PREVIEW_CSP = ("default-src 'self'; script-src 'self' 'wasm-unsafe-eval' {import_map}; style-src 'self' 'unsafe-inline'; img-src 'self' blob: data:; "
               "connect-src 'self' blob: data:; object-src 'none'; base-uri 'none'; frame-ancestors 'none'")


def _export_index(services, bundle: Bundle) -> dict:
    try:
        return services.exports.index(bundle.name, bundle.version)
    except FileNotFoundError:
        raise Problem("not-found", f"{bundle.name}/{bundle.version} was published without an export (bake parameter export=false)") from None


@router.get("/{name}/{version}/export/{path:path}", responses=FILE_RESPONSES, response_class=FileResponse,
            summary="One file of the bundle's engine export (export.json, .glb, .ktx2, VATs, shaders)")
@router.head("/{name}/{version}/export/{path:path}", include_in_schema=False)
def get_export_file(name: NameParam, version: VersionParam, path: str, request: Request, principal: PrincipalDep,
                    services: ServicesDep, session: SessionDep) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    index = _export_index(services, bundle)
    if version == LATEST:
        return _latest_redirect(request, bundle)
    entry = index["files"].get(path)  # only the listed paths: nothing else under the folder is reachable
    if entry is None:
        raise Problem("not-found", f"the export of {bundle.name}/{bundle.version} has no file {path!r} (export.json lists them)")
    return _serve_export_file(request, services, bundle, f"{FILES_FOLDER}/{path}", entry)


@router.get("/{name}/{version}/export.zip", responses=FILE_RESPONSES, response_class=FileResponse,
            summary="The bundle's engine export as one zip (<name>-<version>/export.json and its files)")
@router.head("/{name}/{version}/export.zip", include_in_schema=False)
def get_export_zip(name: NameParam, version: VersionParam, request: Request, principal: PrincipalDep,
                   services: ServicesDep, session: SessionDep) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    entry = _export_index(services, bundle)["zip"]
    if version == LATEST:
        return _latest_redirect(request, bundle)
    response = _serve_export_file(request, services, bundle, ZIP_NAME, entry)
    response.headers["Content-Disposition"] = f'attachment; filename="{bundle.name}-{bundle.version}-export.zip"'
    return response


def _serve_export_file(request: Request, services, bundle: Bundle, path: str, entry: dict) -> Response:
    """An export file (`export/<path>` or `export.zip` of its home) with the bundle files' ETag, cache,
    conditional and range handling, from whichever store holds it (a presigned redirect where enabled)."""
    headers = _file_headers(entry["sha256"], bundle)
    if_none_match = request.headers.get("if-none-match")
    if if_none_match and _etag_matches(if_none_match, entry["sha256"]):
        return Response(status_code=304, headers=headers)
    store = services.exports
    if services.settings.s3_redirect_downloads:
        redirect = bundle_file_redirect(store, bundle.name, bundle.version, path, entry["media_type"], headers, services.settings.s3_presign_seconds)
        if redirect is not None:
            return redirect
    return bundle_file_response(request, store, bundle.name, bundle.version, path, int(entry["size"]), entry["media_type"], headers)


@preview_router.get("/ui/preview")
def preview_folder() -> Response:
    return Response(status_code=307, headers={"Location": "/ui/preview/index.html"})


@preview_router.get("/ui/preview/{path:path}")
def preview_file(path: str) -> FileResponse:
    if path == "":
        path = "index.html"
    media_type = PREVIEW_FILES.get(path)
    if media_type is None or not (PREVIEW_DIR / path).is_file():
        hint = " (run `npm ci` in the preview folder: scripts/setup.sh does)" if path.startswith("node_modules/") and media_type else ""
        raise Problem("not-found", f"no preview file {path!r}{hint}")
    headers = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}
    if path == "index.html":
        headers["Content-Security-Policy"] = PREVIEW_CSP.format(import_map=_import_map_hash())
    return FileResponse(PREVIEW_DIR / path, media_type=media_type, headers=headers)
