"""SQL records of the service: API keys, assets, bakes (with stages, fan-in parts and log) and bundles.

The database, not the broker, is the truth about a bake: workers record every stage's state and
progress here, and the API reads nothing else. Blobs live in the blob store (crowdbake.storage.blobs),
bundles in the bundles folder; rows only name them by sha256 or by name/version.

Changing a model means adding a migration under crowdbake/storage/migrations/versions
(tests/test_storage.py fails when the models and the migrations disagree).
"""
from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import JSON, BigInteger, Boolean, DateTime, Float, ForeignKey, Integer, String, Text, UniqueConstraint
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, dt.datetime: DateTime(timezone=True)}


# Bake and stage states. A bake is "queued" until a worker starts it and ends "succeeded", "failed" or
# "cancelled"; a stage is "queued" once it is due (its message is sent, or is left for the sweeper to
# send while `sent_at` is empty), and additionally "skipped" (publish when the caller did not ask for it).
BAKE_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINAL_BAKE_STATES = frozenset({"succeeded", "failed", "cancelled"})
STAGE_STATES = ("pending", "queued", "running", "retrying", "succeeded", "failed", "skipped", "cancelled")


class ApiKey(Base):
    """An API key: only the sha256 of the secret is stored; `id` is the key's public prefix."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    scopes: Mapped[str] = mapped_column(String(200))  # space-separated
    label: Mapped[str] = mapped_column(String(200), default="")
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    revoked_at: Mapped[dt.datetime | None] = mapped_column(default=None)

    @property
    def scope_set(self) -> frozenset[str]:
        return frozenset(self.scopes.split())


class Asset(Base):
    """A validated upload: a character, a cloth cache (PC2 + OBJ) or a texture.

    `digest` identifies the content (the file's sha256; for a cloth, the sha256 of its two files'
    digests), so the same upload twice gives the same asset. `files` maps a role ("file", or "cache"
    and "mesh") to {sha256, size, filename, media_type}; `info` holds what validation measured.
    """

    __tablename__ = "assets"
    # Unique per owner: two keys uploading the same bytes get an asset each (the blobs are shared).
    __table_args__ = (UniqueConstraint("kind", "digest", "created_by", name="uq_assets_kind_digest_owner"),)

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    kind: Mapped[str] = mapped_column(String(20))
    digest: Mapped[str] = mapped_column(String(64))
    filename: Mapped[str] = mapped_column(String(255))
    size: Mapped[int] = mapped_column(BigInteger)
    files: Mapped[dict[str, Any]] = mapped_column(JSON)
    info: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    created_by: Mapped[str | None] = mapped_column(String(32), default=None)


class Bake(Base):
    """One bake job: inputs (asset ids), parameters, state and where it stands.

    `input_key` is the sha256 of the inputs' digests, the parameters, the name/version and the code
    version: the work folder is named by it, so a rerun finds its finished stages. `attempt` grows on
    each retry; task messages of an older attempt are dropped. `fan_in_attempt` is not read: the fan-in
    barrier is the state of the stage row after a fan-out (crowdbake.storage.records.claim_fan_in).

    Two unique columns reserve what a bake must not share while it is queued or running (both NULL
    once it ended; NULLs never collide): `live_key`, its input key (identical submits get the same bake
    and two bakes never run in one work folder), and `publish_slot`, "<name>/<version>" of a bake that
    publishes (a submit of the same version from other inputs is a conflict at once, not after a whole
    bake; once published, the bundle's row holds the version).
    """

    __tablename__ = "bakes"
    __table_args__ = (UniqueConstraint("live_key", name="uq_bakes_live_key"), UniqueConstraint("publish_slot", name="uq_bakes_publish_slot"))

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    state: Mapped[str] = mapped_column(String(20), default="queued", index=True)
    name: Mapped[str] = mapped_column(String(64), index=True)
    version: Mapped[str] = mapped_column(String(64))
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    inputs: Mapped[dict[str, Any]] = mapped_column(JSON)
    input_key: Mapped[str] = mapped_column(String(64), index=True)
    publish: Mapped[bool] = mapped_column(Boolean, default=True)
    public: Mapped[bool] = mapped_column(Boolean, default=False)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    fan_in_attempt: Mapped[int | None] = mapped_column(Integer, default=None)
    error: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[dt.datetime] = mapped_column(default=utcnow, onupdate=utcnow)
    started_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    finished_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    created_by: Mapped[str | None] = mapped_column(String(32), default=None)
    live_key: Mapped[str | None] = mapped_column(String(64), default=None)
    publish_slot: Mapped[str | None] = mapped_column(String(130), default=None)

    stages: Mapped[list["BakeStage"]] = relationship(
        back_populates="bake", cascade="all, delete-orphan", order_by="BakeStage.position"
    )


class BakeStage(Base):
    """One stage of a bake: state, progress (done of total) and timings.

    Delivery bookkeeping (crowdbake.jobs.sweeper): `queued_at`/`sent_at` say when the stage became due
    and when its message went to the broker (empty: the sweeper sends it); `owner` is the delivery
    running it ("host:pid:task id") and `heartbeat_at` its last sign of life. `retries` counts transient
    errors and lost workers alike, against CROWDBAKE_TASK_MAX_RETRIES.
    """

    __tablename__ = "bake_stages"

    bake_id: Mapped[str] = mapped_column(ForeignKey("bakes.id", ondelete="CASCADE"), primary_key=True)
    stage: Mapped[str] = mapped_column(String(20), primary_key=True)
    position: Mapped[int] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(20), default="pending")
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    retries: Mapped[int] = mapped_column(Integer, default=0)
    seconds: Mapped[float | None] = mapped_column(Float, default=None)
    started_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    finished_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    queued_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    sent_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    owner: Mapped[str | None] = mapped_column(String(160), default=None)
    heartbeat_at: Mapped[dt.datetime | None] = mapped_column(default=None)

    bake: Mapped[Bake] = relationship(back_populates="stages")


class BakePart(Base):
    """One fanned-out task of a bake (one clip's loop, or one impostor-views task): the fan-in barrier.

    Rows are inserted (done = false) when the stage before a fan-out stage finishes; each task marks its
    own row done; the task that leaves no row of its stage undone enqueues the next stage. Delivery
    bookkeeping as in BakeStage.
    """

    __tablename__ = "bake_parts"

    bake_id: Mapped[str] = mapped_column(ForeignKey("bakes.id", ondelete="CASCADE"), primary_key=True)
    part: Mapped[str] = mapped_column(String(100), primary_key=True)
    stage: Mapped[str] = mapped_column(String(20))
    spec: Mapped[dict[str, Any]] = mapped_column(JSON)
    done: Mapped[bool] = mapped_column(Boolean, default=False)
    retries: Mapped[int] = mapped_column(Integer, default=0)
    queued_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    sent_at: Mapped[dt.datetime | None] = mapped_column(default=None)
    owner: Mapped[str | None] = mapped_column(String(160), default=None)
    heartbeat_at: Mapped[dt.datetime | None] = mapped_column(default=None)


class BakeLog(Base):
    """One line of a bake's log (append-only, so concurrent tasks never overwrite each other)."""

    __tablename__ = "bake_log"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    bake_id: Mapped[str] = mapped_column(ForeignKey("bakes.id", ondelete="CASCADE"), index=True)
    at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    level: Mapped[str] = mapped_column(String(10))
    stage: Mapped[str | None] = mapped_column(String(20), default=None)
    message: Mapped[str] = mapped_column(Text)


class Bundle(Base):
    """A published bundle: <name>/<version> in the bundles folder, never changed once published."""

    __tablename__ = "bundles"
    __table_args__ = (UniqueConstraint("name", "version", name="uq_bundles_name_version"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64), index=True)
    version: Mapped[str] = mapped_column(String(64))
    manifest_sha256: Mapped[str] = mapped_column(String(64))
    size: Mapped[int] = mapped_column(BigInteger)
    file_count: Mapped[int] = mapped_column(Integer)
    public: Mapped[bool] = mapped_column(Boolean, default=False)
    bake_id: Mapped[str | None] = mapped_column(String(40), default=None)
    published_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
