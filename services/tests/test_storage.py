"""Storage: the blob store, migrations that match the models, API keys, bundle records, settings and
the bake records' fan-in barrier."""
from __future__ import annotations

import hashlib
import os
import shutil

import pytest
from pydantic import ValidationError
from sqlalchemy import inspect

from crowdbake.storage import bake_requests, records
from crowdbake.settings import Settings
from crowdbake.stages import STAGES
from crowdbake.storage.blobs import LocalBlobStore, check_digest
from crowdbake.storage.bundles import BundleConflict, find_bundle, register_bundle
from crowdbake.storage.db import head_revision, is_migrated, make_engine, make_sessionmaker, migrate, session_scope
from crowdbake.storage.keys import create_api_key, ensure_bootstrap_key, hash_key, parse_scopes, revoke_api_key, verify_api_key
from crowdbake.storage.models import Base, Bake
from service_fixtures import GOOD_BUNDLE, fresh_test_database


def database_url(tmp_path) -> str:
    """A fresh database: a SQLite file, or a new PostgreSQL database when CROWDBAKE_TEST_DATABASE_URL is set."""
    if os.environ.get("CROWDBAKE_TEST_DATABASE_URL"):
        return fresh_test_database(os.environ["CROWDBAKE_TEST_DATABASE_URL"])
    return f"sqlite:///{tmp_path / 'db.sqlite3'}"


@pytest.fixture
def sessions(tmp_path):
    engine = make_engine(database_url(tmp_path))
    migrate(engine)
    return make_sessionmaker(engine)


# ------------------------------------------------------------------------------------------ blobs


def test_commit_stores_under_the_digest_and_deduplicates(tmp_path):
    store = LocalBlobStore(tmp_path / "blobs")
    data = b"cloth" * 1000
    first = store.incoming()
    first.write(data[:100])
    first.write(data[100:])
    assert store.commit(first) is True
    digest = hashlib.sha256(data).hexdigest()
    assert first.sha256 == digest and first.size == len(data)
    assert store.path(digest).read_bytes() == data
    assert store.path(digest).relative_to(tmp_path / "blobs").parts == ("sha256", digest[:2], digest[2:4], digest)

    again = store.incoming()
    again.write(data)
    assert store.commit(again) is False  # same bytes: nothing new stored
    assert list(store.digests()) == [digest]
    assert list(store.staging_dir.iterdir()) == []  # both staging files are gone


def test_discard_leaves_nothing(tmp_path):
    store = LocalBlobStore(tmp_path / "blobs")
    blob = store.incoming()
    blob.write(b"partial")
    blob.discard()
    blob.discard()  # twice is harmless
    assert list(store.staging_dir.iterdir()) == [] and list(store.digests()) == []


def test_materialize_gives_a_read_only_copy(tmp_path):
    store = LocalBlobStore(tmp_path / "blobs")
    blob = store.incoming()
    blob.write(b"mesh bytes")
    store.commit(blob)
    target = store.materialize(blob.sha256, tmp_path / "work" / "inputs" / "cloth.obj")
    assert target.read_bytes() == b"mesh bytes"
    assert not os.stat(target).st_mode & 0o222  # nobody may write through the link into the store
    with pytest.raises(FileNotFoundError):
        store.materialize("0" * 64, tmp_path / "missing")


@pytest.mark.parametrize("digest", ["../../etc/passwd", "A" * 64, "0" * 63, ""])
def test_digests_that_are_not_sha256_are_refused(digest):
    with pytest.raises(ValueError):
        check_digest(digest)


# ------------------------------------------------------------------------------------- migrations


def test_migrations_match_the_models(tmp_path):
    from alembic.autogenerate import compare_metadata
    from alembic.runtime.migration import MigrationContext

    engine = make_engine(database_url(tmp_path))
    assert not is_migrated(engine)
    migrate(engine)
    migrate(engine)  # idempotent
    assert is_migrated(engine) and head_revision() == "0005"
    with engine.connect() as connection:
        differences = compare_metadata(MigrationContext.configure(connection), Base.metadata)
    assert differences == [], "the models changed without a migration"
    assert set(inspect(engine).get_table_names()) >= {table.name for table in Base.metadata.sorted_tables}


def migrated_from(tmp_path, revision: str, stages: tuple[str, ...], bakes: dict[str, tuple[str, str]]):
    """An engine whose database stood at `revision` holding `bakes` ({bake id: (stage, its state)}, every
    other stage of `stages` pending), then migrated to the head."""
    from alembic import command
    from sqlalchemy import text

    from crowdbake.storage.db import _alembic_config

    engine = make_engine(database_url(tmp_path))
    with engine.begin() as connection:
        config = _alembic_config(engine.url.render_as_string(hide_password=False))
        config.attributes["connection"] = connection
        command.upgrade(config, revision)
        for bake_id, (given, state) in bakes.items():
            connection.execute(text("INSERT INTO bakes (id, name, version, state, input_key, params, inputs, publish, public, attempt, "
                                    "created_at, updated_at) VALUES (:id, 'walker', :id, 'queued', :id, '{}', '{}', true, false, 0, "
                                    "CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"), {"id": bake_id})
            for position, stage in enumerate(stages):
                connection.execute(text("INSERT INTO bake_stages (bake_id, stage, position, state, done, total, retries) "
                                        "VALUES (:id, :stage, :position, :state, 0, 0, 0)"),
                                   {"id": bake_id, "stage": stage, "position": position, "state": state if stage == given else "pending"})
    migrate(engine)
    return engine


def test_bakes_made_before_the_loops_stage_get_its_row(tmp_path):
    """Migration 0004: a bake whose rows predate the loops stage gets one after validate, pending where its
    cycle stage has not run (a queued bake, or one retried later, then goes on), skipped where it has."""
    engine = migrated_from(tmp_path, "0003", ("validate", "cycle", "poses", "impostors", "pack", "publish"),
                           {"bk_queued": ("cycle", "pending"), "bk_done": ("cycle", "succeeded")})
    with session_scope(make_sessionmaker(engine)) as session:
        for bake_id, loops_state in (("bk_queued", "pending"), ("bk_done", "skipped")):
            bake = session.get(Bake, bake_id)
            assert [(row.stage, row.position) for row in bake.stages] == list(zip(STAGES, range(len(STAGES))))
            assert records.stage_row(session, bake_id, "loops").state == loops_state


def test_bakes_made_before_the_probes_stage_get_its_row(tmp_path):
    """Migration 0005: a bake whose rows predate the probes stage gets one after cycle, pending where its
    poses stage has not run (the bake then fans its probes out when it gets there), skipped where it has
    (its poses stage draws the probes itself)."""
    poses_states = {"bk_queued": "pending", "bk_posing": "running", "bk_done": "succeeded"}
    engine = migrated_from(tmp_path, "0004", ("validate", "loops", "cycle", "poses", "impostors", "pack", "publish"),
                           {bake_id: ("poses", state) for bake_id, state in poses_states.items()})
    with session_scope(make_sessionmaker(engine)) as session:
        for bake_id, probes_state in (("bk_queued", "pending"), ("bk_posing", "skipped"), ("bk_done", "skipped")):
            bake = session.get(Bake, bake_id)
            assert [(row.stage, row.position) for row in bake.stages] == list(zip(STAGES, range(len(STAGES))))
            assert records.stage_row(session, bake_id, "probes").state == probes_state
            assert records.stage_row(session, bake_id, "poses").state == poses_states[bake_id]


# ------------------------------------------------------------------------------------------- keys


def test_keys_verify_only_with_their_exact_secret(sessions, tmp_path):
    with session_scope(sessions) as session:
        raw, record = create_api_key(session, "bake,upload", "ci")
        key_id = record.id
    with session_scope(sessions) as session:
        found = verify_api_key(session, raw)
        assert found is not None and found.scope_set == {"bake", "upload"}
        assert found.key_hash == hash_key(raw) and raw not in (found.key_hash, found.scopes, found.label)
        assert verify_api_key(session, raw[:-1] + ("A" if raw[-1] != "A" else "B")) is None
        assert verify_api_key(session, "") is None
        assert verify_api_key(session, "cbk_000000000000_" + "x" * 43) is None
    if (tmp_path / "db.sqlite3").exists():
        assert raw.encode() not in (tmp_path / "db.sqlite3").read_bytes()  # only the digest is stored
    with session_scope(sessions) as session:
        assert revoke_api_key(session, key_id)
    with session_scope(sessions) as session:
        assert verify_api_key(session, raw) is None


def test_unknown_scopes_are_refused():
    assert parse_scopes("upload, bake") == ("bake", "upload")
    assert parse_scopes("upload,admin") == ("admin", "upload")
    with pytest.raises(ValueError, match="root"):
        parse_scopes("upload,root")
    with pytest.raises(ValueError):
        parse_scopes("")


def test_bootstrap_key_has_every_scope(sessions):
    secret = "x" * 40
    with session_scope(sessions) as session:
        ensure_bootstrap_key(session, secret)
    with session_scope(sessions) as session:
        assert verify_api_key(session, secret).scope_set == {"upload", "bake", "publish", "read", "admin"}
        assert verify_api_key(session, "y" * 40) is None


@pytest.mark.parametrize("secret", ["changethis", "short-but-not-default", "  ChangeThis  "])
def test_settings_refuse_a_default_or_short_secret(tmp_path, secret):
    with pytest.raises(ValidationError, match="BOOTSTRAP_KEY"):
        Settings(data_dir=tmp_path, bootstrap_key=secret)


def test_settings_put_everything_under_the_data_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("CROWDBAKE_MAX_UPLOAD_BYTES", "1234")
    settings = Settings(data_dir=tmp_path / "d")
    assert settings.max_upload_bytes == 1234
    assert settings.blob_dir == tmp_path / "d" / "blobs" and settings.bundles_dir == tmp_path / "d" / "bundles"
    assert settings.database_url == f"sqlite:///{tmp_path / 'd' / 'crowdbake.sqlite3'}"
    assert settings.uses_filesystem_broker


# ----------------------------------------------------------------------------------------- bundles


def test_register_bundle_is_idempotent_and_refuses_other_bytes(sessions, tmp_path):
    bundles = tmp_path / "bundles"
    shutil.copytree(GOOD_BUNDLE, bundles / "walker" / "1.0.0")
    with session_scope(sessions) as session:
        first = register_bundle(session, bundles, "walker", "1.0.0", False, None)
        expected = hashlib.sha256((GOOD_BUNDLE / "manifest.json").read_bytes()).hexdigest()
        assert first.manifest_sha256 == expected
        assert register_bundle(session, bundles, "walker", "1.0.0", False, None).id == first.id
    # The same version with another manifest (folder replaced behind the store's back) is a conflict.
    manifest = bundles / "walker" / "1.0.0" / "manifest.json"
    manifest.write_bytes(manifest.read_bytes().replace(b'"producer"', b'"producer" ', 1))
    with session_scope(sessions) as session, pytest.raises(BundleConflict):
        register_bundle(session, bundles, "walker", "1.0.0", False, None)


def test_latest_is_the_most_recent(sessions, tmp_path):
    bundles = tmp_path / "bundles"
    for version in ("1.0.0", "1.1.0"):
        shutil.copytree(GOOD_BUNDLE, bundles / "walker" / version)
        with session_scope(sessions) as session:
            register_bundle(session, bundles, "walker", version, False, None)
    with session_scope(sessions) as session:
        assert find_bundle(session, "walker", "latest").version == "1.1.0"


# ---------------------------------------------------------------------------------------- records


def new_bake(session, name="walker", params=None) -> Bake:
    params = params or {"tile_size": 32}
    key = bake_requests.input_key({"character": "a" * 64}, name, "1.0.0", params)
    return bake_requests.create_bake(session, name=name, version="1.0.0", params=params, inputs={}, key=key, publish=True, public=False, created_by=None)


def test_input_key_depends_on_everything_that_decides_the_output():
    base = bake_requests.input_key({"character": "a"}, "walker", "1.0.0", {"tile_size": 32})
    assert base == bake_requests.input_key({"character": "a"}, "walker", "1.0.0", {"tile_size": 32})
    assert base != bake_requests.input_key({"character": "b"}, "walker", "1.0.0", {"tile_size": 32})
    assert base != bake_requests.input_key({"character": "a"}, "walker", "1.0.1", {"tile_size": 32})
    assert base != bake_requests.input_key({"character": "a"}, "walker", "1.0.0", {"tile_size": 64})


def test_fan_in_enqueues_pack_exactly_once_per_attempt(sessions):
    with session_scope(sessions) as session:
        bake_id = new_bake(session).id
    with session_scope(sessions) as session:
        parts = records.record_fan_out(session, bake_id, [{"id": "f0000-e0", "frame": 0}, {"id": "f0005-e0", "frame": 5}, {"id": "f0005-e1", "frame": 5}])
    assert parts == ["impostors/f0000-e0", "impostors/f0005-e0", "impostors/f0005-e1"]
    remaining = []
    for part in [parts[1], parts[1], parts[0], parts[2]]:  # a redelivered part counts once
        with session_scope(sessions) as session:
            remaining.append(records.complete_part(session, bake_id, part))
    assert remaining == [2, 2, 1, 0]
    with session_scope(sessions) as session:
        assert records.stage_row(session, bake_id, "impostors").done == 3
        assert records.claim_fan_in(session, bake_id, 0) is True
    with session_scope(sessions) as session:
        assert records.claim_fan_in(session, bake_id, 0) is False  # a redelivered part cannot enqueue pack twice
    with session_scope(sessions) as session:
        bake = session.get(Bake, bake_id)
        records.fail_bake(session, bake, "pack", {"type": "stage-failed", "title": "t", "detail": "d"})
    with session_scope(sessions) as session:
        bake = bake_requests.retry_bake(session, bake_id, 0)
        assert bake.attempt == 1 and bake.state == "queued" and bake.error is None
    with session_scope(sessions) as session:
        assert records.claim_fan_in(session, bake_id, 1) is True  # the new attempt has its own barrier


def test_two_fan_outs_in_one_attempt_each_queue_their_next_stage_once_and_their_outputs_travel(sessions, tmp_path):
    """A bake of several clips fans out twice (the clips' loops, then the impostor views). Each fan-in
    queues its own next stage exactly once; the impostors' fan-out keeps the loops' parts, whose output
    listings bring every clip's loop to a cycle stage on another machine (private work folders)."""
    from types import SimpleNamespace

    from crowdbake.jobs.deliveries import StageContext
    from crowdbake.jobs.exchange import pull_inputs, push_outputs
    from crowdbake.storage.models import BakePart

    with session_scope(sessions) as session:
        bake_id = new_bake(session).id
    items = [{"id": "0-idle", "clip": "Idle"}, {"id": "1-walking", "clip": "Walking"}]
    services = SimpleNamespace(sessions=sessions, blobs=LocalBlobStore(tmp_path / "blobs"), exchanges_work=True)
    validating = StageContext(services, bake_id, 0, "validate", tmp_path / "machine-validate")
    (validating.work / "validate").mkdir(parents=True)
    (validating.work / "validate" / "record.json").write_text("{}")
    with session_scope(sessions) as session:
        records.finish_stage(session, bake_id, "validate", 0.1, {"outputs": push_outputs(validating, ("validate",))})
        assert records.record_fan_out(session, bake_id, items, "loops") == ["loops/0-idle", "loops/1-walking"]
    for item in items:  # each part on a machine of its own: it stores what it wrote
        ctx = StageContext(services, bake_id, 0, "loops", tmp_path / f"machine-{item['id']}")
        for name in (f"cycle/loops/{item['id']}.npz", f"cycle/loops/{item['id']}.json"):
            (ctx.work / name).parent.mkdir(parents=True, exist_ok=True)
            (ctx.work / name).write_text(item["clip"])
        with session_scope(sessions) as session:
            part = session.get(BakePart, (bake_id, f"loops/{item['id']}"))
            part.spec = dict(part.spec, outputs=push_outputs(ctx, (f"cycle/loops/{item['id']}.npz", f"cycle/loops/{item['id']}.json")))
    with session_scope(sessions) as session:
        assert records.complete_part(session, bake_id, "loops/0-idle") == 1
    with session_scope(sessions) as session:
        assert records.complete_part(session, bake_id, "loops/1-walking") == 0
        assert records.stage_row(session, bake_id, "loops").done == 2
        assert records.claim_fan_in(session, bake_id, 0, "cycle") is True
    with session_scope(sessions) as session:
        assert records.claim_fan_in(session, bake_id, 0, "cycle") is False  # a redelivered last part queues nothing
        assert records.stage_row(session, bake_id, "cycle").state == "queued"
    joining = StageContext(services, bake_id, 0, "cycle", tmp_path / "machine-cycle")
    pull_inputs(joining, "cycle")
    assert sorted(path.name for path in (joining.work / "cycle" / "loops").iterdir()) == ["0-idle.json", "0-idle.npz", "1-walking.json", "1-walking.npz"]
    with session_scope(sessions) as session:
        records.record_fan_out(session, bake_id, [{"id": "f0000-e0"}])
        assert records.parts_left(session, bake_id, "loops") == 0 and records.parts_left(session, bake_id, "impostors") == 1
    with session_scope(sessions) as session:
        assert records.complete_part(session, bake_id, "impostors/f0000-e0") == 0
        assert records.claim_fan_in(session, bake_id, 0) is True  # pack, the impostors' own barrier
        assert session.query(BakePart).filter(BakePart.bake_id == bake_id, BakePart.stage == "loops").count() == 2


def test_progress_weights_cover_every_stage(sessions):
    assert set(records.STAGE_WEIGHTS) == set(STAGES)
    assert sum(records.STAGE_WEIGHTS.values()) == pytest.approx(1.0)
    with session_scope(sessions) as session:
        bake = new_bake(session)
        assert records.overall_progress(bake) == 0.0
        for row in bake.stages:
            row.state = "succeeded"
        assert records.overall_progress(bake) == pytest.approx(1.0)


def test_stage_results_with_infinite_figures_are_stored_as_json():
    """A pack result carries the PSNR of identical pictures, +inf; PostgreSQL's json type refused it
    (DataError) and failed the bake. Non-finite figures are stored as null."""
    from crowdbake.storage.records import json_safe

    stored = json_safe({"psnr_db_worst": float("inf"), "ssim": [1.0, float("nan")], "nested": {"x": -float("inf"), "n": 3}})
    assert stored == {"psnr_db_worst": None, "ssim": [1.0, None], "nested": {"x": None, "n": 3}}
    import json

    json.dumps(stored, allow_nan=False)
