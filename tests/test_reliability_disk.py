"""A full disk fails a bake cleanly and publishes nothing; once there is room, a retry succeeds.

Two real mechanisms make writes fail (docs/reliability.md says which ran):

* `tmpfs`: the bundles folder is a small tmpfs (`mount -t tmpfs -o size=768k`), smaller than the bundle,
  so the publish stage's writes fail with ENOSPC part way through the bundle. Needs root with
  CAP_SYS_ADMIN; skipped with the reason otherwise. ENOSPC is transient, so the stage is retried
  CROWDBAKE_TASK_MAX_RETRIES times before the bake fails. Afterwards the tmpfs is remounted larger.
* `rlimit-fsize`: the worker runs with RLIMIT_FSIZE of 1 MiB (and SIGXFSZ ignored, so the kernel
  answers EFBIG instead of killing it): no stage can write a file over 1 MiB. Works
  unprivileged. A file-size limit does not go away by itself, so the bake fails at once (in validate,
  which copies the 3 MB cloth cache); a worker without the limit then bakes the retry.

And the API: an upload onto a full blob store is a 503 problem, and leaves nothing behind.

Regressions (fixed): an upload that filled the blob store's disk was a 500 "unexpected error"
(crowdbake.api.problems now answers ENOSPC/EDQUOT with 503 not-ready); a bake failed by an OSError
showed the server's work-folder path in its error (crowdbake.jobs.failures.describe_error now gives
the errno and its reason; the path stays in the worker's log).
"""
from __future__ import annotations

import errno
import os
import resource
import shutil
import signal
import subprocess
from contextlib import contextmanager
from pathlib import Path

import pytest
from sqlalchemy import func, select

from crowdbake.formats.bundle import verify_bundle
from reliability_fixtures import FAST_PARAMS, RedisServer, bake_body, files_under, make_service, upload_sample, wait_for_bake

pytestmark = [pytest.mark.integration, pytest.mark.slow]

BAKE_TIMEOUT_S = 240
TMPFS_SIZE = "768k"         # the sample's bundle with FAST_PARAMS is about 1.5 MB (its body skinned)
FSIZE_LIMIT = 1 << 20       # the sample's pose caches are 0.4 to 3 MB each
MAX_RETRIES = 2


@contextmanager
def small_tmpfs(folder: Path, size: str):
    """Mount a tmpfs of `size` on `folder` (skips the test when mounting is not permitted)."""
    folder.mkdir(parents=True, exist_ok=True)
    mount = shutil.which("mount")
    result = subprocess.run([mount or "mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(folder)], capture_output=True, text=True) if mount else None
    if result is None or result.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({result.stderr.strip() if result else 'no mount command'}); the rlimit-fsize case covers full disks")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def limit_file_size() -> None:
    """In the worker, before exec: writes past FSIZE_LIMIT fail with EFBIG instead of raising SIGXFSZ."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FSIZE_LIMIT, FSIZE_LIMIT))


def bundle_rows(service, name: str) -> int:
    from crowdbake.storage.models import Bundle

    with service.sessions()() as session:
        return session.scalar(select(func.count()).select_from(Bundle).where(Bundle.name == name))


@pytest.mark.parametrize("mechanism", ["tmpfs", "rlimit-fsize"])
def test_a_full_disk_fails_the_bake_cleanly_and_a_retry_succeeds(mechanism, sample, tmp_path):
    redis = RedisServer(tmp_path / "redis").start()
    settings_env = {"CROWDBAKE_TASK_MAX_RETRIES": str(MAX_RETRIES), "CROWDBAKE_TASK_RETRY_BACKOFF_MAX": "1"}
    mounted = None
    if mechanism == "tmpfs":
        mounted = small_tmpfs(tmp_path / "bundles-fs", TMPFS_SIZE)
        settings_env["CROWDBAKE_BUNDLES_DIR"] = str(mounted.__enter__())
    service = make_service(tmp_path / "service", redis.url, **settings_env)
    try:
        service.start_api()
        worker = service.start_worker(concurrency=2, preexec_fn=limit_file_size if mechanism == "rlimit-fsize" else None)
        name = f"full-{mechanism}"
        with service.client() as client:
            ids = upload_sample(client, sample)
            created = client.post("/v1/bakes", json=bake_body(ids, name, "1.0.0", FAST_PARAMS))
            assert created.status_code == 202, created.text
            bake_id = created.json()["id"]
            bake = wait_for_bake(client, bake_id, BAKE_TIMEOUT_S, explain=lambda: worker.tail(60))
            assert bake["state"] == "failed", bake
            error = bake["error"]
            stages = {stage["stage"]: stage for stage in bake["stages"]}
            if mechanism == "tmpfs":
                # Retried as transient, then failed with the reason, in the stage that writes the bundle.
                assert error["stage"] == "publish" and os.strerror(errno.ENOSPC) in error["detail"], error
                assert stages["publish"]["retries"] == MAX_RETRIES
            else:
                # Not transient: the first stage that writes a file over the limit (validate copies the
                # 3 MB cloth cache into the work folder) fails at once.
                assert error["stage"] == "validate" and os.strerror(errno.EFBIG) in error["detail"], error
                assert stages["validate"]["retries"] == 0
            assert stages["pack"]["state"] == ("succeeded" if mechanism == "tmpfs" else "pending")
            print(f"\nfull disk ({mechanism}): failed in {error['stage']} after {stages[error['stage']]['retries']} retries: {error['detail'][:80]}")
            # Nothing half-published: no file under the bundles folder, no record, nothing served.
            assert files_under(service.settings.bundles_dir) == []
            assert bundle_rows(service, name) == 0
            assert client.get(f"/v1/bundles/{name}/1.0.0").status_code == 404
            # The reason reaches the user, the server's paths do not (they are in the worker's log).
            assert str(service.settings.data_dir) not in error["detail"] and "/tmp" not in error["detail"], error
            # No temporary file of an interrupted atomic write is left in the work folder either.
            work = service.settings.work_dir / bake["input_key"]
            assert [path for path in files_under(work) if Path(path).name.startswith(".")] == []

            # Room again: a larger tmpfs, or a worker without the limit. The retry reuses finished stages.
            if mechanism == "tmpfs":
                subprocess.run(["mount", "-o", "remount,size=64m", str(service.settings.bundles_dir)], check=True)
            else:
                worker.stop()
                worker = service.start_worker(concurrency=2)
            assert client.post(f"/v1/bakes/{bake_id}/retry").status_code == 202
            bake = wait_for_bake(client, bake_id, BAKE_TIMEOUT_S, explain=lambda: worker.tail(60))
            assert bake["state"] == "succeeded", bake["error"]
            verify_bundle(service.settings.bundles_dir / name / "1.0.0")
            assert bundle_rows(service, name) == 1
    finally:
        service.stop()
        redis.stop()
        if mounted is not None:
            mounted.__exit__(None, None, None)


def test_an_upload_onto_a_full_blob_store_is_a_503_problem_and_leaves_nothing(sample, tmp_path):
    """The blob store's disk fills while an upload streams in: the client gets a problem document it
    can act on (503, try later), the staging file is gone, no blob and no row were added."""
    with small_tmpfs(tmp_path / "blobs-fs", "1m") as blobs:
        service = make_service(tmp_path / "service", "filesystem://", CROWDBAKE_BLOB_DIR=str(blobs))
        service.start_api()
        try:
            with service.client("upload") as client:
                response = client.post("/v1/assets/cloth", files={"cache": ("cloth.pc2", (sample / "cloth.pc2").read_bytes()),
                                                                  "mesh": ("cloth.obj", (sample / "cloth.obj").read_bytes())})
                assert response.status_code == 503 and response.headers["content-type"] == "application/problem+json", response.text
                assert os.strerror(errno.ENOSPC) in response.json()["detail"]
                assert files_under(blobs) == []
                # A small upload still fits afterwards: the failed one freed its space.
                small = client.post("/v1/assets/textures", files={"file": ("diffuse_00.png", (sample / "textures" / "diffuse_00.png").read_bytes())})
                assert small.status_code == 201, small.text
        finally:
            service.stop()
