"""Assets: upload a character, a cloth cache, a texture, a chosen cycle or a clip timeline; read their records.

An upload is streamed to a staging file while it is hashed, validated (crowdbake.ingest.uploads), and only
then committed to the blob store and recorded. The same content uploaded again returns the existing
asset (200 instead of 201). A rejected upload leaves neither blobs nor rows behind.
"""
from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Query, Request, Response
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

from crowdbake.api.deps import AssetReadKey, ServicesDep, SessionDep, UploadKey
from crowdbake.api.disconnects import run_until_disconnect
from crowdbake.api.problems import Problem
from crowdbake.api.schemas import MAX_LIST_OFFSET, AssetKind, AssetPublic, AssetsPublic, problem_responses
from crowdbake.api.uploads import MultipartUpload, UploadedFile, read_multipart
from crowdbake.ingest.cycle_document import check_cycle_upload
from crowdbake.ingest.timeline import check_timeline_upload
from crowdbake.ingest.studio_inputs import MEDIA_TYPES as STUDIO_MEDIA_TYPES
from crowdbake.ingest.studio_inputs import check_jpeg_texture, check_point_cache, pc2_first_frame, placement_sample
from crowdbake.ingest.obj_sequence import ZipLimits, convert_obj_sequence
from crowdbake.ingest.uploads import _extension, check_character, check_cloth, check_texture
from crowdbake.storage import records
from crowdbake.storage.assets import store_asset
from crowdbake.storage.blobs import BlobStore, IncomingBlob
from crowdbake.storage.models import Asset

router = APIRouter(prefix="/v1/assets", tags=["assets"])

MEDIA_TYPES = {
    "glb": "model/gltf-binary",
    "gltf": "model/gltf+json",
    "pc2": "application/x-pc2",
    "obj": "model/obj",
    "png": "image/png",
    "json": "application/json",
    **STUDIO_MEDIA_TYPES,
}
# 201 with the new asset; 200 with the asset already stored under the same content (uploads are
# stored once by sha256, and the Location names the existing asset).
UPLOAD_RESPONSES = {200: {"model": AssetPublic, "description": "Already stored: the existing asset with these bytes"},
                    **problem_responses(400, 413, 415)}


def _multipart_body(properties: dict[str, dict[str, Any]], required: list[str]) -> dict[str, Any]:
    """The OpenAPI description of a multipart body (the route reads the stream itself)."""
    return {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
        "type": "object", "properties": properties, "required": required}}}}}


_FILE = {"type": "string", "format": "binary"}


def _require_file(upload: MultipartUpload, field: str) -> UploadedFile:
    if field not in upload.files:
        raise Problem("malformed-request", f"the multipart body needs a file in the field {field!r}", [{"field": field, "message": "missing"}])
    return upload.files[field]


def _store_asset(
    session, blobs: BlobStore, response: Response, kind: str, staged: dict[str, tuple[IncomingBlob, str, str]],
    info: dict[str, Any], created_by: str | None,
) -> Asset:
    """Store the asset (crowdbake.storage.assets): 201 when new, 200 with the existing one's Location."""
    asset, created = store_asset(session, blobs, kind, staged, info, created_by)
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/v1/assets/{asset.id}"
    return asset


@router.post(
    "/characters", response_model=AssetPublic, status_code=201, responses=UPLOAD_RESPONSES,
    summary="Upload a character (.glb, or a self-contained .gltf)",
    openapi_extra=_multipart_body({"file": _FILE}, ["file"]),
)
async def upload_character(request: Request, response: Response, key: UploadKey, services: ServicesDep, session: SessionDep) -> Asset:
    upload = await read_multipart(request, services.blobs, services.settings.max_upload_bytes, {"file"})
    try:
        uploaded = _require_file(upload, "file")
        info = await run_in_threadpool(check_character, uploaded.blob.path, uploaded.filename, "file")
        media_type = MEDIA_TYPES[info["format"]]
        return _store_asset(session, services.blobs, response, "character", {"file": (uploaded.blob, uploaded.filename, media_type)}, info, key.key_id)
    finally:
        upload.discard()


def _cycle_frames(upload: MultipartUpload) -> int | None:
    text = upload.fields.get("cycle_frames")
    if text is None or text.strip() == "":
        return None
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 2:
        raise Problem("validation-error", "cycle_frames must be an integer >= 2", [{"field": "cycle_frames", "message": f"{text!r} is not an integer >= 2"}])
    return value


@router.post(
    "/cloth", response_model=AssetPublic, status_code=201, responses=UPLOAD_RESPONSES,
    summary="Upload a cloth cache: a PC2 or MDD with its OBJ rest mesh, an Alembic .abc alone (needs the crowdbake[alembic] "
            "extra on the API host), or a zip of OBJ frames (one topology)",
    openapi_extra=_multipart_body(
        {"cache": _FILE, "mesh": _FILE, "sequence": _FILE,
         "cycle_frames": {"type": "integer", "minimum": 2, "description": "Frames per walk cycle, to check there are two cycles."}},
        [],
    ),
)
async def upload_cloth(request: Request, response: Response, key: UploadKey, services: ServicesDep, session: SessionDep) -> Asset:
    settings = services.settings
    upload = await read_multipart(request, services.blobs, settings.max_upload_bytes, {"cache", "mesh", "sequence"}, {"cycle_frames"})
    converted: list[IncomingBlob] = []
    try:
        cycle_frames = _cycle_frames(upload)
        has_pair = "cache" in upload.files or "mesh" in upload.files
        if has_pair == ("sequence" in upload.files):
            raise Problem(
                "malformed-request", "send either 'cache' (.pc2 or .mdd) with 'mesh' (.obj), 'cache' (.abc) alone, or 'sequence' (.zip of OBJ frames)",
                [{"field": name, "message": "missing" if name not in upload.files else "unexpected with the other form"} for name in ("cache", "mesh", "sequence")],
            )
        if has_pair and _extension(_require_file(upload, "cache").filename) in (".mdd", ".abc"):
            # MDD and Alembic are stored as uploaded; the validate stage stages them as PC2 + OBJ with their fps.
            cache, mesh = upload.files["cache"], upload.files.get("mesh")
            # Alembic runs a Blender child for up to 300 s: it ends when this request's client leaves.
            info = await run_until_disconnect(request, check_point_cache, cache.blob.path, cache.filename, mesh and mesh.blob.path, mesh and mesh.filename, cycle_frames)
            staged = {"cache": (cache.blob, cache.filename, MEDIA_TYPES[info["format"]])}
            if mesh is not None:
                staged["mesh"] = (mesh.blob, mesh.filename, MEDIA_TYPES["obj"])
        elif has_pair:
            cache, mesh = _require_file(upload, "cache"), _require_file(upload, "mesh")
            info = await run_in_threadpool(check_cloth, cache.blob.path, cache.filename, mesh.blob.path, mesh.filename, cycle_frames)
            info["placement_sample"] = placement_sample(pc2_first_frame(cache.blob.path))
            staged = {"cache": (cache.blob, cache.filename, MEDIA_TYPES["pc2"]), "mesh": (mesh.blob, mesh.filename, MEDIA_TYPES["obj"])}
        else:
            sequence = upload.files["sequence"]
            cache_blob, mesh_blob = services.blobs.incoming(), services.blobs.incoming()
            converted += [cache_blob, mesh_blob]
            limits = ZipLimits(settings.max_zip_entries, settings.max_zip_uncompressed_bytes, settings.max_zip_ratio)
            info = await run_in_threadpool(convert_obj_sequence, sequence.blob.path, sequence.filename, limits, cache_blob, mesh_blob, cycle_frames)
            cache_blob.close()
            mesh_blob.close()
            info["placement_sample"] = placement_sample(pc2_first_frame(cache_blob.path))
            stem = sequence.filename.rsplit(".", 1)[0] or "cloth"
            staged = {"cache": (cache_blob, f"{stem}.pc2", MEDIA_TYPES["pc2"]), "mesh": (mesh_blob, f"{stem}.obj", MEDIA_TYPES["obj"])}
            info["source"] = {"filename": sequence.filename, "sha256": sequence.blob.sha256, "size": sequence.blob.size}
        return _store_asset(session, services.blobs, response, "cloth", staged, info, key.key_id)
    finally:
        upload.discard()
        for blob in converted:
            blob.discard()


@router.post(
    "/textures", response_model=AssetPublic, status_code=201, responses=UPLOAD_RESPONSES,
    summary="Upload a texture: a diffuse variation (PNG, or JPEG: no alpha, so no colour-region codes) or the outfit colour map (PNG)",
    openapi_extra=_multipart_body({"file": _FILE}, ["file"]),
)
async def upload_texture(request: Request, response: Response, key: UploadKey, services: ServicesDep, session: SessionDep) -> Asset:
    upload = await read_multipart(request, services.blobs, services.settings.max_upload_bytes, {"file"})
    try:
        uploaded = _require_file(upload, "file")
        if _extension(uploaded.filename) in (".jpg", ".jpeg"):
            info = await run_in_threadpool(check_jpeg_texture, uploaded.blob.path, uploaded.filename, services.settings.max_texture_pixels, "file")
        else:
            info = await run_in_threadpool(check_texture, uploaded.blob.path, uploaded.filename, services.settings.max_texture_pixels, "file")
        media_type = MEDIA_TYPES["jpeg"] if info.get("format") == "jpeg" else MEDIA_TYPES["png"]
        return _store_asset(session, services.blobs, response, "texture", {"file": (uploaded.blob, uploaded.filename, media_type)}, info, key.key_id)
    finally:
        upload.discard()


@router.post(
    "/cycles", response_model=AssetPublic, status_code=201, responses=UPLOAD_RESPONSES,
    summary="Upload a chosen cycle: cycle.json from `crowdbake cycle`, with its looped.pc2 or alone (the bake closes it again)",
    openapi_extra=_multipart_body({"cycle": _FILE, "looped": _FILE}, ["cycle"]),
)
async def upload_cycle(request: Request, response: Response, key: UploadKey, services: ServicesDep, session: SessionDep) -> Asset:
    upload = await read_multipart(request, services.blobs, services.settings.max_upload_bytes, {"cycle", "looped"})
    try:
        document, looped = _require_file(upload, "cycle"), upload.files.get("looped")
        info = await run_in_threadpool(check_cycle_upload, document.blob.path, document.filename, looped and looped.blob.path, looped and looped.filename)
        staged = {"file": (document.blob, document.filename, MEDIA_TYPES["json"])}
        if looped is not None:
            staged["looped"] = (looped.blob, looped.filename, MEDIA_TYPES["pc2"])
        return _store_asset(session, services.blobs, response, "cycle", staged, info, key.key_id)
    finally:
        upload.discard()


@router.post(
    "/timelines", response_model=AssetPublic, status_code=201, responses=UPLOAD_RESPONSES,
    summary="Upload a clip timeline: which clip, at which clip frame, plays at each frame of a cloth cache of several clips (docs/inputs.md)",
    openapi_extra=_multipart_body({"timeline": _FILE}, ["timeline"]),
)
async def upload_timeline(request: Request, response: Response, key: UploadKey, services: ServicesDep, session: SessionDep) -> Asset:
    upload = await read_multipart(request, services.blobs, services.settings.max_upload_bytes, {"timeline"})
    try:
        document = _require_file(upload, "timeline")
        info = await run_in_threadpool(check_timeline_upload, document.blob.path, document.filename)
        return _store_asset(session, services.blobs, response, "timeline", {"file": (document.blob, document.filename, MEDIA_TYPES["json"])}, info, key.key_id)
    finally:
        upload.discard()


@router.get("", response_model=AssetsPublic, responses=problem_responses())
def list_assets(
    key: AssetReadKey, session: SessionDep,
    kind: AssetKind | None = None,
    limit: int = Query(100, ge=1, le=1000), offset: int = Query(0, ge=0, le=MAX_LIST_OFFSET),
) -> AssetsPublic:
    query = key.only_own(select(Asset).order_by(Asset.created_at.desc(), Asset.id), Asset.created_by)
    if kind:
        query = query.where(Asset.kind == kind)
    assets = session.scalars(query.offset(offset).limit(limit)).all()
    return AssetsPublic(data=[AssetPublic.model_validate(asset) for asset in assets], count=len(assets))


@router.get("/{asset_id}", response_model=AssetPublic, responses=problem_responses(404))
def get_asset(asset_id: str, key: AssetReadKey, session: SessionDep) -> Asset:
    asset = records.by_id(session, Asset, asset_id)
    if asset is None or not key.owns(asset.created_by):  # another key's asset is not there for this one
        raise Problem("not-found", f"no asset {asset_id!r}")
    return asset
