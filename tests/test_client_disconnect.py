"""A client that uploads a slow Alembic and leaves ends its Blender child, against a real uvicorn.

Regression: the Blender child reading an uploaded .abc ran in a thread-pool thread bounded only by its
300 s deadline, so a client could start one, close its connection, and start another. The cloth route
now listens for the disconnect while the reader works (crowdbake.api.disconnects) and the reader kills
the child's process group and removes its temp folder (crowdbake.formats.alembic.ReadCancelled).
"""
from __future__ import annotations

import os
import socket
import sys
import time
from pathlib import Path

import pytest

from repo_paths import SHARED_ASSETS
from service_fixtures import free_port, local_api_key, service_env, start_api

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "services" / "tests"))
from test_alembic_hostile import _descendants, _wait_for, slow_alembic  # noqa: E402

# The client leaves this long after Blender starts; the read needs about 10 s in all.
LEAVE_AFTER_S = 1.0
# From the client's close to no Blender: the disconnect, a poll of the reader (0.2 s) and the kill.
GONE_WITHIN_S = 3.0


@pytest.fixture
def server(tmp_path):
    from crowdbake.formats.alembic import alembic_available
    from crowdbake.settings import Settings

    if not alembic_available():
        pytest.skip("the crowdbake[alembic] extra (Blender's bpy) is not installed: pip install -r services/requirements-alembic.txt")
    key = local_api_key(tmp_path / "data", "upload", "leaver")
    settings = Settings(data_dir=tmp_path / "data")
    server_tmp = tmp_path / "server-tmp"  # the API's temp folders, to see that none stays
    server_tmp.mkdir()
    env = service_env(tmp_path / "data", "filesystem://", TMPDIR=str(server_tmp))
    port = free_port()
    process = start_api(env, port, tmp_path / "api.log")
    yield process, port, key, settings, server_tmp
    process.stop()


def test_a_client_leaving_an_alembic_upload_ends_its_blender_child(server, tmp_path):
    process, port, key, settings, server_tmp = server
    source = SHARED_ASSETS / "long_skirt" / "long_skirt.abc"
    if not source.is_file():
        pytest.skip(f"third-party asset long_skirt/long_skirt.abc not found under {SHARED_ASSETS}")
    cache = slow_alembic(source, tmp_path / "slow.abc").read_bytes()
    body = (b'--x\r\nContent-Disposition: form-data; name="cache"; filename="slow.abc"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n" + cache + b"\r\n--x--\r\n")
    request = (f"POST /v1/assets/cloth HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {key}\r\n"
               f"Content-Type: multipart/form-data; boundary=x\r\nContent-Length: {len(body)}\r\n\r\n").encode() + body
    before = set(_descendants(process.popen.pid))
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(request)
        assert _wait_for(lambda: set(_descendants(process.popen.pid)) - before, 20), "Blender never started"
        time.sleep(LEAVE_AFTER_S)
        blender = set(_descendants(process.popen.pid)) - before
        assert blender, "Blender finished before the client left: the test proves nothing"
    left_at = time.monotonic()
    assert _wait_for(lambda: not set(_descendants(process.popen.pid)) - before, GONE_WITHIN_S), \
        f"Blender still runs {GONE_WITHIN_S} s after its client left:\n{process.tail()}"
    seconds = time.monotonic() - left_at
    assert not any(os.path.exists(f"/proc/{pid}") for pid in blender)
    assert _wait_for(lambda: list(server_tmp.iterdir()) == [], 2), list(server_tmp.iterdir())
    staging = settings.blob_dir / ".incoming"
    assert not staging.exists() or list(staging.iterdir()) == []
    assert process.popen.poll() is None and "unhandled error" not in process.log.read_text(errors="replace")
    print(f"Blender gone {seconds:.2f} s after the client left")
