"""A bake request's inputs on the server (POST /v1/bakes, and the web page that posts there): the assets it
names, found for the key, and checked before anything is queued: the parameters as the stages take them
(crowdbake.params), the inputs' mode (crowdbake.ingest.input_modes), and the assets against what their
uploads measured (crowdbake.ingest.bake_request). Every refusal is a problem naming the field at fault."""
from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from crowdbake.api.deps import Principal
from crowdbake.api.problems import Problem
from crowdbake.errors import InputError
from crowdbake.ingest.bake_request import check_request_placement, check_two_cycles, cycle_frames_for, request_fps
from crowdbake.ingest.cycle_document import check_cycle_fits_cloth
from crowdbake.ingest.input_modes import BakeInputSet, InputConflict, InputMode
from crowdbake.ingest.timeline import check_timeline_request
from crowdbake.params import BakeParams, FrameRateError
from crowdbake.storage import records
from crowdbake.storage.models import Asset

# The asset kind each input role names (a clip's cache is a cloth asset).
ROLE_KINDS = {"character": "character", "cloth": "cloth", "textures": "texture", "cycle": "cycle", "timeline": "timeline", "clip_cloth": "cloth"}


def find_assets(session: Session, requested: BakeInputSet[str], key: Principal) -> BakeInputSet[Asset]:
    """The assets a request names, each of its role's kind and owned by `key`; one problem listing every
    one that is not (its field as in the request body: clip_cloth.K.cloth for a clip's cache)."""
    errors: list[dict[str, Any]] = []

    def find(role: str, asset_id: str) -> Asset | None:
        kind = ROLE_KINDS[role.split(".")[0]]
        asset = records.by_id(session, Asset, asset_id)
        if asset is None or asset.kind != kind or not key.owns(asset.created_by):
            field = f"{role}.cloth" if role.startswith("clip_cloth.") else role
            errors.append({"field": field, "message": f"no {kind} asset {asset_id!r}"})
        return asset

    assets = requested.map(find)
    if errors:
        raise Problem("validation-error", "the bake names assets that do not exist", errors)
    return assets


def check_params(params: dict[str, Any]) -> None:
    """The stages' own BakeParams checks too (crowdbake.params: the same table as the request model)."""
    try:
        BakeParams.from_dict(params)
    except (ValueError, TypeError) as error:
        field = f"params.{error.field}" if getattr(error, "field", None) else "params"
        raise Problem("validation-error", f"the parameters are not accepted: {error}", [{"field": field, "message": str(error)}]) from None


def check_inputs(assets: BakeInputSet[Asset], params: dict[str, Any]) -> InputMode:
    """The inputs' mode, after the checks of that mode against the assets' info, and the textures' names."""
    try:
        mode = assets.mode(params.get("cycle_frames"))
    except InputConflict as conflict:
        raise Problem("validation-error", conflict.title, [{"field": conflict.field, "message": conflict.message}]) from None
    if mode is InputMode.CLIP_CLOTH:  # several clips, a cache each: the worker joins them (crowdbake.ingest.clip_caches)
        _check_clip_cloth(assets.character, assets.clip_cloth, params)
    elif mode is InputMode.TIMELINE:  # several clips: the timeline sets the clip and its length
        _check_timeline(assets.character, assets.cloth, assets.timeline, params)
    elif mode in (InputMode.CLOTH, InputMode.CYCLE):
        _check_cycle(assets.character, assets.cloth, assets.cycle, params)
    else:
        _check_body_only(assets.character)
    _check_texture_formats(dict(assets.textures))
    return mode


def input_digests(assets: BakeInputSet[Asset]) -> dict[str, Any]:
    """The bytes the inputs name, shaped as the bake records them (BakeInputSet.record), for the input key
    (crowdbake.storage.bake_requests.input_key): a cloth's or a cycle's stored files (several a role),
    the other assets' digest. Roles not given are left out, so the keys of bakes without them stay what they were."""
    def identity(role: str, asset: Asset) -> Any:
        if role in ("cloth", "cycle") or role.startswith("clip_cloth."):
            return {name: entry["sha256"] for name, entry in asset.files.items()}
        return asset.digest

    return assets.map(identity).record()


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


def _check_timeline(character: Asset, cloth: Asset, timeline: Asset, params: dict[str, Any]) -> None:
    """A timeline (crowdbake.ingest.timeline) against the cloth and the character, as the validate stage
    checks the files, and the garment on the clip the bundle carries (the timeline's first clip when
    params.animation is not given). Problems name the field and, for the timeline, the JSON pointer (`where`)."""
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


def _check_clip_cloth(character: Asset, clip_cloth: tuple[tuple[str, Asset], ...], params: dict[str, Any]) -> None:
    """One cloth asset per clip (crowdbake.ingest.clip_caches): each clip the character's and once, the
    caches alike and each two of its clip's cycles long; the garment sits on the character at each clip's first pose."""
    from crowdbake.ingest.clip_caches import check_clip_cloth_request

    clips = [clip for clip, _ in clip_cloth]
    cloths = [cloth for _, cloth in clip_cloth]
    try:
        check_clip_cloth_request(character.info or {}, clips, [cloth.info or {} for cloth in cloths], params.get("fps"))
        for k, (clip, cloth) in enumerate(clip_cloth):
            try:
                check_request_placement(character.info, cloth.info, clip, params.get("up"), params.get("units"))
            except InputError as error:
                raise InputError(f"clip {clip!r}: {error.message}", error.field if error.field in ("params.up", "params.units") else f"clip_cloth.{k}") from None
    except InputError as error:
        status = "validation-error" if error.field.endswith(".clip") or error.field.startswith("params.") else "invalid-file"
        raise Problem(status, "the clips' cloth caches do not fit the character or each other", [{"field": error.field, "message": error.message}]) from None


def _check_body_only(character: Asset) -> None:
    """A bake without cloth (crowdbake.stages.body_only): the character must have an animation to loop."""
    if not float((character.info or {}).get("animation_seconds") or 0.0) > 0 and not (character.info or {}).get("animations"):
        raise Problem("validation-error", "the character has no animation to loop", [{"field": "character", "message": "a body without cloth needs its walk animation"}])


def _check_texture_formats(textures: dict[str, Asset]) -> None:
    """A texture's name must say its format (the validate stage reads diffuse_*.jpg as JPEG)."""
    errors = []
    for name, texture in textures.items():
        stored = (texture.info or {}).get("format", "png")
        named = "jpeg" if name.lower().endswith((".jpg", ".jpeg")) else "png"
        if stored != named:
            errors.append({"field": f"textures.{name}", "message": f"the asset is a {stored.upper()} image; name it with its extension"})
    if errors:
        raise Problem("validation-error", "a texture's name does not match its format", errors)


def taken_elsewhere(name: str, version: str) -> Problem:
    """The one 409 for a name/version another workspace holds, published (public or private) or being baked:
    names and versions are one namespace, so that it is taken is told, and nothing more."""
    return Problem("conflict", f"{name}/{version} is taken by another workspace; bundles never change, choose a new version")

