"""The blob and bundle store contracts, run on the local folders and on a real S3 server alike.

The S3 server is the one scripts/test.sh starts (CROWDBAKE_TEST_S3_URL, with its keys and bucket);
without one, a private moto server is started for this module, and without moto the S3 cases skip.
Each test gets its own key prefix in the bucket, so tests never see each other's objects.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import tracemalloc
import uuid
from pathlib import Path

import httpx
import pytest
from fastapi import Request  # at module level: the test app's routes are annotated with it

from crowdbake.storage.blobs import LocalBlobStore
from crowdbake.storage.bundle_store import LocalBundleStore
from crowdbake.storage.bundles import BundleConflict, find_bundle, register_bundle
from crowdbake.storage.cache import DigestMismatch, ReadCache
from crowdbake.storage.db import make_engine, make_sessionmaker, migrate, session_scope
from service_fixtures import GOOD_BUNDLE, fresh_test_database, free_port

MiB = 1 << 20
PART = 5 * MiB  # S3's smallest multipart part


# ------------------------------------------------------------------------------------- the server


@pytest.fixture(scope="module")
def s3_server():
    """(endpoint, key id, secret, bucket) of the S3 server the tests use."""
    if os.environ.get("CROWDBAKE_TEST_S3_URL"):
        yield (os.environ["CROWDBAKE_TEST_S3_URL"], os.environ.get("CROWDBAKE_TEST_S3_ACCESS_KEY_ID", "crowdbake-test"),
               os.environ.get("CROWDBAKE_TEST_S3_SECRET_ACCESS_KEY", "crowdbake-test-secret"),
               os.environ.get("CROWDBAKE_TEST_S3_BUCKET", "crowdbake-test"))
        return
    server = Path(sys.executable).parent / "moto_server"
    if not server.exists():
        pytest.skip("no S3 server: set CROWDBAKE_TEST_S3_URL (scripts/test.sh does) or install moto[server]")
    port = free_port()
    process = subprocess.Popen([str(server), "-H", "127.0.0.1", "-p", str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                httpx.get(f"http://127.0.0.1:{port}/", timeout=1)
                break
            except httpx.TransportError:
                if time.monotonic() > deadline or process.poll() is not None:
                    pytest.fail("moto_server did not start")
                time.sleep(0.2)
        yield f"http://127.0.0.1:{port}", "crowdbake-test", "crowdbake-test-secret", "crowdbake-test"
    finally:
        process.terminate()
        process.wait(timeout=30)


@pytest.fixture
def s3(s3_server):
    """(client, bucket, prefix): a client of the server and a key prefix no other test uses."""
    from crowdbake.storage.s3 import ensure_bucket, make_client

    endpoint, key_id, secret, bucket = s3_server
    client = make_client(endpoint, "us-east-1", key_id, secret)
    ensure_bucket(client, bucket)
    return client, bucket, f"test-{uuid.uuid4().hex[:12]}/"


def make_blob_store(kind: str, tmp_path: Path, request, part_bytes: int = PART, cache_max_bytes: int = 64 * MiB):
    if kind == "local":
        return LocalBlobStore(tmp_path / "blobs")
    from crowdbake.storage.s3 import S3BlobStore

    client, bucket, prefix = request.getfixturevalue("s3")
    return S3BlobStore(client, bucket, prefix, tmp_path / "cache", cache_max_bytes, part_bytes)


def make_bundle_store(kind: str, tmp_path: Path, request):
    if kind == "local":
        return LocalBundleStore(tmp_path / "bundles")
    from crowdbake.storage.s3_bundles import S3BundleStore

    client, bucket, prefix = request.getfixturevalue("s3")
    return S3BundleStore(client, bucket, prefix, ReadCache(tmp_path / "cache", 64 * MiB), PART)


@pytest.fixture(params=["local", "s3"])
def blobs(request, tmp_path):
    return make_blob_store(request.param, tmp_path, request)


@pytest.fixture(params=["local", "s3"])
def bundles(request, tmp_path):
    return make_bundle_store(request.param, tmp_path, request)


def stored(store, data: bytes) -> str:
    blob = store.incoming()
    blob.write(data)
    store.commit(blob)
    return blob.sha256


def other_bundle(tmp_path: Path) -> Path:
    """The good vector bundle with other manifest bytes (still valid): the same version, other bytes."""
    folder = tmp_path / "other"
    shutil.copytree(GOOD_BUNDLE, folder)
    manifest = folder / "manifest.json"
    manifest.write_bytes(manifest.read_bytes().replace(b'"producer"', b'"producer" ', 1))
    return folder


def listed_files(folder: Path) -> dict[str, bytes]:
    manifest = json.loads((folder / "manifest.json").read_bytes())
    return {entry["path"]: (folder / entry["path"]).read_bytes() for entry in manifest["files"]}


def test_settings_choose_the_store(tmp_path):
    from pydantic import ValidationError

    from crowdbake.settings import Settings
    from crowdbake.storage.store import open_store

    local = open_store(Settings(data_dir=tmp_path / "d"))
    assert isinstance(local.blobs, LocalBlobStore) and isinstance(local.bundles, LocalBundleStore)
    with pytest.raises(ValidationError, match="S3_BUCKET"):
        Settings(data_dir=tmp_path, store="s3")
    with pytest.raises(ValidationError, match="SECRET_ACCESS_KEY"):
        Settings(data_dir=tmp_path, store="s3", s3_bucket="b", s3_access_key_id="k")
    with pytest.raises(ValidationError, match="s3_part_bytes"):
        Settings(data_dir=tmp_path, store="s3", s3_bucket="b", s3_part_bytes=MiB)


def test_open_store_on_s3(s3, s3_server, tmp_path):
    from crowdbake.settings import Settings
    from crowdbake.storage.s3 import S3BlobStore
    from crowdbake.storage.s3_bundles import S3BundleStore
    from crowdbake.storage.store import open_store

    client, bucket, prefix = s3
    endpoint, key_id, secret, _ = s3_server
    settings = Settings(data_dir=tmp_path / "d", store="s3", s3_endpoint_url=endpoint, s3_bucket=bucket, s3_prefix=prefix.rstrip("/"),
                        s3_access_key_id=key_id, s3_secret_access_key=secret)
    stores = open_store(settings)
    assert isinstance(stores.blobs, S3BlobStore) and isinstance(stores.bundles, S3BundleStore)
    assert stores.blobs.cache is stores.bundles.cache and stores.blobs.prefix == prefix
    digest = stored(stores.blobs, b"through the settings")
    assert client.head_object(Bucket=bucket, Key=f"{prefix}blobs/sha256/{digest[:2]}/{digest[2:4]}/{digest}")["ContentLength"] == 20


# ------------------------------------------------------------------------------------------ blobs


def test_commit_deduplicates_and_reads_back(blobs):
    data = b"cloth" * 1000
    first = blobs.incoming()
    first.write(data[:100])
    first.write(data[100:])
    assert blobs.commit(first) is True
    digest = hashlib.sha256(data).hexdigest()
    assert first.sha256 == digest and blobs.exists(digest) and blobs.size(digest) == len(data)
    with blobs.open(digest) as handle:
        assert handle.read() == data
    again = blobs.incoming()
    again.write(data)
    assert blobs.commit(again) is False  # the same bytes: nothing new stored
    assert list(blobs.digests()) == [digest]
    assert list(blobs.staging_dir.iterdir()) == []  # both staging files are gone
    blobs.delete(digest)
    assert not blobs.exists(digest) and list(blobs.digests()) == []
    with pytest.raises(FileNotFoundError):
        blobs.open(digest)


def test_materialize_gives_a_read_only_copy(blobs, tmp_path):
    digest = stored(blobs, b"mesh bytes")
    target = blobs.materialize(digest, tmp_path / "work" / "inputs" / "cloth.obj")
    assert target.read_bytes() == b"mesh bytes"
    assert not os.stat(target).st_mode & 0o222  # nobody may write through the link into the store
    again = blobs.materialize(digest, tmp_path / "work2" / "cloth.obj")  # a cache hit for S3
    assert again.read_bytes() == b"mesh bytes"
    with pytest.raises(FileNotFoundError):
        blobs.materialize("0" * 64, tmp_path / "missing")


@pytest.mark.parametrize("kind", ["local", "s3"])
def test_a_large_upload_streams_in_bounded_memory(kind, tmp_path, request):
    """24 MiB written 1 MiB at a time and committed: the Python heap peaks near one 5 MiB part."""
    store = make_blob_store(kind, tmp_path, request)
    chunk = os.urandom(MiB)
    total = 24
    expected = hashlib.sha256()
    tracemalloc.start()
    try:
        blob = store.incoming()
        for index in range(total):
            piece = chunk[:-1] + bytes([index])
            expected.update(piece)
            blob.write(piece)
        assert store.commit(blob) is True
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert blob.sha256 == expected.hexdigest() and store.size(blob.sha256) == total * MiB
    assert peak < 2 * PART + 2 * MiB, f"peak {peak / MiB:.1f} MiB while committing {total} MiB"
    reread = hashlib.sha256()
    with store.open(blob.sha256) as handle:
        while piece := handle.read(MiB):
            reread.update(piece)
    assert reread.hexdigest() == blob.sha256
    if kind == "s3":  # sent as a multipart upload: S3's ETag of one names its part count
        head = store.client.head_object(Bucket=store.bucket, Key=store.key(blob.sha256))
        assert head["ETag"].strip('"').endswith(f"-{-(-total * MiB // PART)}")


def test_s3_reads_are_checked_against_the_digest(tmp_path, request):
    """Bytes changed in the bucket behind the store's back are refused, and nothing is cached."""
    store = make_blob_store("s3", tmp_path, request)
    digest = stored(store, b"honest bytes")
    store.client.delete_object(Bucket=store.bucket, Key=store.key(digest))
    store.client.put_object(Bucket=store.bucket, Key=store.key(digest), Body=b"tampered bytes")
    with pytest.raises(DigestMismatch):
        store.materialize(digest, tmp_path / "out")
    assert not store.cache.path(digest).exists() and not (tmp_path / "out").exists()


def test_s3_commit_never_replaces_an_object(tmp_path, request):
    """The conditional put: a key that exists keeps its bytes even when exists() was not asked first."""
    from crowdbake.storage.s3 import put_file_once

    store = make_blob_store("s3", tmp_path, request)
    digest = stored(store, b"first")
    source = tmp_path / "second"
    source.write_bytes(b"second")
    assert put_file_once(store.client, store.bucket, store.key(digest), source, PART) is False
    with store.open(digest) as handle:
        assert handle.read() == b"first"


def test_the_cache_evicts_the_least_recently_used(tmp_path, request):
    store = make_blob_store("s3", tmp_path, request, cache_max_bytes=2500)
    digests = [stored(store, bytes([index]) * 1000) for index in range(3)]
    store.materialize(digests[0], tmp_path / "a")
    time.sleep(0.05)
    store.materialize(digests[1], tmp_path / "b")
    time.sleep(0.05)
    store.materialize(digests[0], tmp_path / "a2")  # a hit: digest 0 is now the most recently used
    time.sleep(0.05)
    store.materialize(digests[2], tmp_path / "c")  # 3000 bytes > 2500: the oldest goes
    assert [store.cache.path(d).exists() for d in digests] == [True, False, True]
    assert (tmp_path / "b").read_bytes() == bytes([1]) * 1000  # a materialized link outlives eviction


def test_presigned_blob_url(blobs):
    digest = stored(blobs, b"presigned")
    url = blobs.presigned_url(digest, 60)
    if isinstance(blobs, LocalBlobStore):
        assert url is None
    else:
        assert httpx.get(url).content == b"presigned"


# ---------------------------------------------------------------------------------------- bundles


def test_small_objects_are_parsed_once_and_revalidated_by_etag(s3):
    """Manifests and export indexes (RevalidatedObjects): a read whose ETag still matches keeps the parsed
    copy (no second parse), a changed object is parsed again, a deleted one is noticed, and only the most
    recently read `size` are kept."""
    from crowdbake.storage.s3 import RevalidatedObjects

    client, bucket, prefix = s3
    parsed = []

    def parse(data: bytes) -> str:
        parsed.append(data)
        return data.decode()

    objects = RevalidatedObjects(client, bucket, size=2)
    key = prefix + "small/a.json"
    client.put_object(Bucket=bucket, Key=key, Body=b"one")
    assert objects.get(key, parse, "gone") == "one" and objects.get(key, parse, "gone") == "one"
    assert parsed == [b"one"]
    client.put_object(Bucket=bucket, Key=key, Body=b"two")
    assert objects.get(key, parse, "gone") == "two" and parsed == [b"one", b"two"]
    for other in ("b", "c"):
        client.put_object(Bucket=bucket, Key=f"{prefix}small/{other}.json", Body=other.encode())
        objects.get(f"{prefix}small/{other}.json", parse, "gone")
    assert objects.get(key, parse, "gone") == "two" and parsed[-1] == b"two" and len(parsed) == 5  # evicted, parsed again
    client.delete_object(Bucket=bucket, Key=key)
    with pytest.raises(FileNotFoundError, match="gone"):
        objects.get(key, parse, "gone")


def test_publish_reads_back_and_is_idempotent(bundles, tmp_path):
    published = bundles.publish(GOOD_BUNDLE, "walker", "1.0.0")
    data = (GOOD_BUNDLE / "manifest.json").read_bytes()
    assert published.data == data and published.sha256 == hashlib.sha256(data).hexdigest()
    assert bundles.exists("walker", "1.0.0") and not bundles.exists("walker", "2.0.0")
    for path, content in listed_files(GOOD_BUNDLE).items():
        with bundles.open_file("walker", "1.0.0", path) as handle:
            assert handle.read() == content
        assert bundles.materialize("walker", "1.0.0", path).read_bytes() == content
    with bundles.open_file("walker", "1.0.0", "manifest.json") as handle:
        assert handle.read() == data
    assert bundles.publish(GOOD_BUNDLE, "walker", "1.0.0").sha256 == published.sha256  # same bytes: a no-op
    with pytest.raises(FileNotFoundError):
        bundles.open_file("walker", "1.0.0", "not/listed.bin")
    with pytest.raises(FileNotFoundError):
        bundles.manifest("walker", "9.9.9")


def test_a_published_version_is_never_overwritten(bundles, tmp_path):
    bundles.publish(GOOD_BUNDLE, "walker", "1.0.0")
    with pytest.raises(BundleConflict):
        bundles.publish(other_bundle(tmp_path), "walker", "1.0.0")
    assert bundles.manifest("walker", "1.0.0").data == (GOOD_BUNDLE / "manifest.json").read_bytes()


def test_byte_ranges(bundles):
    bundles.publish(GOOD_BUNDLE, "walker", "1.0.0")
    content = (GOOD_BUNDLE / "impostor" / "uv.cbtx").read_bytes()
    with bundles.open_file("walker", "1.0.0", "impostor/uv.cbtx", (10, 50)) as handle:
        assert handle.read() == content[10:50]
    with bundles.open_file("walker", "1.0.0", "impostor/uv.cbtx", (len(content) - 1, len(content))) as handle:
        assert handle.read() == content[-1:]


class Crash(Exception):
    """Stands for a process killed in the middle of a publish."""


@pytest.mark.parametrize("kind", ["local", "s3"])
def test_a_crash_between_files_leaves_no_version(kind, tmp_path, request, monkeypatch):
    store = make_bundle_store(kind, tmp_path, request)
    stage = store._stage_file
    written = []

    def crash_on_the_third(staging, entry, source):
        if len(written) == 2:
            raise Crash(entry["path"])
        stage(staging, entry, source)
        written.append(entry["path"])

    monkeypatch.setattr(store, "_stage_file", crash_on_the_third)
    monkeypatch.setattr(store, "_abort", lambda staging: None)  # a killed process cleans nothing up
    with pytest.raises(Crash):
        store.publish(GOOD_BUNDLE, "walker", "1.0.0")
    assert len(written) == 2
    assert not store.exists("walker", "1.0.0")
    with pytest.raises(FileNotFoundError):
        store.open_file("walker", "1.0.0", written[0])
    if kind == "local":
        assert not (tmp_path / "bundles" / "walker" / "1.0.0").exists()
    monkeypatch.undo()
    # The version was never claimed: other bytes may still take it, and then only those are visible.
    other = other_bundle(tmp_path)
    assert store.publish(other, "walker", "1.0.0").data == (other / "manifest.json").read_bytes()
    for path, content in listed_files(other).items():
        with store.open_file("walker", "1.0.0", path) as handle:
            assert handle.read() == content
    if kind == "s3":  # what the crash left is listed for removal, and nothing the version uses is
        leftovers = set(store.unreferenced("walker", "1.0.0"))
        assert len(leftovers) == 2 and all(hashlib.sha256((GOOD_BUNDLE / "manifest.json").read_bytes()).hexdigest() in key for key in leftovers)


def test_concurrent_publishers_of_other_bytes_one_wins(bundles, tmp_path):
    sources = [GOOD_BUNDLE, other_bundle(tmp_path)]
    outcomes: list[object] = [None, None]

    def publish(index: int) -> None:
        try:
            outcomes[index] = bundles.publish(sources[index], "walker", "1.0.0").sha256
        except BundleConflict as error:
            outcomes[index] = error

    threads = [threading.Thread(target=publish, args=(index,)) for index in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    winners = [index for index, outcome in enumerate(outcomes) if isinstance(outcome, str)]
    assert len(winners) == 1, outcomes
    assert bundles.manifest("walker", "1.0.0").data == (sources[winners[0]] / "manifest.json").read_bytes()
    for path, content in listed_files(sources[winners[0]]).items():
        with bundles.open_file("walker", "1.0.0", path) as handle:
            assert handle.read() == content


@pytest.mark.parametrize("name, version", [("../x", "1.0.0"), ("walker", "latest"), ("walker", ".1"), ("Walker", "1.0.0"), ("walker", "a/b")])
def test_names_that_are_not_bundle_names_are_refused(bundles, name, version):
    with pytest.raises(ValueError):
        bundles.publish(GOOD_BUNDLE, name, version)


def test_register_bundle_from_a_store(bundles, tmp_path):
    """The record names the store's manifest (on PostgreSQL when CROWDBAKE_TEST_DATABASE_URL is set)."""
    url = os.environ.get("CROWDBAKE_TEST_DATABASE_URL")
    engine = make_engine(fresh_test_database(url) if url else f"sqlite:///{tmp_path / 'db.sqlite3'}")
    migrate(engine)
    sessions = make_sessionmaker(engine)
    published = bundles.publish(GOOD_BUNDLE, "walker", "1.0.0")
    with session_scope(sessions) as session:
        record = register_bundle(session, bundles, "walker", "1.0.0", False, None)
        assert (record.manifest_sha256, record.file_count, record.size) == (published.sha256, len(published.files), published.total_size)
    with session_scope(sessions) as session:
        assert find_bundle(session, "walker", "latest").manifest_sha256 == published.sha256
    engine.dispose()


# ------------------------------------------------------------------------------------ downloads


@pytest.fixture
def file_client(bundles):
    """A test app with one route per way of answering: streamed (or FileResponse) and redirected."""
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from crowdbake.api.bundle_files import bundle_file_redirect, bundle_file_response
    from crowdbake.api.problems import install as install_problem_handlers

    published = bundles.publish(GOOD_BUNDLE, "walker", "1.0.0")
    app = FastAPI()
    install_problem_handlers(app)

    def headers_of(entry):
        return {"ETag": f'"{entry["sha256"]}"', "Cache-Control": "public, max-age=31536000, immutable"}

    @app.api_route("/stream/{path:path}", methods=["GET", "HEAD"])
    def stream(path: str, request: Request):
        entry = published.files[path]
        return bundle_file_response(request, bundles, "walker", "1.0.0", path, entry["size"], entry["media_type"], headers_of(entry))

    @app.get("/redirect/{path:path}")
    def redirect(path: str):
        entry = published.files[path]
        response = bundle_file_redirect(bundles, "walker", "1.0.0", path, entry["media_type"], headers_of(entry), 120)
        return response if response is not None else {"redirect": None}

    return TestClient(app, follow_redirects=False), published


def test_downloads_stream_with_etag_and_ranges(file_client):
    client, published = file_client
    path = "impostor/uv.cbtx"
    content = (GOOD_BUNDLE / path).read_bytes()
    etag = f'"{published.files[path]["sha256"]}"'
    whole = client.get(f"/stream/{path}")
    assert whole.status_code == 200 and whole.content == content and whole.headers["etag"] == etag
    assert whole.headers["content-type"] == published.files[path]["media_type"]
    assert "immutable" in whole.headers["cache-control"]
    part = client.get(f"/stream/{path}", headers={"Range": "bytes=100-199"})
    assert part.status_code == 206 and part.content == content[100:200]
    assert part.headers["content-range"] == f"bytes 100-199/{len(content)}"
    suffix = client.get(f"/stream/{path}", headers={"Range": "bytes=-16"})
    assert suffix.status_code == 206 and suffix.content == content[-16:]
    stale = client.get(f"/stream/{path}", headers={"Range": "bytes=0-9", "If-Range": '"other"'})
    assert stale.status_code == 200 and stale.content == content  # the range is for other bytes: send all
    outside = client.get(f"/stream/{path}", headers={"Range": f"bytes={len(content)}-"})
    assert outside.status_code == 416 and outside.headers["content-range"] == f"bytes */{len(content)}"
    assert outside.headers["content-type"] == "application/problem+json"
    head = client.head(f"/stream/{path}")
    assert head.status_code == 200 and head.content == b"" and int(head.headers["content-length"]) == len(content)


def test_downloads_by_presigned_redirect(file_client, bundles):
    client, published = file_client
    path = "poses/body_lod0.cbpc"
    content = (GOOD_BUNDLE / path).read_bytes()
    answer = client.get(f"/redirect/{path}")
    if isinstance(bundles, LocalBundleStore):
        assert answer.json() == {"redirect": None}  # a local store has no URL of its own: stream instead
        return
    assert answer.status_code == 307 and answer.headers["etag"] == f'"{published.files[path]["sha256"]}"'
    assert answer.headers["cache-control"] == "private, max-age=90"
    target = answer.headers["location"]
    fetched = httpx.get(target)
    assert fetched.status_code == 200 and fetched.content == content
    assert fetched.headers["content-type"] == published.files[path]["media_type"]
    # The URL asks the store to answer with the bundle's caching (response-cache-control, signed into the
    # URL); S3 honours it, moto's standalone server (the test server) does not always.
    from urllib.parse import parse_qs, urlsplit

    assert parse_qs(urlsplit(target).query)["response-cache-control"] == ["public, max-age=31536000, immutable"]
    if "cache-control" in fetched.headers:
        assert fetched.headers["cache-control"] == "public, max-age=31536000, immutable"
    ranged = httpx.get(target, headers={"Range": "bytes=8-15"})
    assert ranged.status_code == 206 and ranged.content == content[8:16]
