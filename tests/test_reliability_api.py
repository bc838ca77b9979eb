"""The API process dies (SIGKILL) or is stopped (SIGTERM) in the middle of an upload: no asset is half
stored, and once it is back the same upload succeeds.

Real processes: uvicorn on a temporary data folder (the filesystem broker: no bake runs here). The
client sends the multipart headers and half the body over a raw socket, waits until the server has
staged those bytes, and the test then signals the server.

Regression (fixed in crowdbake.storage.blobs): a SIGKILLed API leaves its half-written staging file in
the blob store's `.incoming/` folder, and nothing ever removed it, so every crash mid-upload leaked
disk. Opening the blob store now sweeps staging files untouched for STALE_STAGING_S (a day).
"""
from __future__ import annotations

import hashlib
import os
import signal
import socket
import time

import pytest
from sqlalchemy import func, select

from crowdbake.storage.blobs import STALE_STAGING_S
from reliability_fixtures import files_under, make_service

# slow: a real server and worker (or browser) for tens of seconds; scripts/test.sh runs it with CROWDBAKE_SLOW_TESTS=1, as CI does
pytestmark = [pytest.mark.integration, pytest.mark.slow]

BOUNDARY = "reliabilityboundary"


def multipart(field: str, filename: str, data: bytes) -> bytes:
    return (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{field}\"; filename=\"{filename}\"\r\n"
            f"Content-Type: application/octet-stream\r\n\r\n").encode() + data + f"\r\n--{BOUNDARY}--\r\n".encode()


def staged_bytes(service) -> int:
    staging = service.settings.blob_dir / ".incoming"
    return sum(path.stat().st_size for path in staging.glob("upload-*")) if staging.is_dir() else 0


def asset_count(service) -> int:
    from crowdbake.storage.models import Asset

    with service.sessions()() as session:
        return session.scalar(select(func.count()).select_from(Asset))


@pytest.fixture
def service(tmp_path):
    service = make_service(tmp_path / "service", "filesystem://")
    service.start_api()
    try:
        yield service
    finally:
        service.stop()


def send_half(service, body: bytes, head: bytes) -> socket.socket:
    """Open a connection, send the headers and half the body, and return once the server has staged
    part of it (it is streaming the file part into the blob store's staging folder)."""
    sock = socket.create_connection(("127.0.0.1", service.port), timeout=30)
    half = len(body) // 2
    sock.sendall(head + body[:half])
    deadline = time.monotonic() + 10
    while staged_bytes(service) < half // 2:
        assert time.monotonic() < deadline, "the server never staged the first half of the upload"
        time.sleep(0.02)
    return sock


@pytest.mark.parametrize("fault", ["sigkill", "sigterm-client-leaves", "sigterm-client-finishes"])
def test_api_stops_mid_upload_then_a_retry_succeeds(service, sample, fault):
    """SIGKILL: the process dies at once. SIGTERM: uvicorn drains in-flight requests, so a client that
    goes away has its staged bytes discarded, and one that finishes its body gets its asset (201)."""
    glb = (sample / "character.glb").read_bytes()
    digest = hashlib.sha256(glb).hexdigest()
    body = multipart("file", "character.glb", glb)
    head = (f"POST /v1/assets/characters HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {service.keys['upload']}\r\n"
            f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\nContent-Length: {len(body)}\r\n\r\n").encode()
    sock = send_half(service, body, head)
    finished = None
    try:
        service.api.popen.send_signal(signal.SIGKILL if fault == "sigkill" else signal.SIGTERM)
        if fault == "sigterm-client-finishes":
            sock.sendall(body[len(body) // 2:])
            finished = sock.recv(65536)
        elif fault == "sigterm-client-leaves":
            time.sleep(0.5)
    finally:
        sock.close()
    service.api.popen.wait(timeout=30)

    if fault == "sigterm-client-finishes":
        assert finished.startswith(b"HTTP/1.1 201"), finished[:200]
        assert asset_count(service) == 1
    else:
        # Nothing of the interrupted upload is an asset: no committed blob, no row.
        assert files_under(service.settings.blob_dir / "sha256") == []
        assert asset_count(service) == 0
    if fault == "sigterm-client-leaves":
        assert staged_bytes(service) == 0  # the server discarded its own staging file

    if fault == "sigkill":
        # A killed process cannot clean up: its staging file stays. Dated a day back (a crash long ago),
        # the next start sweeps it; a fresh one might be a live upload of another API process and stays.
        leftovers = sorted((service.settings.blob_dir / ".incoming").glob("upload-*"))
        assert len(leftovers) == 1
        old = time.time() - STALE_STAGING_S - 60
        os.utime(leftovers[0], (old, old))
        fresh = service.settings.blob_dir / ".incoming" / "upload-inflight"
        fresh.write_bytes(b"a live upload of another process")

    service.start_api()  # same port, same data folder
    with service.client("upload") as client:
        response = client.post("/v1/assets/characters", files={"file": ("character.glb", glb)})
    assert response.status_code == (200 if fault == "sigterm-client-finishes" else 201), response.text
    assert response.json()["digest"] == digest and response.json()["files"]["file"]["size"] == len(glb)
    assert files_under(service.settings.blob_dir / "sha256") == [f"{digest[:2]}/{digest[2:4]}/{digest}"]
    assert asset_count(service) == 1
    leftovers = sorted(path.name for path in (service.settings.blob_dir / ".incoming").glob("upload-*"))
    assert leftovers == (["upload-inflight"] if fault == "sigkill" else [])
