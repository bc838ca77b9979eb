"""Hostile requests against a real uvicorn (the deploy options), each answered in seconds with a 4xx
problem and within a bounded growth of the API process's peak memory (VmHWM, reset before each case).

Bodies (crowdbake.api.request_bodies): a body is bounded by its route before it is read, and read only
once its key verifies. Before, POST /v1/bakes/check read 200 MiB sent without a key (+1 GB of the API's
memory, seconds) before answering 401, and a 6 GiB Content-Length was never answered 413.
"""
from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import pytest

from service_fixtures import free_port, local_api_key, service_env, start_api

MiB = 1 << 20
# The most a hostile request may add to the API process's peak memory.
MEMORY_BUDGET_KIB = 300 * 1024
ANSWER_SECONDS = 5.0


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    keys = {scopes: local_api_key(root / "data", scopes, scopes) for scopes in ("bake", "upload")}
    port = free_port()
    process = start_api(service_env(root / "data", "filesystem://", CROWDBAKE_MAX_UPLOAD_BYTES=str(64 * MiB)), port, root / "api.log")
    yield {"port": port, "pid": process.popen.pid, "keys": keys}
    process.stop()


def _status_kib(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


class PeakMemory:
    """Growth of a process's peak resident memory over a block (Linux: VmHWM, reset through clear_refs)."""

    def __init__(self, pid: int):
        self.pid = pid

    def __enter__(self) -> "PeakMemory":
        Path(f"/proc/{self.pid}/clear_refs").write_text("5")
        self.before = _status_kib(self.pid, "VmRSS")
        return self

    def __exit__(self, *_) -> None:
        self.growth_kib = _status_kib(self.pid, "VmHWM") - self.before


def _head(method: str, path: str, headers: dict[str, str]) -> bytes:
    lines = [f"{method} {path} HTTP/1.1", "Host: 127.0.0.1", *(f"{name}: {value}" for name, value in headers.items())]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def send_until_answered(port: int, head: bytes, chunks, timeout: float = 30) -> tuple[bytes, int, float]:
    """Send `head`, then `chunks` while the server reads them; (the answer, body bytes sent, seconds).
    Stops sending as soon as the server answers or closes."""
    started = time.monotonic()
    sent = 0
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as sock:
        sock.sendall(head)
        sock.setblocking(False)
        answer = b""
        for chunk in chunks:
            try:
                answer += sock.recv(65536)
            except BlockingIOError:
                pass
            except ConnectionResetError:
                break
            if answer:
                break
            try:
                sock.sendall(chunk)
            except BlockingIOError:
                time.sleep(0.01)  # the server is not reading: wait for its answer
            except (BrokenPipeError, ConnectionResetError):
                break
            sent += len(chunk)
        sock.setblocking(True)
        sock.settimeout(timeout)
        try:
            while b"\r\n\r\n" not in answer or not answer.endswith(b"}"):
                more = sock.recv(65536)
                if not more:
                    break
                answer += more
        except (socket.timeout, ConnectionResetError):
            pass
    return answer, sent, time.monotonic() - started


def _zeros(total: int, size: int = 64 * 1024):
    for _ in range(total // size):
        yield b"\0" * size


def _chunked(total: int, size: int = 64 * 1024):
    for _ in range(total // size):
        yield f"{size:x}\r\n".encode() + b" " * size + b"\r\n"
    yield b"0\r\n\r\n"


def _problem(answer: bytes) -> tuple[int, dict]:
    head, _, body = answer.partition(b"\r\n\r\n")
    assert b"content-type: application/problem+json" in head.lower(), answer[:300]
    return int(head.split(b" ", 2)[1]), json.loads(body)


@pytest.mark.parametrize("path", ["/v1/bakes/check", "/v1/bakes", "/v1/assets/characters"])
@pytest.mark.parametrize("key", [None, "cbk_000000000000_" + "A" * 43], ids=["no key", "unknown key"])
@pytest.mark.parametrize("framing", ["chunked", "length"])
def test_a_body_without_a_valid_key_is_refused_before_it_is_read(server, path, key, framing):
    """200 MiB chunked, or 60 MiB announced (within the upload limit), without a valid key: refused
    while the first megabytes are still being sent; 401, or 413 where the announced length is already
    over the route's limit."""
    if framing == "chunked":
        headers, chunks, expected = {"Transfer-Encoding": "chunked"}, _chunked(200 * MiB), 401
    else:
        headers, chunks = {"Content-Length": str(60 * MiB)}, _zeros(60 * MiB)
        expected = 401 if path.startswith("/v1/assets/") else 413
    headers["Content-Type"] = "multipart/form-data; boundary=x" if path.startswith("/v1/assets/") else "application/json"
    if key is not None:
        headers["Authorization"] = f"Bearer {key}"
    with PeakMemory(server["pid"]) as memory:
        answer, sent, seconds = send_until_answered(server["port"], _head("POST", path, headers), chunks)
    status, problem = _problem(answer)
    assert status == expected and problem["type"] == ("/problems/unauthorized" if expected == 401 else "/problems/payload-too-large"), problem
    assert seconds < ANSWER_SECONDS and sent < 32 * MiB, (seconds, sent)
    assert memory.growth_kib < MEMORY_BUDGET_KIB


@pytest.mark.parametrize("key", [None, "bake"])
@pytest.mark.parametrize("path", ["/v1/bakes/check", "/v1/bakes", "/v1/assets/characters"])
def test_a_content_length_over_the_routes_limit_is_413_at_once(server, path, key):
    """6 GiB announced: 413 before a byte of the body is read, with or without a key."""
    headers = {"Content-Type": "application/json", "Content-Length": str(6 << 30)}
    if key is not None:
        headers["Authorization"] = f"Bearer {server['keys'][key]}"
    answer, _, seconds = send_until_answered(server["port"], _head("POST", path, headers), [])
    status, problem = _problem(answer)
    assert (status, problem["type"]) == (413, "/problems/payload-too-large"), problem
    assert str(6 << 30) in problem["detail"] and seconds < ANSWER_SECONDS


def test_a_json_route_takes_a_megabyte_not_the_upload_limit(server):
    """2 MiB announced to POST /v1/bakes with a valid key: over the JSON limit (1 MiB), under the upload limit."""
    headers = {"Content-Type": "application/json", "Content-Length": str(2 * MiB), "Authorization": f"Bearer {server['keys']['bake']}"}
    answer, _, _ = send_until_answered(server["port"], _head("POST", "/v1/bakes", headers), [])
    status, problem = _problem(answer)
    assert status == 413 and str(1 * MiB) in problem["detail"], problem


@pytest.mark.parametrize("path", ["/v1/bakes/check", "/v1/bakes"])
def test_a_chunked_body_is_cut_off_at_the_limit_while_streaming(server, path):
    """No Content-Length: a valid key streaming 200 MiB of JSON whitespace is stopped at 1 MiB."""
    headers = {"Content-Type": "application/json", "Transfer-Encoding": "chunked", "Authorization": f"Bearer {server['keys']['bake']}"}
    with PeakMemory(server["pid"]) as memory:
        answer, sent, seconds = send_until_answered(server["port"], _head("POST", path, headers), _chunked(200 * MiB))
    status, problem = _problem(answer)
    assert (status, problem["type"]) == (413, "/problems/payload-too-large"), problem
    assert seconds < ANSWER_SECONDS and sent < 32 * MiB, (seconds, sent)
    assert memory.growth_kib < MEMORY_BUDGET_KIB


def test_a_small_body_with_a_valid_key_still_reaches_the_route(server):
    body = json.dumps({"name": "walker", "version": "1.0.0", "inputs": {"character": ["0" * 64]}}).encode()
    headers = {"Content-Type": "application/json", "Content-Length": str(len(body)), "Authorization": f"Bearer {server['keys']['bake']}",
               "Connection": "close"}
    answer, _, _ = send_until_answered(server["port"], _head("POST", "/v1/bakes/check", headers) + body, [])
    assert answer.startswith(b"HTTP/1.1 204"), answer[:300]


# ---------------------------------------------------------------------------------------- timelines


def _claiming_frames(total: int) -> bytes:
    """No rows, one segment over `total` frames: a few hundred bytes claiming every frame."""
    return json.dumps({"fps": 24, "total_frames": total, "segments": [
        {"clip": "Walk", "first_frame": 0, "last_frame": total - 1, "pure_first_frame": 0, "pure_last_frame": total - 1, "clip_frames": 24}]}).encode()


def _overlapping_segments(count: int, total: int) -> bytes:
    """`count` segments, segment k starting at frame k and running to the last frame: segments x frames of
    work for a reader that fills each segment's frames."""
    segments = [{"clip": f"c{k}", "first_frame": k, "last_frame": total - 1, "pure_first_frame": k, "pure_last_frame": k, "clip_frames": 24}
                for k in range(count)]
    segments[-1]["pure_last_frame"] = total - 1
    return json.dumps({"fps": 24, "total_frames": total, "segments": segments}).encode()


def _back_to_back_segments(count: int, total: int) -> bytes:
    """A valid timeline at the frame limit: `count` clips, each playing total / count frames once."""
    step = total // count
    segments = [{"clip": f"clip {k}", "first_frame": k * step, "last_frame": (k + 1) * step - 1, "pure_first_frame": k * step,
                 "pure_last_frame": (k + 1) * step - 1, "clip_frames": 24} for k in range(count)]
    return json.dumps({"fps": 24, "total_frames": count * step, "segments": segments}).encode()


TIMELINES = {
    # Was 201 with +1.2-1.5 GB of the API's memory (a clip frame and two temporaries per claimed frame).
    "total_frames 2^26, no rows": (_claiming_frames(1 << 26), 422, "/total_frames"),
    "total_frames 2^31 - 1, no rows": (_claiming_frames((1 << 31) - 1), 422, "/total_frames"),
    # Was 97 s of the API's CPU: every segment's frames filled, 10,000 x 10^6.
    "10,000 segments each to frame 10^6": (_overlapping_segments(10_000, 10**6 + 1), 422, "/total_frames"),
    "10,000 segments each to the last of 100,000 frames": (_overlapping_segments(10_000, 100_000), 422, "/segments/2/first_frame"),
    "10,000 clips over 100,000 frames (valid)": (_back_to_back_segments(10_000, 100_000), 201, None),
}


@pytest.mark.parametrize("case", list(TIMELINES))
def test_a_timeline_claiming_frames_costs_seconds_and_bounded_memory(server, case):
    import httpx

    document, status, pointer = TIMELINES[case]
    with PeakMemory(server["pid"]) as memory, httpx.Client(base_url=f"http://127.0.0.1:{server['port']}", timeout=60) as client:
        started = time.monotonic()
        response = client.post("/v1/assets/timelines", files={"timeline": ("timeline.json", document)},
                               headers={"Authorization": f"Bearer {server['keys']['upload']}"})
        seconds = time.monotonic() - started
    assert response.status_code == status, response.text[:500]
    if pointer is not None:
        assert response.json()["errors"][0]["where"] == pointer, response.text[:500]
    assert seconds < ANSWER_SECONDS, seconds
    assert memory.growth_kib < MEMORY_BUDGET_KIB, memory.growth_kib
