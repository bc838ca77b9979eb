"""Request and response bodies, one family per resource (AssetPublic, BakeCreate, BakePublic, ...)."""
from __future__ import annotations

import datetime as dt
import re
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from crowdbake.pipeline import MAX_AZIMUTHS, MAX_ELEVATIONS, MAX_IMPOSTOR_FRAMES, MAX_TILE_SIZE

# List offsets go to SQL as 64-bit integers; a larger one used to raise OverflowError (a 500).
MAX_LIST_OFFSET = 2**62

# The bundle spec's name and version rules (shared_formats/SPEC.md, "manifest.json").
NAME_PATTERN = r"^[a-z0-9][a-z0-9._-]{0,63}$"
VERSION_PATTERN = r"^[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}$"
# Texture files the pipeline reads from its textures folder.
TEXTURE_NAME_PATTERN = r"^(diffuse_[A-Za-z0-9_-]{1,40}|outfits)\.png$"


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


class AssetPublic(BaseModel):
    """A validated upload. `digest` identifies the content: re-uploading the same bytes returns this asset."""

    model_config = ConfigDict(from_attributes=True)

    id: str
    kind: Literal["character", "cloth", "texture"]
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


class BakeParamsIn(BaseModel):
    """Bake parameters (crowdbake.pipeline.BakeParams, whose limits these are); unknown keys are refused."""

    model_config = ConfigDict(extra="forbid")

    cycle_frames: int | None = Field(None, ge=2, le=100_000, description="Frames per walk cycle; default from the character's animation.")
    close: Literal["none", "linear", "hermite"] = "hermite"
    candidates: int = Field(5, ge=1, le=50, description="Cycle candidates kept by pass 1 (paper §3).")
    cycle_views: int = Field(5, ge=1, le=32, description="Views of the pass-2 edge metric (paper: 5).")
    impostor_frames: int = Field(10, ge=1, le=MAX_IMPOSTOR_FRAMES, description="Cycle frames baked into impostors (paper: 10).")
    azimuths: int = Field(16, ge=1, le=MAX_AZIMUTHS)
    elevations_deg: list[float] = Field(default_factory=lambda: [0.0, 20.0, 40.0], min_length=1, max_length=MAX_ELEVATIONS)
    tile_size: int = Field(128, ge=4, le=MAX_TILE_SIZE, description="Impostor tile edge in texels (multiple of 4: BC blocks).")
    lod_ratio: float | None = Field(None, gt=0, le=1)
    lod_triangles: int | None = Field(None, ge=2)
    compress: bool = True

    @field_validator("tile_size")
    @classmethod
    def _multiple_of_four(cls, value: int) -> int:
        if value % 4:
            raise ValueError("must be a multiple of 4 (BC1/BC2 blocks are 4x4 texels)")
        return value

    @field_validator("elevations_deg")
    @classmethod
    def _elevations(cls, values: list[float]) -> list[float]:
        if any(not -90.0 <= value <= 90.0 for value in values):
            raise ValueError("elevations must lie in -90..90 degrees")
        if len(set(values)) != len(values):
            raise ValueError("elevations must differ")
        return values

    @model_validator(mode="after")
    def _one_lod_target(self) -> "BakeParamsIn":
        if self.lod_ratio is not None and self.lod_triangles is not None:
            raise ValueError("give lod_ratio or lod_triangles, not both")
        return self


class BakeCreate(BaseModel):
    """Start a bake from uploaded assets; it publishes <name>/<version> when `publish` is true."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(pattern=NAME_PATTERN, examples=["sample-walker"])
    version: str = Field(pattern=VERSION_PATTERN, examples=["1.0.0"])
    character: str = Field(description="Id of a character asset.")
    cloth: str = Field(description="Id of a cloth asset.")
    textures: dict[str, str] = Field(default_factory=dict, description="File name (diffuse_*.png, outfits.png) -> texture asset id.")
    params: BakeParamsIn = Field(default_factory=BakeParamsIn)
    publish: bool = Field(True, description="Publish the bundle when the bake succeeds (needs the publish scope).")
    public: bool = Field(False, description="Readable without a key once published (needs the publish scope).")

    @field_validator("version")
    @classmethod
    def _not_alias(cls, value: str) -> str:
        if value == "latest":
            raise ValueError("'latest' is the alias of the newest version and cannot be a version name")
        return value

    @field_validator("textures")
    @classmethod
    def _texture_names(cls, value: dict[str, str]) -> dict[str, str]:
        bad = [name for name in value if not re.match(TEXTURE_NAME_PATTERN, name)]
        if bad:
            raise ValueError(f"texture names must be diffuse_<variation>.png or outfits.png, got {', '.join(sorted(bad))}")
        if value and not any(name.startswith("diffuse_") for name in value):
            raise ValueError("textures need at least one diffuse_<variation>.png")
        return value


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
