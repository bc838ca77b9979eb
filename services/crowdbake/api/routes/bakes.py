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
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import PlainTextResponse
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from crowdbake.api.bake_inputs import check_inputs, check_params, find_assets, input_digests, taken_elsewhere
from crowdbake.api.deps import BakeKey, Principal, PublishKey, ServicesDep, SessionDep
from crowdbake.api.problems import Problem
from crowdbake.api.schemas import MAX_LIST_OFFSET, BakeCreate, BakePublic, BakesPublic, LogLine, StagePublic, problem_responses
from crowdbake.jobs.sweeper import ENQUEUE_WAIT_S, Dispatcher
from crowdbake.params import NAME_PATTERN
from crowdbake.redact import path_replacements, redact_text, redact_value
from crowdbake.storage import bake_requests, records, sweeps
from crowdbake.storage.bundles import find_bundle
from crowdbake.storage.models import Bake

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


def _dispatch(dispatcher: Dispatcher, session: Session, bake: Bake) -> None:
    """Send the bake's queued, unsent stage, waiting ENQUEUE_WAIT_S at most. A broker that does not
    take it in time leaves the bake queued: the sweeper sends it later, and the bake's log says so."""
    delivery = sweeps.current_delivery(session, bake)
    if delivery is None or dispatcher.send(delivery):
        return
    records.append_log(session, bake.id, "WARNING", delivery.stage, "the job queue did not take the bake within "
                       f"{ENQUEUE_WAIT_S:.0f} s; it stays queued and is sent once the broker answers")
    session.commit()


def _held_elsewhere(session: Session, name: str, version: str, key_digest: str, key) -> Problem:
    """The 409 for a submit whose version (or identical inputs) another live bake holds. Another
    workspace's bake is not named: its id would tell that workspace's state."""
    holder = bake_requests.slot_holder(session, name, version)
    if holder is not None and not key.owns(holder.created_by):
        return taken_elsewhere(name, version)
    if holder is not None and holder.input_key != key_digest:
        return Problem("conflict", f"bake {holder.id} is already baking {name}/{version} from other inputs; "
                       "bundles never change, choose a new version")
    return Problem("conflict", f"an identical bake of {name}/{version} is already queued or running; submit again once it has finished")


@router.post("", response_model=BakePublic, status_code=202, responses=problem_responses(400, 404, 409, 503), summary="Start a bake")
def create_bake(body: BakeCreate, response: Response, key: BakeKey, dispatcher: DispatcherDep, session: SessionDep) -> BakePublic:
    if (body.publish or body.public) and "publish" not in key.scopes:
        raise Problem("forbidden", "publishing a bundle (publish or public true) needs the publish scope")
    assets = find_assets(session, body.input_set(), key)
    params = body.params.model_dump()
    check_params(params)
    check_inputs(assets, params)

    key_digest = bake_requests.input_key(input_digests(assets), body.name, body.version, params, created=body.created)
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
        raise _held_elsewhere(session, body.name, body.version, key_digest, key)

    bake = bake_requests.create_bake(
        session, name=body.name, version=body.version, params=params,
        inputs={**assets.map(lambda role, asset: asset.id).record(), **({"created": body.created} if body.created is not None else {})},
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
        raise _held_elsewhere(session, body.name, body.version, key_digest, key) from None
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
