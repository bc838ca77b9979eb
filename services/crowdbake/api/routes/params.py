"""The bake parameter table (crowdbake.params.PARAMS) as data: names, kinds, defaults, bounds, choices
and help, so a form (the web page's bake form) is built from what this server bakes with and cannot
drift from it. Needs no key: it says nothing about any user's data."""
from __future__ import annotations

from fastapi import APIRouter

from crowdbake.api.schemas import ParamPublic
from crowdbake.params import PARAMS, default_text

router = APIRouter(prefix="/v1/params", tags=["bakes"])


@router.get("", response_model=list[ParamPublic], summary="The bake parameters, their defaults, bounds and choices")
def list_params() -> list[ParamPublic]:
    return [
        ParamPublic(
            name=spec.name, kind=spec.kind, default=list(spec.default) if isinstance(spec.default, tuple) else spec.default,
            default_text=default_text(spec), optional=spec.optional, choices=list(spec.choices) if spec.choices else None,
            minimum=spec.minimum, maximum=spec.maximum, above_zero=spec.above_zero, multiple_of=spec.multiple_of,
            min_items=spec.min_items, max_items=spec.max_items, help=spec.help, flag=spec.flag,
        )
        for spec in PARAMS
    ]
