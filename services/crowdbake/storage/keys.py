"""API keys: minted once, shown once, stored as a sha256 digest, checked in constant time.

A key reads `cbk_<id>_<secret>`: `id` (12 hex digits) is public and finds the record, `secret` carries
256 bits from `secrets`. Because the key has that much entropy, one unsalted sha256 is enough to make
a leaked table useless (there is nothing to brute-force), and it keeps verification a single lookup.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import re
import secrets

from sqlalchemy import select
from sqlalchemy.orm import Session

from crowdbake.storage.models import ApiKey

# admin: see and change every key's assets, bakes and bundles (operators); without it a key sees only
# what it created, plus public bundles (crowdbake.api.deps.Principal).
SCOPES = ("upload", "bake", "publish", "read", "admin")
KEY_PREFIX = "cbk"
_KEY = re.compile(rf"^{KEY_PREFIX}_([0-9a-f]{{12}})_([A-Za-z0-9_-]{{20,}})$")
# Keys given from outside (the bootstrap key) have their own id so they never collide with minted ones.
BOOTSTRAP_KEY_ID = "bootstrap"


def hash_key(raw_key: str) -> str:
    return hashlib.sha256(raw_key.encode()).hexdigest()


def parse_scopes(text: str | list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """'upload,bake' or ['upload', 'bake'] -> ('bake', 'upload'); ValueError names an unknown scope."""
    items = text.replace(",", " ").split() if isinstance(text, str) else list(text)
    unknown = sorted(set(items) - set(SCOPES))
    if unknown:
        raise ValueError(f"unknown scope(s) {', '.join(unknown)}; scopes are {', '.join(SCOPES)}")
    if not items:
        raise ValueError(f"give at least one scope of {', '.join(SCOPES)}")
    return tuple(sorted(set(items)))


def create_api_key(session: Session, scopes: list[str] | tuple[str, ...] | str, label: str = "") -> tuple[str, ApiKey]:
    """Mint a key with `scopes`; returns (the raw key, shown only now; its record, added to `session`)."""
    scope_list = parse_scopes(scopes)
    key_id = secrets.token_hex(6)
    raw_key = f"{KEY_PREFIX}_{key_id}_{secrets.token_urlsafe(32)}"
    record = ApiKey(id=key_id, key_hash=hash_key(raw_key), scopes=" ".join(scope_list), label=label)
    session.add(record)
    return raw_key, record


def ensure_bootstrap_key(session: Session, raw_key: str) -> ApiKey:
    """Make `raw_key` (from the settings) a key with every scope; replaces an earlier bootstrap key."""
    record = session.get(ApiKey, BOOTSTRAP_KEY_ID)
    digest = hash_key(raw_key)
    if record is None:
        record = ApiKey(id=BOOTSTRAP_KEY_ID, key_hash=digest, scopes=" ".join(SCOPES), label="bootstrap (CROWDBAKE_BOOTSTRAP_KEY)")
        session.add(record)
    else:
        record.key_hash, record.scopes, record.revoked_at = digest, " ".join(SCOPES), None
    return record


def verify_api_key(session: Session, raw_key: str) -> ApiKey | None:
    """The live record of `raw_key`, or None (unknown, malformed or revoked). Digests are compared in
    constant time so response timing says nothing about how much of a guess was right."""
    if not raw_key or len(raw_key) > 200:
        return None
    match = _KEY.match(raw_key)
    if match:
        record = session.get(ApiKey, match.group(1))
    else:
        # A bootstrap key is whatever the operator chose; it is found by its digest.
        record = session.scalars(select(ApiKey).where(ApiKey.id == BOOTSTRAP_KEY_ID)).first()
    if record is None or record.revoked_at is not None:
        return None
    if not hmac.compare_digest(record.key_hash, hash_key(raw_key)):
        return None
    return record


def revoke_api_key(session: Session, key_id: str) -> bool:
    record = session.get(ApiKey, key_id)
    if record is None or record.revoked_at is not None:
        return False
    record.revoked_at = dt.datetime.now(dt.timezone.utc)
    return True
