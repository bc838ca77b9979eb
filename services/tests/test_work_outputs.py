"""A stage's outputs carried between two machines' work folders through the blob store
(crowdbake.storage.work_outputs): on local folders and on the S3 test server alike."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from service_fixtures import STORES, settings_overrides, store_env


@pytest.fixture(params=STORES)
def blobs(tmp_path, request):
    from crowdbake.settings import Settings
    from crowdbake.storage.store import open_store

    settings = Settings(data_dir=tmp_path / "store-host", **settings_overrides(store_env(request.param)))
    settings.ensure_dirs()
    return open_store(settings).blobs


def write(root: Path, files: dict[str, bytes]) -> None:
    for relative, data in files.items():
        (root / relative).parent.mkdir(parents=True, exist_ok=True)
        (root / relative).write_bytes(data)


def test_pushed_outputs_arrive_in_another_work_folder_byte_for_byte(blobs, tmp_path):
    from crowdbake.storage import work_outputs

    here, there = tmp_path / "host-a" / "work", tmp_path / "host-b" / "work"
    files = {"poses/body_lod0.cbpc": os.urandom(3000), "poses/textures.npz": b"npz" * 100, "poses/record.json": b"{}\n",
             "poses/sub/deeper.bin": b"\x00" * 10, "cycle/cycle.json": b"not pushed"}
    write(here, files)
    write(here, {"poses/.record.json.tmp": b"half written"})  # an atomic write in flight is never pushed
    digest = work_outputs.push(blobs, here, ["poses"])
    assert sorted(work_outputs.read_listing(blobs, digest)) == sorted(path for path in files if path.startswith("poses/"))

    assert work_outputs.pull(blobs, there, digest) == 4
    got = {path.relative_to(there).as_posix(): path.read_bytes() for path in there.rglob("*") if path.is_file()}
    assert got == {path: data for path, data in files.items() if path.startswith("poses/")}
    # The copies are the work folder's own: writable, and rewriting one leaves the store's bytes alone.
    (there / "poses" / "record.json").write_bytes(b"rewritten by a rerun")
    assert work_outputs.pull(blobs, there, digest) == 1  # only the changed file comes again
    assert (there / "poses" / "record.json").read_bytes() == b"{}\n"
    assert work_outputs.pull(blobs, there, digest) == 0
    # Pushing the same outputs again stores the same listing.
    assert work_outputs.push(blobs, here, ["poses"]) == digest


def test_listings_cannot_name_paths_outside_the_work_folder(blobs, tmp_path):
    import json

    from crowdbake.storage import work_outputs

    for bad in ("../escape", "/etc/passwd", "a/../../b", "a\\b", ""):
        with pytest.raises(ValueError):
            work_outputs.check_relative(bad)
    incoming = blobs.incoming()
    incoming.write(json.dumps({"listing_version": 1, "files": {"../outside": {"sha256": "0" * 64, "size": 1}}}).encode())
    incoming.close()
    blobs.commit(incoming)
    with pytest.raises(ValueError, match="not a path inside a work folder"):
        work_outputs.pull(blobs, tmp_path / "work", incoming.sha256)
    assert not (tmp_path / "outside").exists()
