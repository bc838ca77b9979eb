"""The web page of the service, and the two things it shows that the JSON API does not have:

    GET /ui                                           the page (static HTML + vanilla JS from api/static/)
    GET /v1/bakes/{id}/cycle/{path}                   the cycle search's report.html, plots and cycle.json
    GET /v1/bundles/{name}/{version}/preview/{map}    an impostor atlas layer as PNG (normal, uv, detail)
    GET /v1/bundles/{name}/{version}/archive.zip      the whole bundle as one zip, for the page's Download

The page needs no build step and loads nothing from elsewhere: it polls /v1/bakes and /v1/bundles with
the key the user typed (kept in the tab's sessionStorage) and fetches the report and the previews with
the same key. The page itself is public; everything it shows is behind the usual scopes (bake for
jobs and their reports, read for private bundles).

The report is the file the cycle stage wrote into the bake's work folder (crowdbake.stages.cycle: work/cycle/).
Previews decode one layer of a published bundle's CBTX atlas: the UV map's 16-bit u and v become red
and green, the normal map's RGB is (n + 1) / 2 as stored, the detail map is the diffuse variation 0
as baked; BC1/BC2 layers are decoded with crowdbake.bake.compression. Texels the character does not
cover (UV alpha 0) are transparent in all three.
"""
from __future__ import annotations

import hashlib
import io
import os
import re
import tempfile
import zipfile
from pathlib import Path
from typing import Annotated, Callable, Literal

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, RedirectResponse, Response, StreamingResponse
from starlette.background import BackgroundTask

from crowdbake.api.bundle_files import stream_chunks
from crowdbake.bake.atlas import AtlasLayout
from crowdbake.api.deps import BakeKey, PrincipalDep, ServicesDep, SessionDep
from crowdbake.api.problems import Problem
from crowdbake.api.routes.bundles import IMMUTABLE_SECONDS, NameParam, VersionParam, _bundle_or_problem, _manifest
from crowdbake.api.schemas import problem_responses
from crowdbake.formats.binary import read_texture_layer
from crowdbake.storage import records, work_outputs
from crowdbake.storage.bundle_store import BundleStore
from crowdbake.storage.bundles import LATEST
from crowdbake.storage.models import Bake

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
# Files of the page: plain names only, so a request can never leave the static folder.
STATIC_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]*\.(js|css|svg|png|ico)$")
STATIC_TYPES = {".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml", ".png": "image/png", ".ico": "image/x-icon"}
# The page runs only its own script, talks only to this server, and shows images it fetched as blobs
# or data URLs; the cycle report in its frame brings an inline <style>.
PAGE_CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' blob: data:; "
            "connect-src 'self'; frame-src 'self' blob: data:; object-src 'none'; base-uri 'none'; frame-ancestors 'none'")
# A report opened on its own runs nothing and loads only its plots.
REPORT_CSP = "default-src 'none'; img-src 'self'; style-src 'unsafe-inline'; sandbox"

# What the cycle stage writes (crowdbake.stages.cycle_job.write_cycle_outputs): report.html, cycle.json,
# PNG plots, and the edge images under edges/. Anything else in the work folder stays private.
CYCLE_FILE = re.compile(r"^(report\.html|cycle\.json|(edges/)?[A-Za-z0-9][A-Za-z0-9_-]*\.png)$")
CYCLE_TYPES = {".html": "text/html; charset=utf-8", ".png": "image/png", ".json": "application/json"}

# Material index m of the UV map's blue channel is shown as blue 64·m (clipped), so materials differ.
MATERIAL_BLUE_STEP = 64

page_router = APIRouter(include_in_schema=False)
bake_files_router = APIRouter(prefix="/v1/bakes", tags=["bakes"])
previews_router = APIRouter(prefix="/v1/bundles", tags=["bundles"])
routers = (page_router, bake_files_router, previews_router)


# ------------------------------------------------------------------------------------------ page


@page_router.get("/")
def root() -> RedirectResponse:
    return RedirectResponse("/ui", status_code=307)


@page_router.get("/ui")
@page_router.get("/ui/")
def page() -> FileResponse:
    return FileResponse(STATIC_DIR / "index.html", media_type="text/html; charset=utf-8",
                        headers={"Content-Security-Policy": PAGE_CSP, "Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"})


@page_router.get("/ui/static/{name}")
def static_file(name: str) -> FileResponse:
    if not STATIC_NAME.match(name) or not (STATIC_DIR / name).is_file():
        raise Problem("not-found", f"no page file {name!r}")
    return FileResponse(STATIC_DIR / name, media_type=STATIC_TYPES[Path(name).suffix],
                        headers={"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"})


# ---------------------------------------------------------------------------------- cycle report


@bake_files_router.get(
    "/{bake_id}/cycle/{path:path}", response_class=FileResponse, responses=problem_responses(404),
    summary="The cycle search's report of a bake (report.html, its PNG plots, cycle.json)",
)
def get_cycle_file(bake_id: str, path: str, key: BakeKey, services: ServicesDep, session: SessionDep) -> Response:
    bake = records.by_id(session, Bake, bake_id)
    if bake is None or not key.owns(bake.created_by):
        raise Problem("not-found", f"no bake {bake_id!r}")
    if not CYCLE_FILE.match(path):
        raise Problem("not-found", f"{path!r} is not a file of the cycle report")
    headers = {"Cache-Control": "private, no-cache", "X-Content-Type-Options": "nosniff"}
    suffix = Path(path).suffix
    if suffix == ".html":
        headers["Content-Security-Policy"] = REPORT_CSP
    cycle = next((row for row in bake.stages if row.stage == "cycle"), None)
    why = "the cycle stage has not finished" if cycle is None or cycle.state != "succeeded" else "no such file in the cycle report"
    outputs = (cycle.result or {}).get("outputs") if cycle is not None else None
    if outputs:
        # The cycle stage stores its files as blobs: work folders are private to each worker machine, and
        # deleted once the bundle is published.
        entry = work_outputs.read_listing(services.blobs, outputs).get(f"cycle/{path}")
        if entry is None:
            raise Problem("not-found", f"bake {bake_id}: {why} ({path})")
        body = services.blobs.open(entry["sha256"])
        return StreamingResponse(stream_chunks(body), media_type=CYCLE_TYPES[suffix], headers={**headers, "Content-Length": str(entry["size"])})
    # The work folder is named by the input key (crowdbake.jobs.tasks.work_dir); the cycle stage writes cycle/.
    folder = (Path(services.settings.work_dir) / bake.input_key / "cycle").resolve()
    file_path = (folder / path).resolve()
    if not file_path.is_relative_to(folder) or not file_path.is_file():
        raise Problem("not-found", f"bake {bake_id}: {why} ({path})")
    return FileResponse(file_path, media_type=CYCLE_TYPES[suffix], headers=headers)


# --------------------------------------------------------------------------------- atlas preview


def decode_layer(data: bytes, pixel_format: str, width: int, height: int) -> np.ndarray:
    """One CBTX layer as (height, width, 4) texels: uint8 for rgba8/bc1/bc2/bc5, uint16 for rgba16."""
    from crowdbake.bake.compression import decode

    return np.asarray(decode(data, pixel_format, width, height))


def decode_uv_layer(data: bytes, pixel_format: str, width: int, height: int) -> np.ndarray:
    """One UV-map layer (rgba16, uv32 or uvblock, SPEC.md) as (height, width, 4) uint16 in rgba16's layout
    (u·65535, v·65535, material, coverage 65535/0), so one preview serves both formats."""
    if pixel_format == "rgba16":
        return decode_layer(data, pixel_format, width, height)
    from crowdbake.formats.texel_codecs import unpack_uv32, unpack_uvblock

    if pixel_format == "uvblock":
        u, v, material, covered = unpack_uvblock(data, width, height)
    elif pixel_format == "uv32":
        u, v, material, covered = unpack_uv32(np.frombuffer(data, "<u4").reshape(height, width))
    else:
        raise ValueError(f"a UV map must be rgba16, uv32 or uvblock, not {pixel_format}")
    uv = np.zeros((height, width, 4), dtype=np.uint16)
    uv[..., 0] = np.where(covered, np.rint(u * 65535.0), 0)
    uv[..., 1] = np.where(covered, np.rint(v * 65535.0), 0)
    uv[..., 2] = np.where(covered, material, 0)
    uv[..., 3] = np.where(covered, 65535, 0)
    return uv


def uv_preview(uv: np.ndarray) -> np.ndarray:
    """(H, W, 4) uint16 UV map (SPEC.md: R = u·65535, G = v·65535, B = material, A = coverage) ->
    (H, W, 4) uint8 picture: red u, green v, blue 64·material, opaque where covered, transparent elsewhere."""
    uv = np.asarray(uv)
    if uv.ndim != 3 or uv.shape[2] != 4 or uv.dtype != np.uint16:
        raise ValueError(f"uv_preview: expected (H, W, 4) uint16, got {uv.shape} {uv.dtype}")
    picture = np.zeros(uv.shape, dtype=np.uint8)
    picture[..., 0] = uv[..., 0] >> 8
    picture[..., 1] = uv[..., 1] >> 8
    picture[..., 2] = np.minimum(uv[..., 2].astype(np.uint32) * MATERIAL_BLUE_STEP, 255).astype(np.uint8)
    picture[..., 3] = np.where(uv[..., 3] > 0, 255, 0).astype(np.uint8)
    return picture


def colour_preview(texels: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """(H, W, 4) uint8 normal or detail texels -> the same RGB, opaque where `covered` (H, W) bool.

    The detail map's alpha is a region code, not coverage (SPEC.md), so coverage comes from the UV map."""
    texels = np.asarray(texels)
    if texels.ndim != 3 or texels.shape[2] != 4 or texels.dtype != np.uint8 or covered.shape != texels.shape[:2]:
        raise ValueError(f"colour_preview: expected (H, W, 4) uint8 and (H, W) coverage, got {texels.shape} {texels.dtype}, {covered.shape}")
    picture = texels.copy()
    picture[..., 3] = np.where(covered, 255, 0).astype(np.uint8)
    return picture


def select_tiles(atlas: np.ndarray, cell: tuple[int, int], azimuth: int | None, elevation: int | None) -> np.ndarray:
    """The part of an atlas (rows = elevations, columns = azimuths of cells (width, height) texels, SPEC.md)
    to show: one view, one elevation row, one azimuth column, or all of it when both are None."""
    width, height = cell
    rows = slice(None) if elevation is None else slice(elevation * height, (elevation + 1) * height)
    columns = slice(None) if azimuth is None else slice(azimuth * width, (azimuth + 1) * width)
    return atlas[rows, columns]


def png_bytes(picture: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(picture), "RGBA").save(buffer, format="PNG")
    return buffer.getvalue()


def render_preview(local_file: Callable[[str], Path], maps: dict[str, str], kind: str, layer: int, cell: tuple[int, int],
                   azimuth: int | None, elevation: int | None) -> bytes:
    """PNG of layer `layer` of the bundle's `kind` map, cut to the selected tiles.

    local_file: a bundle path -> a local file with its bytes (BundleStore.materialize)."""
    uv_format, width, height, _, uv_data = read_texture_layer(local_file(maps["uv"]), layer)
    uv = decode_uv_layer(uv_data, uv_format, width, height)
    if kind == "uv":
        picture = uv_preview(uv)
    else:
        pixel_format, map_width, map_height, _, data = read_texture_layer(local_file(maps[kind]), layer)
        if (map_width, map_height) != (width, height):
            raise ValueError(f"the {kind} map is {map_width}x{map_height}, the uv map {width}x{height}")
        texels = decode_layer(data, pixel_format, width, height)
        if pixel_format == "bc5":  # the normal's two in-view components: show the rebuilt third in blue, as a view-space map
            xy = texels[..., :2].astype(np.float64) / 255.0 * 2.0 - 1.0
            texels = texels.copy()
            texels[..., 2] = np.rint((np.sqrt(np.maximum(0.0, 1.0 - (xy ** 2).sum(axis=-1))) + 1.0) * 127.5).astype(np.uint8)
        picture = colour_preview(texels, uv[..., 3] > 0)
    return png_bytes(select_tiles(picture, cell, azimuth, elevation))


@previews_router.get(
    "/{name}/{version}/preview/{kind}", response_class=Response, responses={**problem_responses(404), 200: {"content": {"image/png": {}}}},
    summary="One impostor atlas layer as PNG (uv: u red, v green; normal; detail), all views or one",
)
def get_atlas_preview(
    name: NameParam, version: VersionParam, kind: Literal["normal", "uv", "detail"], request: Request,
    principal: PrincipalDep, services: ServicesDep, session: SessionDep,
    frame: Annotated[int, Query(ge=0, description="Layer k of the atlas: cycle frame impostor.frame_indices[k].")] = 0,
    azimuth: Annotated[int | None, Query(ge=0, description="Only this azimuth's column (index into impostor.azimuths_deg).")] = None,
    elevation: Annotated[int | None, Query(ge=0, description="Only this elevation's row (index into impostor.elevations_deg).")] = None,
) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    published = _manifest(services, bundle)
    impostor = published.manifest["impostor"]
    errors = []
    for field, value, count in (("frame", frame, len(impostor["frame_indices"])), ("azimuth", azimuth, len(impostor["azimuths_deg"])),
                                ("elevation", elevation, len(impostor["elevations_deg"]))):
        if value is not None and value >= count:
            errors.append({"field": field, "message": f"{field} {value} is outside 0..{count - 1}"})
    if errors:
        raise Problem("validation-error", "the bundle has no such view", errors)
    maps = impostor["maps"]
    if kind not in maps:
        raise Problem("not-found", f"bundle {name} {version} has no {kind} map (baked without --detail-map)")
    sha256 = published.files[maps[kind]]["sha256"]
    etag = hashlib.sha256(f"{sha256}/{published.files[maps['uv']]['sha256']}/{frame}/{azimuth}/{elevation}".encode()).hexdigest()
    headers = {"ETag": f'"{etag}"', "X-Content-Type-Options": "nosniff"}
    if version == LATEST:
        headers["Cache-Control"] = "no-cache"
    else:
        headers["Cache-Control"] = f"{'public' if bundle.public else 'private'}, max-age={IMMUTABLE_SECONDS}, immutable"
    if request.headers.get("if-none-match", "").strip() == headers["ETag"]:
        return Response(status_code=304, headers=headers)
    layout = AtlasLayout.from_manifest(impostor)
    try:
        png = render_preview(lambda path: services.bundles.materialize(bundle.name, bundle.version, path), maps, kind, frame,
                             (layout.cell_width, layout.cell_height), azimuth, elevation)
    except FileNotFoundError:
        raise Problem("internal-error", "a published file is missing from the bundle store", status=500) from None
    return Response(png, media_type="image/png", headers=headers)


# ------------------------------------------------------------------------------------ bundle archive

# Every entry gets this date (zip's epoch), so a bundle's archive is the same bytes every time.
ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def write_bundle_zip(store: BundleStore, name: str, version: str, paths: list[str], target) -> None:
    """manifest.json and the manifest's files (relative `paths`) of the published name/version into the
    zip `target` (a path or a binary file), under <name>/<version>/ as crowdview's cache lays bundles out.
    Stored, not deflated: the atlases are block-compressed already, and the client can check each
    file's sha256 as it is. Files are streamed from the store (an object store's are not cached here)."""
    with zipfile.ZipFile(target, "w", zipfile.ZIP_STORED) as archive:
        for path in ["manifest.json", *paths]:
            info = zipfile.ZipInfo(f"{name}/{version}/{path}", date_time=ZIP_DATE)
            info.external_attr = 0o644 << 16
            with store.open_file(name, version, path) as source, archive.open(info, "w", force_zip64=True) as entry:
                while chunk := source.read(1 << 20):
                    entry.write(chunk)


@previews_router.get(
    "/{name}/{version}/archive.zip", response_class=FileResponse, responses={**problem_responses(404), 200: {"content": {"application/zip": {}}}},
    summary="The whole bundle as one zip (<name>/<version>/manifest.json and its files)",
)
def get_bundle_archive(name: NameParam, version: VersionParam, principal: PrincipalDep, services: ServicesDep, session: SessionDep) -> Response:
    bundle = _bundle_or_problem(session, principal, name, version)
    published = _manifest(services, bundle)
    handle = tempfile.NamedTemporaryFile(prefix="bundle-", suffix=".zip", delete=False)
    try:
        with handle:
            write_bundle_zip(services.bundles, bundle.name, bundle.version, [entry["path"] for entry in published.manifest["files"]], handle)
    except FileNotFoundError:
        os.unlink(handle.name)
        raise Problem("internal-error", "a published file is missing from the bundle store", status=500) from None
    except BaseException:
        os.unlink(handle.name)
        raise
    headers = {"Cache-Control": "no-cache" if version == LATEST else f"{'public' if bundle.public else 'private'}, max-age={IMMUTABLE_SECONDS}, immutable",
               "X-Content-Type-Options": "nosniff"}
    return FileResponse(handle.name, media_type="application/zip", filename=f"{bundle.name}-{bundle.version}.zip", headers=headers,
                        background=BackgroundTask(os.unlink, handle.name))
