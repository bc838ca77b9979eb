"""Request and response bodies, one family per resource (AssetPublic, BakeCreate, BakePublic, ...)."""
from __future__ import annotations

import datetime as dt
import re
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, create_model, field_validator, model_validator

from crowdbake.ingest.input_modes import BakeInputSet
from crowdbake.params import CREATED_RULE, NAME_PATTERN, PARAMS, SPECS, VERSION_PATTERN, cross_field_problem, pydantic_fields

# List offsets go to SQL as 64-bit integers; a larger one would raise OverflowError in the driver (a 500).
MAX_LIST_OFFSET = 2**62

# Texture files the validate stage reads from its textures folder.
# A diffuse variation may be a JPEG (no alpha: no colour-region codes); the outfit map is a PNG.
TEXTURE_NAME_PATTERN = r"^(diffuse_[A-Za-z0-9_-]{1,40}\.(png|jpg|jpeg)|outfits\.png)$"


class Problem(BaseModel):
    """RFC 9457 problem details (media type application/problem+json)."""

    type: str = Field(examples=["/problems/invalid-file"])
    title: str
    status: int
    detail: str
    instance: str | None = None
    errors: list[dict[str, Any]] | None = Field(
        None, description="One entry per problem: field, message, file (or zip entry), where (byte offset or line)."
    )


PROBLEM_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": Problem, "content": {"application/problem+json": {}}, "description": description}
    for status, description in {401: "Missing or invalid API key", 403: "The key lacks the scope", 422: "Invalid parameters"}.items()
}


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    descriptions = {
        400: "Malformed request", 404: "Not found", 409: "Conflict with the current state", 413: "Body too large",
        415: "Unsupported file format", 416: "Range not satisfiable", 503: "Not ready",
    }
    responses = dict(PROBLEM_RESPONSES)
    for status in statuses:
        responses[status] = {"model": Problem, "content": {"application/problem+json": {}}, "description": descriptions.get(status, "Problem")}
    return responses


# ------------------------------------------------------------------------------------------ assets


class StoredFile(BaseModel):
    sha256: str
    size: int
    filename: str
    media_type: str


AssetKind = Literal["character", "cloth", "texture", "cycle", "timeline"]


class AssetPublic(BaseModel):
    """A validated upload. `digest` identifies the content: re-uploading the same bytes returns this asset."""

    model_config = ConfigDict(from_attributes=True)

    id: str
    kind: AssetKind
    digest: str
    filename: str
    size: int
    files: dict[str, StoredFile]
    info: dict[str, Any]
    created_at: dt.datetime

    @field_validator("created_at")
    @classmethod
    def _in_utc(cls, value: dt.datetime) -> dt.datetime:
        # SQLite hands back naive datetimes; without an offset the value is not an RFC 3339 date-time.
        return value.replace(tzinfo=dt.timezone.utc) if value.tzinfo is None else value


class AssetsPublic(BaseModel):
    data: list[AssetPublic]
    count: int


# ------------------------------------------------------------------------------------------- bakes


class _BakeParamsChecks(BaseModel):
    """The checks pydantic's field bounds cannot say, from the same table (crowdbake.params)."""

    model_config = ConfigDict(extra="forbid")

    @field_validator(*(spec.name for spec in PARAMS if spec.kind == "floats"), check_fields=False)
    @classmethod
    def _list_values(cls, values: list[float], info) -> list[float]:
        problem = SPECS[info.field_name].problem(values)
        if problem is not None:
            raise ValueError(problem)
        return values

    @model_validator(mode="after")
    def _combination(self):
        clash = cross_field_problem(self.__dict__)
        if clash is not None:
            raise ValueError(clash[1])
        return self


# The request model is derived from crowdbake.params.PARAMS: the same names, defaults, bounds and
# choices as `crowdbake bake` (services/tests/test_params.py checks they agree).
BakeParamsIn = create_model("BakeParamsIn", __base__=_BakeParamsChecks, __module__=__name__, **pydantic_fields())
BakeParamsIn.__doc__ = "Bake parameters (crowdbake.params.PARAMS: one table for REST and CLI); unknown keys are refused."


class ParamPublic(BaseModel):
    """One bake parameter of GET /v1/params (crowdbake.params.ParamSpec): what a form needs to offer it."""

    name: str
    kind: Literal["int", "float", "str", "bool", "floats", "name_or_index"]
    default: Any = Field(description="The value a bake uses when the parameter is left out; null: derived, as default_text says.")
    default_text: str = Field(description="The default as a person reads it (a value, or how a null default is derived).")
    optional: bool = Field(description="Whether null is accepted (it means the derived default).")
    choices: list[str] | None = None
    minimum: float | None = None
    maximum: float | None = None
    above_zero: bool = False
    multiple_of: int | None = None
    min_items: int | None = None
    max_items: int | None = None
    help: str = Field(description="What the parameter is (its default in default_text).")
    flag: str = Field(description="The `crowdbake bake` command-line flag.")


SHA256_PATTERN = re.compile(r"^[0-9a-f]{64}$")
INPUT_ROLE_PATTERN = re.compile(r"^(character|cloth|cycle|timeline|textures\.[A-Za-z0-9._-]{1,64}|clip_cloth\.[0-9]{1,2})$")
MAX_CHECK_ROLES = 64  # a character, cloth, cycle and textures: far fewer than this
MAX_FILES_PER_ROLE = 4  # a cloth cache and its mesh, a cycle and its looped cache


def _input_role(role: str) -> str:
    if not INPUT_ROLE_PATTERN.match(role):
        raise ValueError(f"{role!r} is not an input role (character, cloth, cycle, timeline, textures.FILE, clip_cloth.K)")
    return role


def _role_digests(digests: list[str]) -> list[str]:
    if not 1 <= len(digests) <= MAX_FILES_PER_ROLE or not all(SHA256_PATTERN.match(d) for d in digests):
        raise ValueError(f"an input role must list 1 to {MAX_FILES_PER_ROLE} sha256 digests in lowercase hex")
    return digests


# Checked per key and per value, so that a 422 points at the very role (errors[].where: /inputs/ROLE).
InputRole = Annotated[str, AfterValidator(_input_role)]
RoleDigests = Annotated[list[str], AfterValidator(_role_digests)]


class BakeCheck(BaseModel):
    """Before any upload: may a bake of these inputs publish <name>/<version>? 204 when it may (the
    version is free, or this key's own bake of the same inputs published it: the submit reuses that
    bake), 409 as POST /v1/bakes would answer after the uploads when it is taken from other inputs."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(pattern=NAME_PATTERN, examples=["sample-walker"])
    version: str = Field(pattern=VERSION_PATTERN, examples=["1.0.0"])
    inputs: dict[InputRole, RoleDigests] = Field(
        description="Input role (character, cloth, cycle, timeline, textures.FILE, clip_cloth.K: the K-th entry's cloth) -> the sha256 (hex) of each local file of it.",
        examples=[{"character": ["9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"]}])
    params: BakeParamsIn = Field(default_factory=BakeParamsIn)
    created: str | None = Field(None, pattern=CREATED_RULE.pattern, description="As POST /v1/bakes `created`.")
    publish: bool = Field(True, description="As POST /v1/bakes `publish`: a bake that will not publish may share a version being baked.")

    @field_validator("inputs")
    @classmethod
    def _character_and_role_count(cls, value: dict[str, list[str]]) -> dict[str, list[str]]:
        if "character" not in value or len(value) > MAX_CHECK_ROLES:
            raise ValueError(f"inputs must name the character and at most {MAX_CHECK_ROLES} roles")
        return value


class ClipClothIn(BaseModel):
    """One clip's cloth: a separate simulation of the character's animation `clip` from rest."""

    model_config = ConfigDict(extra="forbid")

    clip: str = Field(min_length=1, max_length=128, description="Name of one of the character's animations.", examples=["Walking"])
    cloth: str = Field(description="Id of a cloth asset simulating that clip alone, from its frame 0.")


class BakeCreate(BaseModel):
    """Start a bake from uploaded assets; it publishes <name>/<version> when `publish` is true."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(pattern=NAME_PATTERN, examples=["sample-walker"])
    version: str = Field(pattern=VERSION_PATTERN, examples=["1.0.0"])
    character: str = Field(description="Id of a character asset.")
    cloth: str | None = Field(None, description="Id of a cloth asset. None: the body alone, its animation's own loop "
                                                "sampled at params.fps (default 30), as `crowdbake bake` without --cloth.")
    textures: dict[str, str] = Field(default_factory=dict, description="File name (diffuse_*.png or diffuse_*.jpg, outfits.png) -> texture asset id.")
    cycle: str | None = Field(
        None, description="Id of a cycle asset (POST /v1/assets/cycles): bake this cycle instead of searching, as "
                          "`crowdbake bake --cycle`. Its frames must lie within the cloth's.")
    timeline: str | None = Field(
        None, description="Id of a timeline asset (POST /v1/assets/timelines): the cloth plays several clips, as "
                          "`crowdbake bake --timeline`; cycle.json gains a loop per clip and a transition per change of clip, "
                          "and the bundle carries every loop and transition.")
    clip_cloth: list[ClipClothIn] = Field(
        default_factory=list, max_length=64,
        description="One cloth cache per clip, as `crowdbake bake --clip-cloth` (docs/inputs.md): each a separate simulation of "
                    "one clip, instead of `cloth` and `timeline`. A loop per clip and no transitions (no simulation joined the "
                    "clips); the bundle carries every loop.")
    params: BakeParamsIn = Field(default_factory=BakeParamsIn)
    # `created` stands beside name and version, not among BakeParams: like them it is what the manifest
    # says about the bundle, not how it is baked (no stage but pack reads it, and it is passed to
    # BakeInputs.created exactly as `crowdbake bake --created`). It does enter the bake's input key, as
    # name and version do, so the same inputs with another time are another bake.
    created: str | None = Field(
        None, pattern=CREATED_RULE.pattern, examples=["2006-09-04T12:00:00Z"],
        description="The manifest's `created` time, RFC 3339 UTC (as `crowdbake bake --created`). "
                    "Default: SOURCE_DATE_EPOCH on the worker, else the uploads' time.",
    )
    publish: bool = Field(True, description="Publish the bundle when the bake succeeds (needs the publish scope).")
    public: bool = Field(False, description="Readable without a key once published (needs the publish scope).")

    @field_validator("version")
    @classmethod
    def _not_alias(cls, value: str) -> str:
        if value == "latest":
            raise ValueError("'latest' is the alias of the newest version and cannot be a version name")
        return value

    @field_validator("created")
    @classmethod
    def _real_time(cls, value: str | None) -> str | None:
        # The pattern admits 2006-13-45T99:00:00Z; a manifest must carry a time that exists.
        if value is not None:
            try:
                dt.datetime.strptime(value, "%Y-%m-%dT%H:%M:%SZ")
            except ValueError:
                raise ValueError(f"{value!r} is not a UTC time that exists (RFC 3339, like 2006-09-04T12:00:00Z)") from None
        return value

    @field_validator("textures")
    @classmethod
    def _texture_names(cls, value: dict[str, str]) -> dict[str, str]:
        bad = [name for name in value if not re.match(TEXTURE_NAME_PATTERN, name)]
        if bad:
            raise ValueError(f"texture names must be diffuse_<variation>.png (or .jpg) or outfits.png, got {', '.join(sorted(bad))}")
        if value and not any(name.startswith("diffuse_") for name in value):
            raise ValueError("textures need at least one diffuse_<variation>.png")
        return value

    def input_set(self) -> BakeInputSet[str]:
        """The inputs' asset ids, as every boundary describes a bake's inputs (crowdbake.ingest.input_modes)."""
        return BakeInputSet(character=self.character, cloth=self.cloth, cycle=self.cycle, timeline=self.timeline,
                            textures=self.textures, clip_cloth=[(entry.clip, entry.cloth) for entry in self.clip_cloth])


class StagePublic(BaseModel):
    stage: str
    state: str
    done: int
    total: int
    retries: int
    seconds: float | None
    started_at: dt.datetime | None
    finished_at: dt.datetime | None


class BakeError(BaseModel):
    stage: str
    type: str
    title: str
    detail: str
    field: str | None = None


class LogLine(BaseModel):
    at: dt.datetime
    level: str
    stage: str | None
    message: str


class BakePublic(BaseModel):
    id: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    name: str
    version: str
    params: dict[str, Any]
    inputs: dict[str, Any]
    input_key: str
    publish: bool
    public: bool
    attempt: int
    progress: float = Field(description="0..1 over all stages.")
    stages: list[StagePublic]
    error: BakeError | None
    log: list[LogLine] = Field(description="The newest lines of the bake's log (all of it at /log).")
    bundle_url: str | None = Field(description="The published bundle's manifest, once published.")
    created_at: dt.datetime
    updated_at: dt.datetime
    started_at: dt.datetime | None
    finished_at: dt.datetime | None


class BakesPublic(BaseModel):
    data: list[BakePublic]
    count: int


# ----------------------------------------------------------------------------------------- bundles


class BundlePublic(BaseModel):
    name: str
    version: str
    manifest_sha256: str
    size: int
    file_count: int
    public: bool
    bake_id: str | None
    published_at: dt.datetime
    manifest_url: str
    export_url: str | None = Field(None, description="The engine export's folder (export.json and its files, docs/export.md); null: published without one.")


class BundleVersionsPublic(BaseModel):
    name: str
    latest: str
    versions: list[BundlePublic]


class BundleNamesPublic(BaseModel):
    names: list[str]


class BundleUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    public: bool


# ------------------------------------------------------------------------------------------ health


class HealthPublic(BaseModel):
    status: str
    version: str


class ReadinessPublic(BaseModel):
    status: str
    checks: dict[str, str]
