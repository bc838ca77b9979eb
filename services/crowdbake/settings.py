"""The service's settings: one class, read once from CROWDBAKE_* environment variables.

Every path defaults to a folder under `data_dir`, so `CROWDBAKE_DATA_DIR=/srv/crowdbake` is the only
setting a single machine needs. The API, the workers and the CLI all build their state from the same
class, so a worker started with the API's environment sees the API's database, blobs and broker.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

MiB = 1 << 20

# Secrets people paste from examples; a server started with one of these is a server anyone can use.
KNOWN_DEFAULT_SECRETS = frozenset({"changethis", "changeme", "secret", "password", "admin", "crowdbake", "test", "default"})
# A bootstrap key is compared against stored sha256 digests; below this many characters it is guessable.
MIN_SECRET_LENGTH = 32


class Settings(BaseSettings):
    """Configuration of the crowdbake service (see docs/service.md for the table)."""

    model_config = SettingsConfigDict(env_prefix="CROWDBAKE_", extra="ignore", validate_default=True)

    data_dir: Path = Field(Path("crowdbake-data"), description="Root folder for the defaults below.")
    database_url: str | None = Field(None, description="SQLAlchemy URL; default a SQLite file in data_dir.")
    blob_dir: Path | None = Field(None, description="Content-addressed blob store; default data_dir/blobs.")
    bundles_dir: Path | None = Field(None, description="Published bundles; default data_dir/bundles.")
    work_dir: Path | None = Field(None, description="Per-bake work folders keyed by input hash; default data_dir/work.")
    broker_url: str = Field("filesystem://", description="Celery broker: redis://... in production.")
    broker_dir: Path | None = Field(None, description="Folder of the filesystem broker; default data_dir/broker.")
    queue: str = Field("crowdbake", description="Celery queue the bake tasks go to.")

    store: Literal["local", "s3"] = Field(
        "local", description="Where blobs and bundles live: local folders (blob_dir, bundles_dir) or an S3-compatible bucket."
    )
    s3_endpoint_url: str | None = Field(None, description="S3 API endpoint (http://minio:9000); unset means AWS S3 itself.")
    s3_bucket: str | None = Field(None, description="Bucket of the blobs and bundles (required when store is s3).")
    s3_prefix: str = Field("", description="Key prefix inside the bucket, so several deployments can share one.")
    s3_region: str = Field("us-east-1", description="Region the client signs requests for.")
    s3_access_key_id: SecretStr | None = Field(None, description="Access key; unset means boto3's own credential chain.")
    s3_secret_access_key: SecretStr | None = Field(None, description="Secret key paired with s3_access_key_id.")
    s3_addressing_style: Literal["path", "virtual", "auto"] = Field(
        "path", description="Bucket in the path (MinIO and most self-hosted stores) or in the host name."
    )
    s3_part_bytes: int = Field(16 * MiB, ge=5 * MiB, description="Multipart upload part size; also the most one upload holds in memory.")
    s3_presign_seconds: int = Field(300, gt=0, le=7 * 24 * 3600, description="Lifetime of a presigned download URL.")
    s3_redirect_downloads: bool = Field(
        False, description="Answer bundle file downloads with a 307 to a presigned URL (the object store sends the bytes) instead of streaming them."
    )
    cache_dir: Path | None = Field(None, description="Local read-through cache of an object store's blobs and bundle files; default data_dir/cache.")
    cache_max_bytes: int = Field(4096 * MiB, gt=0, description="Cache size above which the least recently used files are evicted.")

    max_upload_bytes: int = Field(512 * MiB, gt=0, description="Largest request body accepted (413 above).")
    max_zip_entries: int = Field(10_000, gt=0, description="Most entries in an uploaded OBJ-sequence zip.")
    max_zip_uncompressed_bytes: int = Field(4096 * MiB, gt=0, description="Most bytes a zip may expand to.")
    max_zip_ratio: float = Field(200.0, gt=1, description="Largest uncompressed/compressed ratio of one entry.")
    max_texture_pixels: int = Field(8192 * 8192, gt=0, description="Largest PNG (width x height) accepted.")

    header_timeout_s: float = Field(10.0, gt=0, description="Seconds a connection may take to send a request's headers (then it is closed).")
    body_min_bytes_per_s: int = Field(1024, ge=0, description="Slowest request body accepted after the grace period (408 below; 0 = no minimum).")
    body_grace_s: float = Field(10.0, ge=0, description="Seconds a request body may start slowly before the minimum rate applies.")
    body_max_seconds: float = Field(900.0, gt=0, description="Longest a request body may take to arrive, whatever its rate (408 after).")
    shared_workspace: bool = Field(
        False, description="Every key sees and changes every key's assets, bakes and bundles (one team, one workspace); "
        "off: a key sees only what it created, plus public bundles, unless it has the admin scope.",
    )
    bootstrap_key: SecretStr | None = Field(
        None, description="If set, an API key with every scope that exists from start-up (>= 32 characters)."
    )
    task_max_retries: int = Field(3, ge=0, description="Retries of a stage after a transient error.")
    task_retry_backoff_max: float = Field(60.0, gt=0, description="Longest wait between retries (seconds).")
    progress_interval: float = Field(0.5, ge=0, description="Least seconds between two progress writes of a stage.")
    migrate_on_start: bool = Field(True, description="Run the database migrations when the API starts.")
    heartbeat_interval: float = Field(10.0, gt=0, description="Seconds between two heartbeats of a running stage (written by a thread in the worker).")
    heartbeat_timeout: float = Field(
        60.0, gt=0, description="A running stage whose last heartbeat is older than this many seconds lost its worker and is re-queued."
    )
    sweep_interval: float = Field(
        15.0, ge=0, description="Seconds between two passes of the API's sweeper (re-queue lost stages, send unsent ones, delete old work folders); 0 turns it off."
    )
    dispatch_after: float = Field(5.0, ge=0, description="A queued stage whose message was not sent for this many seconds is sent by the sweeper.")
    work_keep_seconds: float = Field(
        7 * 24 * 3600.0, ge=0, description="Work folders of failed and unpublished bakes are deleted this long after the bake ended."
    )

    @field_validator("bootstrap_key")
    @classmethod
    def _refuse_weak_secret(cls, value: SecretStr | None) -> SecretStr | None:
        if value is None:
            return None
        secret = value.get_secret_value()
        if secret.strip().lower() in KNOWN_DEFAULT_SECRETS or len(secret) < MIN_SECRET_LENGTH:
            raise ValueError(
                f"CROWDBAKE_BOOTSTRAP_KEY is a default or has fewer than {MIN_SECRET_LENGTH} characters; "
                "generate one with `python -c 'import secrets; print(secrets.token_urlsafe(32))'`"
            )
        return value

    @model_validator(mode="after")
    def _fill_defaults(self) -> "Settings":
        data = self.data_dir.expanduser().resolve()
        self.data_dir = data
        self.blob_dir = (self.blob_dir or data / "blobs").expanduser().resolve()
        self.bundles_dir = (self.bundles_dir or data / "bundles").expanduser().resolve()
        self.work_dir = (self.work_dir or data / "work").expanduser().resolve()
        self.broker_dir = (self.broker_dir or data / "broker").expanduser().resolve()
        self.cache_dir = (self.cache_dir or data / "cache").expanduser().resolve()
        self.s3_prefix = self.s3_prefix.strip("/") + "/" if self.s3_prefix.strip("/") else ""
        if self.store == "s3" and not self.s3_bucket:
            raise ValueError("CROWDBAKE_STORE=s3 needs CROWDBAKE_S3_BUCKET")
        if (self.s3_access_key_id is None) != (self.s3_secret_access_key is None):
            raise ValueError("set both CROWDBAKE_S3_ACCESS_KEY_ID and CROWDBAKE_S3_SECRET_ACCESS_KEY, or neither")
        if self.heartbeat_timeout <= self.heartbeat_interval:
            raise ValueError("CROWDBAKE_HEARTBEAT_TIMEOUT must be longer than CROWDBAKE_HEARTBEAT_INTERVAL")
        if not self.database_url:
            self.database_url = f"sqlite:///{data / 'crowdbake.sqlite3'}"
        return self

    @property
    def uses_filesystem_broker(self) -> bool:
        return self.broker_url.startswith("filesystem:")

    def ensure_dirs(self) -> None:
        """Create the folders this configuration writes to."""
        for folder in (self.data_dir, self.blob_dir, self.bundles_dir, self.work_dir) + ((self.cache_dir,) if self.store == "s3" else ()):
            folder.mkdir(parents=True, exist_ok=True)
        if self.uses_filesystem_broker:
            (self.broker_dir / "queue").mkdir(parents=True, exist_ok=True)
            (self.broker_dir / "processed").mkdir(parents=True, exist_ok=True)


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process's settings, read from the environment once."""
    return Settings()


def redact_url(url: str) -> str:
    """`url` with any password replaced by `***` (redis://:secret@host -> redis://:***@host), for logs and
    messages: a broker or database URL often carries its credentials."""
    from urllib.parse import urlsplit, urlunsplit

    parts = urlsplit(url)
    if parts.password is None:
        return url
    user = parts.username or ""
    host = parts.hostname or ""
    if parts.port is not None:
        host = f"{host}:{parts.port}"
    return urlunsplit(parts._replace(netloc=f"{user}:***@{host}"))

