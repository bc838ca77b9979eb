"""POST /v1/bakes/check: whether a bake may publish NAME/VERSION, asked before anything is uploaded.

POST /v1/bakes refuses a version already published from other inputs (409), but only once the assets it
names are uploaded. The client (crowdbake submit) sends this check first, with the sha256 of each local
file, the parameters and the manifest time. The answer is the one POST /v1/bakes would give:

- 204: the version is not published, or this key's own bake published it from these very inputs (a
  submit then reuses that bake);
- 409 (problem+json): it is published from other inputs. When another workspace holds it, published
  (public or private) or being baked, the answer is one and the same (taken_elsewhere): which of those it
  is, its bake, inputs and parameters are neither compared nor revealed (a submit from this key could not
  reuse that bake whatever its inputs, since reuse needs the key that owns it). Names and versions are one
  namespace, so that the version is taken is the one thing POST /v1/bakes would tell as well.
"""
from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Response
from sqlalchemy.orm import Session

from crowdbake.api.bake_inputs import taken_elsewhere
from crowdbake.api.deps import BakeKey, SessionDep
from crowdbake.api.problems import Problem
from crowdbake.api.schemas import BakeCheck, problem_responses
from crowdbake.ingest.input_modes import BakeInputSet
from crowdbake.storage import bake_requests
from crowdbake.storage.bundles import find_bundle
from crowdbake.storage.models import Asset, Bake

router = APIRouter(prefix="/v1/bakes", tags=["bakes"])


def asset_digests(asset: Asset) -> set[str]:
    """Every sha256 an asset answers to: its digest, its stored files, the source it was converted from."""
    found = {asset.digest} | {entry.get("sha256") for entry in (asset.files or {}).values()}
    found.add(((asset.info or {}).get("source") or {}).get("sha256"))
    return {value for value in found if value}


def _canonical(value: Any) -> Any:
    return json.loads(json.dumps(value, sort_keys=True))  # tuples and lists, as the database holds them


def difference(session: Session, bake: Bake, body: BakeCheck) -> str | None:
    """What differs between `bake`'s inputs and the check's (a role, a file, a parameter, the time), or None."""
    published = BakeInputSet.from_record(bake.inputs or {}).roles()
    for role in sorted(set(published) | set(body.inputs)):
        if role not in published or role not in body.inputs:
            return f"its bake had no {role}" if role not in published else f"its bake had a {role}, this one has none"
        asset = session.get(Asset, published[role])
        known = asset_digests(asset) if asset is not None else set()
        if not set(body.inputs[role]) <= known:
            return f"its {role} has other bytes"
    wanted, had = _canonical(body.params.model_dump()), _canonical(bake.params or {})
    for name in sorted(set(wanted) | set(had)):
        if wanted.get(name) != had.get(name):
            return f"parameter {name} was {had.get(name)!r}, this bake asks for {wanted.get(name)!r}"
    if body.created != (bake.inputs or {}).get("created"):
        return f"its manifest time was {(bake.inputs or {}).get('created') or 'the default'}, this bake asks for {body.created or 'the default'}"
    return None


def taken(name: str, version: str, why: str | None = None) -> Problem:
    reason = f" ({why})" if why else ""
    return Problem("conflict", f"{name}/{version} is already published from other inputs{reason}; bundles never change, choose a new version")


@router.post("/check", status_code=204, response_class=Response, responses=problem_responses(400, 409),
             summary="Check, before uploading, that a bake may publish its name and version")
def check_bake(body: BakeCheck, key: BakeKey, session: SessionDep) -> Response:
    published = find_bundle(session, body.name, body.version)
    if published is not None:
        bake = session.get(Bake, published.bake_id) if published.bake_id else None
        if bake is None:
            raise taken(body.name, body.version)  # published without a bake: nobody's to reuse
        if not key.owns(bake.created_by):
            raise taken_elsewhere(body.name, body.version)
        why = difference(session, bake, body)
        if why is not None:
            raise taken(body.name, body.version, why)
        return Response(status_code=204)
    holder = bake_requests.slot_holder(session, body.name, body.version) if body.publish else None
    if holder is not None and not key.owns(holder.created_by):
        raise taken_elsewhere(body.name, body.version)
    return Response(status_code=204)
