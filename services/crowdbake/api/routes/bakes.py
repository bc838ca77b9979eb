"""Bakes: start one (202 + Location), follow it (state, progress per stage, error, log), cancel it,
retry it, publish it later.

Submitting the same inputs, parameters, name and version again returns the existing bake (200) unless
it failed or was cancelled: the input key (crowdbake.storage.bake_requests.input_key) makes resubmission
idempotent, and the work folder it names makes a rerun fast. While a bake is queued or running it
holds its input key and, when it publishes, its name/version in unique columns, so of two concurrent
submits one creates the bake and the other gets it (same inputs) or a 409 at once (other inputs),
and no two bakes ever run in one work folder.

Starting a bake never waits on the broker for more than ENQUEUE_WAIT_S: the bake is saved as queued,
its first message sent by a thread of the dispatcher; a message that did not go out is sent by the
sweeper (crowdbake.jobs.sweeper), and by a re-submit of the same bake. Cancel, retry and publish are
compare-and-set transitions (crowdbake.storage.bake_requests): of two racing calls one wins, the other 409.
"""
from __future__ import annotations

import logging
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import PlainTextResponse
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from crowdbake.api.deps import BakeKey, Principal, PublishKey, ServicesDep, SessionDep
from crowdbake.api.problems import Problem
from crowdbake.api.schemas import MAX_LIST_OFFSET, BakeCreate, BakePublic, BakesPublic, LogLine, StagePublic, problem_responses
from crowdbake.errors import InputError
from crowdbake.ingest.bake_request import check_request_placement, check_two_cycles, cycle_frames_for, request_fps
from crowdbake.ingest.cycle_document import check_cycle_fits_cloth
from crowdbake.ingest.timeline import check_timeline_request
from crowdbake.jobs.sweeper import ENQUEUE_WAIT_S, Dispatcher
from crowdbake.params import NAME_PATTERN, BakeParams, FrameRateError
from crowdbake.redact import path_replacements, redact_text, redact_value
from crowdbake.storage import bake_requests, records, sweeps
from crowdbake.storage.bundles import find_bundle
from crowdbake.storage.models import Asset, Bake

logger = logging.getLogger(__name__)
router = APIRouter(prefix="/v1/bakes", tags=["bakes"])

LOG_LINES_IN_BAKE = 50


async def get_dispatcher(request: Request) -> Dispatcher:
    return request.app.state.dispatcher


DispatcherDep = Annotated[Dispatcher, Depends(get_dispatcher)]


def bake_public(session: Session, bake: Bake, log_lines: int = LOG_LINES_IN_BAKE) -> BakePublic:
    """The bake as clients see it; log lines and the error never show server paths (crowdbake.redact)."""
    settings = session.info.get("settings")  # set by crowdbake.api.deps.get_session
    replacements = path_replacements(settings) if settings is not None else []
    bundle_url = None
    if bake.publish and bake.stages and bake.stages[-1].state == "succeeded":
        bundle_url = f"/v1/bundles/{bake.name}/{bake.version}/manifest.json"
    return BakePublic(
        id=bake.id, state=bake.state, name=bake.name, version=bake.version, params=bake.params, inputs=bake.inputs,
        input_key=bake.input_key, publish=bake.publish, public=bake.public, attempt=bake.attempt,
        progress=records.overall_progress(bake),
        stages=[StagePublic(
            stage=row.stage, state=row.state, done=row.done, total=row.total, retries=row.retries, seconds=row.seconds,
            started_at=records.to_utc(row.started_at), finished_at=records.to_utc(row.finished_at),
        ) for row in bake.stages],
        error=redact_value(bake.error, replacements),
        log=[LogLine(at=records.to_utc(line.at), level=line.level, stage=line.stage, message=redact_text(line.message, replacements))
             for line in (records.log_lines(session, bake.id, log_lines) if log_lines else [])],
        bundle_url=bundle_url,
        created_at=records.to_utc(bake.created_at), updated_at=records.to_utc(bake.updated_at),
        started_at=records.to_utc(bake.started_at), finished_at=records.to_utc(bake.finished_at),
    )


def _get_bake(session: Session, bake_id: str, key: Principal) -> Bake:
    """The bake, if it exists and `key` owns it (another key's bake is a 404: its id reveals nothing)."""
    bake = records.by_id(session, Bake, bake_id)
    if bake is None or not key.owns(bake.created_by):
        raise Problem("not-found", f"no bake {bake_id!r}")
    return bake


def _asset(session: Session, asset_id: str, kind: str, field: str, errors: list[dict[str, Any]], key: Principal) -> Asset | None:
    asset = records.by_id(session, Asset, asset_id)
    if asset is None or asset.kind != kind or not key.owns(asset.created_by):
        errors.append({"field": field, "message": f"no {kind} asset {asset_id!r}"})
        return None
    return asset


def _check_params(params: dict[str, Any]) -> None:
    """The stages' own BakeParams checks too (crowdbake.params: the same table as the request model)."""
    try:
        BakeParams.from_dict(params)
    except (ValueError, TypeError) as error:
        field = f"params.{error.field}" if getattr(error, "field", None) else "params"
        raise Problem("validation-error", f"the parameters are not accepted: {error}", [{"field": field, "message": str(error)}]) from None


def _check_cycle(character: Asset, cloth: Asset, cycle: Asset | None, params: dict[str, Any]) -> None:
    """The animation must exist, the cloth must hold two cycles of it (or the given cycle, whose frames
    must lie within it: crowdbake.ingest.cycle_document) and sit on the character
    (crowdbake.ingest.bake_request), as problems naming the field."""
    try:
        if cycle is None:
            check_two_cycles(character.info, cloth.info, params.get("cycle_frames"), params.get("fps"), params.get("animation", 0))
        else:  # as the validate stage: the cycle length must still be known, the given cycle then sets it
            cycle_frames_for(character.info, cloth.info, params.get("cycle_frames"), params.get("fps"), params.get("animation", 0))
            check_cycle_fits_cloth(cycle.info, cloth.info)
        check_request_placement(character.info, cloth.info, params.get("animation", 0), params.get("up"), params.get("units"))
    except InputError as error:
        if isinstance(error, FrameRateError):
            raise Problem("validation-error", "the frame rate is out of range", [{"field": error.field, "message": error.message}]) from None
        if error.field in ("params.animation", "params.up", "params.units"):
            title = {"params.animation": "the character has no such animation",
                     "params.up": "the cloth cache is not Y-up", "params.units": "the cloth cache is not in metres"}[error.field]
            raise Problem("validation-error", title, [{"field": error.field, "message": error.message}]) from None
        if error.field == "cycle":
            raise Problem("invalid-file", "the cycle does not fit the cloth", [{"field": "cycle", "message": error.message}]) from None
        if error.field == "cloth" and "two cycles" not in error.message:
            raise Problem("invalid-file", "the garment does not sit on the character", [{"field": "cloth", "message": error.message}]) from None
        if error.field == "cloth":
            raise Problem("invalid-file", "too few frames for two cycles", [{"field": "cloth", "message": error.message}]) from None
        raise Problem("validation-error", "the character has no animation to take the cycle length from",
                      [{"field": error.field, "message": error.message}]) from None


def _check_timeline(character: Asset, cloth: Asset | None, cycle: Asset | None, timeline: Asset, params: dict[str, Any]) -> None:
    """A timeline (crowdbake.ingest.timeline) against the cloth and the character, as the validate stage
    checks the files, and the garment on the clip the bundle carries (the timeline's first clip when
    params.animation is not given). Problems name the field and, for the timeline, the JSON pointer (`where`)."""
    if cloth is None or cycle is not None:
        field = "cloth" if cloth is None else "cycle"
        message = "a timeline says which clip plays at each frame of a cloth cache" if cloth is None else "a cycle chooses one loop; a timeline asks for a loop per clip"
        raise Problem("validation-error", "the timeline does not go with these inputs", [{"field": field, "message": message}])
    if params.get("cycle_frames") is not None:
        raise Problem("validation-error", "the timeline gives each clip's period",
                      [{"field": "params.cycle_frames", "message": "the timeline gives each clip's period: drop cycle_frames"}])
    try:
        fps = request_fps(cloth.info, params.get("fps"))
        check_timeline_request(timeline.info, character.info, cloth.info, fps, params.get("animation"))
    except InputError as error:
        if isinstance(error, FrameRateError):
            raise Problem("validation-error", "the frame rate is out of range", [{"field": error.field, "message": error.message}]) from None
        if error.field == "params.animation":
            raise Problem("validation-error", "the timeline does not play that animation", [{"field": error.field, "message": error.message}]) from None
        pointer = getattr(error, "pointer", None)
        raise Problem("invalid-file", "the timeline does not fit the cloth and the character",
                      [{"field": "timeline", "message": error.message, **({"where": pointer} if pointer else {})}]) from None
    animation = params.get("animation") if params.get("animation") is not None else next(iter(timeline.info["clips"]))
    try:
        check_request_placement(character.info, cloth.info, animation, params.get("up"), params.get("units"))
    except InputError as error:
        status = "validation-error" if error.field in ("params.up", "params.units") else "invalid-file"
        raise Problem(status, "the garment does not sit on the character", [{"field": error.field, "message": error.message}]) from None


def _check_clip_cloth(body: BakeCreate, character: Asset, cloths: list[Asset], params: dict[str, Any]) -> None:
    """One cloth asset per clip (crowdbake.ingest.clip_caches): alone (no cloth, timeline or cycle), each
    clip the character's and once, the caches alike and each two of its clip's cycles long; the garment
    sits on the character at each clip's first pose."""
    from crowdbake.ingest.clip_caches import check_clip_cloth_request

    for given in ("cloth", "timeline", "cycle"):
        if getattr(body, given) is not None:
            raise Problem("validation-error", "one cache per clip stands alone",
                          [{"field": given, "message": f"clip_cloth gives every clip its own cache (separate simulations): leave out {given}"}])
    if params.get("cycle_frames") is not None:
        raise Problem("validation-error", "each clip's animation gives its period",
                      [{"field": "params.cycle_frames", "message": "with clip_cloth each clip's period is its animation's: drop cycle_frames"}])
    clips = [entry.clip for entry in body.clip_cloth]
    try:
        check_clip_cloth_request(character.info or {}, clips, [cloth.info or {} for cloth in cloths], params.get("fps"))
        for k, (clip, cloth) in enumerate(zip(clips, cloths)):
            try:
                check_request_placement(character.info, cloth.info, clip, params.get("up"), params.get("units"))
            except InputError as error:
                raise InputError(f"clip {clip!r}: {error.message}", error.field if error.field in ("params.up", "params.units") else f"clip_cloth.{k}") from None
    except InputError as error:
        status = "validation-error" if error.field.endswith(".clip") or error.field.startswith("params.") else "invalid-file"
        raise Problem(status, "the clips' cloth caches do not fit the character or each other", [{"field": error.field, "message": error.message}]) from None


def _check_body_only(character: Asset, cycle: Asset | None, params: dict[str, Any]) -> None:
    """A bake without cloth (crowdbake.stages.body_only): no cycle to give or length to set, and the
    character must have an animation to loop."""
    if cycle is not None or params.get("cycle_frames") is not None:
        field = "cycle" if cycle is not None else "params.cycle_frames"
        raise Problem("validation-error", "a cycle applies to a cloth cache", [{"field": field, "message": "without cloth the cycle is the animation's own loop"}])
    if not float((character.info or {}).get("animation_seconds") or 0.0) > 0 and not (character.info or {}).get("animations"):
        raise Problem("validation-error", "the character has no animation to loop", [{"field": "character", "message": "a body without cloth needs its walk animation"}])


def _check_texture_formats(textures: dict[str, Asset | None]) -> None:
    """A texture's name must say its format (the validate stage reads diffuse_*.jpg as JPEG)."""
    errors = []
    for name, texture in textures.items():
        stored = (texture.info or {}).get("format", "png") if texture is not None else None
        named = "jpeg" if name.lower().endswith((".jpg", ".jpeg")) else "png"
        if stored is not None and stored != named:
            errors.append({"field": f"textures.{name}", "message": f"the asset is a {stored.upper()} image; name it with its extension"})
    if errors:
        raise Problem("validation-error", "a texture's name does not match its format", errors)


def _dispatch(dispatcher: Dispatcher, session: Session, bake: Bake) -> None:
    """Send the bake's queued, unsent stage, waiting ENQUEUE_WAIT_S at most. A broker that does not
    take it in time leaves the bake queued: the sweeper sends it later, and the bake's log says so."""
    delivery = sweeps.current_delivery(session, bake)
    if delivery is None or dispatcher.send(delivery):
        return
    records.append_log(session, bake.id, "WARNING", delivery.stage, "the job queue did not take the bake within "
                       f"{ENQUEUE_WAIT_S:.0f} s; it stays queued and is sent once the broker answers")
    session.commit()


def _held_elsewhere(session: Session, name: str, version: str, key_digest: str) -> Problem:
    """The 409 for a submit whose version (or identical inputs) another live bake holds."""
    holder = bake_requests.slot_holder(session, name, version)
    if holder is not None and holder.input_key != key_digest:
        return Problem("conflict", f"bake {holder.id} is already baking {name}/{version} from other inputs; "
                       "bundles never change, choose a new version")
    return Problem("conflict", f"an identical bake of {name}/{version} is already queued or running; submit again once it has finished")


@router.post("", response_model=BakePublic, status_code=202, responses=problem_responses(400, 404, 409, 503), summary="Start a bake")
def create_bake(body: BakeCreate, response: Response, key: BakeKey, dispatcher: DispatcherDep, session: SessionDep) -> BakePublic:
    if (body.publish or body.public) and "publish" not in key.scopes:
        raise Problem("forbidden", "publishing a bundle (publish or public true) needs the publish scope")
    errors: list[dict[str, Any]] = []
    character = _asset(session, body.character, "character", "character", errors, key)
    cloth = _asset(session, body.cloth, "cloth", "cloth", errors, key) if body.cloth is not None else None
    textures = {name: _asset(session, asset_id, "texture", f"textures.{name}", errors, key) for name, asset_id in sorted(body.textures.items())}
    cycle = _asset(session, body.cycle, "cycle", "cycle", errors, key) if body.cycle is not None else None
    timeline = _asset(session, body.timeline, "timeline", "timeline", errors, key) if body.timeline is not None else None
    clip_cloths = [_asset(session, entry.cloth, "cloth", f"clip_cloth.{k}.cloth", errors, key) for k, entry in enumerate(body.clip_cloth)]
    if errors:
        raise Problem("validation-error", "the bake names assets that do not exist", errors)
    params = body.params.model_dump()
    _check_params(params)
    if body.clip_cloth:  # several clips, a cache each: the worker joins them (crowdbake.ingest.clip_caches)
        _check_clip_cloth(body, character, clip_cloths, params)
    elif timeline is not None:  # several clips: the timeline sets the clip and its length
        _check_timeline(character, cloth, cycle, timeline, params)
    elif cloth is not None:
        _check_cycle(character, cloth, cycle, params)
    else:
        _check_body_only(character, cycle, params)
    _check_texture_formats(textures)

    digests = {
        "character": character.digest,
        # Only when given, so the keys of bakes with cloth are what they were.
        **({"cloth": {role: entry["sha256"] for role, entry in cloth.files.items()}} if cloth is not None else {}),
        "textures": {name: texture.digest for name, texture in textures.items()},
        # Only when given, so the keys of bakes that search their cycle are what they were.
        **({"cycle": {role: entry["sha256"] for role, entry in cycle.files.items()}} if cycle is not None else {}),
        **({"timeline": timeline.digest} if timeline is not None else {}),
        **({"clip_cloth": [[entry.clip, {role: f["sha256"] for role, f in cloth.files.items()}] for entry, cloth in zip(body.clip_cloth, clip_cloths)]}
           if clip_cloths else {}),
    }
    key_digest = bake_requests.input_key(digests, body.name, body.version, params, created=body.created)
    existing = bake_requests.reusable_bake(session, key_digest)
    if existing is not None and key.owns(existing.created_by):
        return _existing(dispatcher, session, response, existing)
    published = find_bundle(session, body.name, body.version)
    if published is not None:
        raise Problem("conflict", f"{body.name}/{body.version} is already published from other inputs; bundles never change, choose a new version")
    holder = bake_requests.slot_holder(session, body.name, body.version) if body.publish else None
    if holder is not None:
        if holder.input_key == key_digest and key.owns(holder.created_by):
            return _existing(dispatcher, session, response, holder)  # committed since the lookup above
        raise _held_elsewhere(session, body.name, body.version, key_digest)

    bake = bake_requests.create_bake(
        session, name=body.name, version=body.version, params=params,
        inputs={"character": character.id, **({"cloth": cloth.id} if cloth is not None else {}), "textures": {name: texture.id for name, texture in textures.items()},
                **({"cycle": cycle.id} if cycle is not None else {}), **({"timeline": timeline.id} if timeline is not None else {}),
                **({"clip_cloth": [[entry.clip, cloth.id] for entry, cloth in zip(body.clip_cloth, clip_cloths)]} if clip_cloths else {}),
                **({"created": body.created} if body.created is not None else {})},
        key=key_digest, publish=body.publish, public=body.public, created_by=key.key_id,
    )
    try:
        session.commit()
    except IntegrityError:
        # A concurrent submit reserved the input key or the version first: the same bake, or a 409.
        session.rollback()
        existing = bake_requests.live_bake(session, key_digest)
        if existing is not None and key.owns(existing.created_by):
            return _existing(dispatcher, session, response, existing)
        raise _held_elsewhere(session, body.name, body.version, key_digest) from None
    _dispatch(dispatcher, session, bake)
    response.headers["Location"] = f"/v1/bakes/{bake.id}"
    return bake_public(session, bake)


def _existing(dispatcher: Dispatcher, session: Session, response: Response, bake: Bake) -> BakePublic:
    """The same bake again: 200, and its first message is sent now if it never was."""
    _dispatch(dispatcher, session, bake)
    response.status_code = 200
    response.headers["Location"] = f"/v1/bakes/{bake.id}"
    return bake_public(session, bake)


@router.get("", response_model=BakesPublic, responses=problem_responses())
def list_bakes(
    key: BakeKey, session: SessionDep,
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"] | None = None,
    name: str | None = Query(None, pattern=NAME_PATTERN, description="Only bakes of this bundle name."),
    limit: int = Query(50, ge=1, le=500), offset: int = Query(0, ge=0, le=MAX_LIST_OFFSET),
) -> BakesPublic:
    query = key.only_own(select(Bake).order_by(Bake.created_at.desc(), Bake.id), Bake.created_by)
    if state:
        query = query.where(Bake.state == state)
    if name:
        query = query.where(Bake.name == name)
    bakes = session.scalars(query.offset(offset).limit(limit)).all()
    return BakesPublic(data=[bake_public(session, bake, log_lines=0) for bake in bakes], count=len(bakes))


@router.get("/{bake_id}", response_model=BakePublic, responses=problem_responses(404))
def get_bake(bake_id: str, key: BakeKey, session: SessionDep) -> BakePublic:
    return bake_public(session, _get_bake(session, bake_id, key))


@router.get("/{bake_id}/log", response_class=PlainTextResponse, responses=problem_responses(404), summary="The bake's whole log as text")
def get_bake_log(bake_id: str, key: BakeKey, services: ServicesDep, session: SessionDep) -> str:
    bake = _get_bake(session, bake_id, key)
    replacements = path_replacements(services.settings)
    return "".join(
        f"{records.to_utc(line.at).strftime('%Y-%m-%dT%H:%M:%S.%fZ')} {line.level:<7} {line.stage or '-':<9} {redact_text(line.message, replacements)}\n"
        for line in records.log_lines(session, bake.id)
    )


@router.post("/{bake_id}/cancel", response_model=BakePublic, status_code=202, responses=problem_responses(404, 409))
def cancel_bake(bake_id: str, key: BakeKey, session: SessionDep) -> BakePublic:
    _get_bake(session, bake_id, key)
    try:
        bake = bake_requests.cancel_bake(session, bake_id)
    except bake_requests.TransitionRefused as refused:
        session.rollback()
        raise Problem("invalid-state", str(refused)) from None
    session.commit()
    return bake_public(session, bake)


@router.post("/{bake_id}/retry", response_model=BakePublic, status_code=202, responses=problem_responses(404, 409, 503))
def retry_bake(bake_id: str, key: BakeKey, dispatcher: DispatcherDep, session: SessionDep) -> BakePublic:
    seen = _get_bake(session, bake_id, key)
    if seen.state not in ("failed", "cancelled"):
        raise Problem("invalid-state", f"only failed or cancelled bakes can be retried; bake {bake_id} is {seen.state}")
    try:
        bake = bake_requests.retry_bake(session, bake_id, seen.attempt)
        session.commit()
    except bake_requests.TransitionRefused as refused:
        session.rollback()
        raise Problem("invalid-state", str(refused)) from None
    except IntegrityError:
        session.rollback()
        raise Problem("conflict", f"another bake is now baking the inputs or the version {seen.name}/{seen.version} of bake {bake_id}; "
                      "retry once it has finished") from None
    _dispatch(dispatcher, session, bake)
    return bake_public(session, bake)


@router.post("/{bake_id}/publish", response_model=BakePublic, status_code=202, responses=problem_responses(404, 409, 503),
             summary="Publish a bake that was run with publish=false")
def publish_bake(bake_id: str, key: PublishKey, dispatcher: DispatcherDep, session: SessionDep) -> BakePublic:
    seen = _get_bake(session, bake_id, key)
    try:
        bake = bake_requests.request_publish(session, bake_id)
        session.commit()
    except bake_requests.TransitionRefused as refused:
        session.rollback()
        raise Problem("invalid-state", str(refused)) from None
    except IntegrityError:
        session.rollback()
        raise Problem("conflict", f"another bake is baking {seen.name}/{seen.version}; bundles never change") from None
    _dispatch(dispatcher, session, bake)
    return bake_public(session, bake)
