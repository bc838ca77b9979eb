"""Slow clients against a real uvicorn over raw sockets: connections that never finish their headers are
closed after the header deadline, and an upload whose body trickles in is answered 408 and leaves no
staging file. Settings: 2 s for headers, bodies at least 1 KiB/s after 1 s of grace."""
from __future__ import annotations

import socket
import time

import pytest

from service_fixtures import free_port, local_api_key, service_env, start_api

HEADER_TIMEOUT_S = 2.0


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from crowdbake.settings import Settings

    root = tmp_path_factory.mktemp("slow")
    key = local_api_key(root / "data", "upload", "slow")
    settings = Settings(data_dir=root / "data")
    env = service_env(root / "data", "filesystem://", CROWDBAKE_HEADER_TIMEOUT_S=str(HEADER_TIMEOUT_S),
                      CROWDBAKE_BODY_MIN_BYTES_PER_S="1024", CROWDBAKE_BODY_GRACE_S="1")
    port = free_port()
    process = start_api(env, port, root / "api.log")
    yield port, key, settings
    process.stop()


def _closed_within(sock: socket.socket, seconds: float) -> bool:
    """True when the server closes `sock` (recv returns b'' or the connection resets) within `seconds`."""
    sock.settimeout(seconds)
    try:
        while True:
            if sock.recv(4096) == b"":
                return True
    except ConnectionResetError:
        return True
    except socket.timeout:
        return False


def test_connections_with_incomplete_headers_are_closed(server):
    port, _, _ = server
    started = time.monotonic()
    sockets = []
    for k in range(20):
        sock = socket.create_connection(("127.0.0.1", port))
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * k)  # never the blank line
        sockets.append(sock)
    # A client dribbling a byte now and then does not reset the deadline.
    for _ in range(3):
        time.sleep(0.5)
        sockets[0].sendall(b"b")
    closed = [_closed_within(sock, HEADER_TIMEOUT_S + 3) for sock in sockets]
    for sock in sockets:
        sock.close()
    assert all(closed) and time.monotonic() - started < HEADER_TIMEOUT_S + 4
    # The server still answers others.
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        assert sock.recv(64).startswith(b"HTTP/1.1 200")


def trickle(port: int, request: bytes, byte: bytes, while_waiting=lambda: None) -> tuple[bytes, float]:
    """Send `request`, then one `byte` every half second (far below 1 KiB/s) until the server answers or
    15 s pass; (the answer, seconds taken). `while_waiting` runs after each byte."""
    started = time.monotonic()
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(request)
        sock.settimeout(0.5)
        answer = b""
        while time.monotonic() - started < 15 and not answer:
            try:
                sock.sendall(byte)
            except (BrokenPipeError, ConnectionResetError):
                break
            try:
                answer = sock.recv(4096)
            except socket.timeout:
                pass
            while_waiting()
        sock.settimeout(2)
        try:
            answer += sock.recv(4096)
        except (socket.timeout, ConnectionResetError):
            pass
    return answer, time.monotonic() - started


def test_an_upload_trickling_in_is_refused_and_leaves_no_staging_file(server):
    port, key, settings = server
    staging = settings.blob_dir / ".incoming"
    head = b'--x\r\nContent-Disposition: form-data; name="file"; filename="c.glb"\r\n\r\n'
    request = (f"POST /v1/assets/characters HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {key}\r\n"
               f"Content-Type: multipart/form-data; boundary=x\r\nContent-Length: 100000\r\n\r\n").encode() + head
    seen = []
    answer, elapsed = trickle(port, request, b"g", lambda: seen.append(staging.exists() and any(staging.iterdir())))
    assert answer.startswith(b"HTTP/1.1 408"), answer[:200]
    assert b"request-timeout" in answer and elapsed < 6
    assert any(seen)  # the upload had begun its staging file...
    assert not any(staging.iterdir())  # ...and the refusal removed it


def test_a_json_body_trickling_in_is_a_408_too(server):
    """FastAPI reads a JSON body before the route runs and turns any error of that read into a 400 "error
    parsing the body", unless it is an HTTPException: the deadline's refusal is one, so it stays a 408."""
    port, key, _ = server
    request = (f"POST /v1/bakes/check HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {key}\r\n"
               f"Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n{{").encode()
    answer, elapsed = trickle(port, request, b" ")
    assert answer.startswith(b"HTTP/1.1 408") and b"request-timeout" in answer, answer[:300]
    assert elapsed < 6
