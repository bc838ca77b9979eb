"""The client's connection to a crowdbake server: exit codes, problem documents and retries.

Every request the client makes may be repeated safely: uploads are deduplicated by sha256 (the same
bytes give back the same asset), starting a bake with the same inputs gives back the same bake, and
the rest are reads. So a connection error, or an answer that says the server is restarting or
overloaded (502, 503, 504, 429), is retried with exponential backoff until `retry_for` seconds have
passed without a usable answer; only then does the client give up with EXIT_UNREACHABLE.
"""
from __future__ import annotations

import enum
import logging
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import httpx

logger = logging.getLogger(__name__)


class Exit(enum.IntEnum):
    """`crowdbake submit`'s exit codes (docs/service.md, "Exit codes"), one per thing a script reacts to differently."""

    DONE = 0           # the bake succeeded (and the bundle downloaded and verified, with --download)
    BAKE_FAILED = 1    # the bake failed or was cancelled, or its bundle did not verify
    USAGE = 2          # the command line is wrong: options, missing files, flag combinations
    REJECTED = 3       # the server refused the input: names, parameters, files (4xx other than 401/403)
    AUTH = 4           # no key, a key the server does not know, or a key without the scope
    UNREACHABLE = 5    # no usable answer from the server after retrying, or a server error (5xx)
    TIMED_OUT = 6      # the bake did not end within --timeout (it goes on on the server)


# Answers that mean "try again": overloaded (429), a proxy without its backend (502, 504), not ready (503).
RETRY_STATUSES = frozenset({429, 502, 503, 504})
AUTH_STATUSES = frozenset({401, 403})
# Backoff between attempts: doubling from the first, capped, so a restart of a few seconds is caught
# quickly and a long outage costs one request every BACKOFF_MAX_S.
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 8.0
# A server that refuses the connection before it has ever answered is not restarting: most likely the URL
# is wrong or nothing runs there. So the first contact is tried this many times (0.5 s, then 1 s apart)
# and then reported in one line, instead of waiting out --retry-for; once the server has answered, a
# refused connection is a restart and is retried for --retry-for like any other. 429/503 are always retried.
FIRST_CONTACT_TRIES = 3


class ClientError(Exception):
    """A failure the command reports as one line and `exit_code`; `problem` is the server's problem
    document when there was one (RFC 9457: type, title, status, detail, errors)."""

    def __init__(self, message: str, exit_code: Exit, problem: dict[str, Any] | None = None):
        super().__init__(message)
        self.exit_code = Exit(exit_code)
        self.problem = problem


def problem_of(response: httpx.Response) -> dict[str, Any]:
    """The response's problem document, or one made from its status and text when it has none."""
    try:
        body = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict) and "status" in body:
        return body
    return {"type": "about:blank", "title": f"HTTP {response.status_code}", "status": response.status_code,
            "detail": response.text.strip()[:200]}


def problem_line(problem: dict[str, Any]) -> str:
    """One line from a problem document: its title, detail and first error entry."""
    line = f"{problem.get('title', 'HTTP ' + str(problem.get('status')))}: {problem.get('detail', '')}".rstrip(": ")
    errors = problem.get("errors") or []
    if errors:
        first = errors[0]
        where = " ".join(str(first[key]) for key in ("file", "where") if first.get(key))
        line += f" [{first.get('field', '?')}{' ' + where if where else ''}: {first.get('message', '')}]"
        if len(errors) > 1:
            line += f" (+{len(errors) - 1} more)"
    return line


def exit_code_for_status(status: int) -> Exit:
    if status in AUTH_STATUSES:
        return Exit.AUTH
    if status >= 500:
        return Exit.UNREACHABLE
    return Exit.REJECTED


def backoff_delays(first: float = BACKOFF_FIRST_S, most: float = BACKOFF_MAX_S):
    """first, 2·first, 4·first, ... capped at `most` (seconds), forever."""
    delay = first
    while True:
        yield delay
        delay = min(delay * 2, most)


@dataclass
class Server:
    """An httpx client on one server with the retry policy above.

    `say` receives one line per retry (the command prints it on stderr), `sleep` and `clock` are
    time.sleep and time.monotonic except in tests of the policy itself."""

    client: httpx.Client
    retry_for: float
    say: Callable[[str], None] = lambda line: print(line, file=sys.stderr, flush=True)
    sleep: Callable[[float], None] = time.sleep
    clock: Callable[[], float] = time.monotonic
    retries: int = field(default=0, init=False)
    answered: bool = field(default=False, init=False)  # whether the server has answered once (see FIRST_CONTACT_TRIES)

    @property
    def url(self) -> str:
        return str(self.client.base_url)

    def request(self, method: str, path: str, what: str, *, accept: frozenset[int] = frozenset(), stream: bool = False,
                **make_kwargs: Callable[[], Any] | Any) -> httpx.Response:
        """Send the request until it gets an answer that is not worth retrying; raise ClientError for
        an error answer (unless its status is in `accept`). Keyword values that are callables are
        called for every attempt (files to reopen); the rest are passed as they are. With `stream`,
        a successful answer's body is left unread (iterate it, then close the response)."""
        deadline = self.clock() + self.retry_for
        delays = backoff_delays()
        tries = 0
        while True:
            tries += 1
            kwargs = {name: value() if callable(value) else value for name, value in make_kwargs.items()}
            try:
                response = self.client.send(self.client.build_request(method, path, **kwargs), stream=stream)
                if stream and response.status_code >= 400:
                    response.read()
                reason = None if response.status_code not in RETRY_STATUSES else f"HTTP {response.status_code} {problem_of(response).get('detail', '')}".strip()
            except httpx.ConnectError as error:  # refused, DNS: nobody there, or a server restarting
                if not self.answered and tries >= FIRST_CONTACT_TRIES:
                    cause = "connection refused" if "refused" in str(error).lower() else str(error)
                    raise ClientError(f"cannot connect to {self.url}: {cause}", Exit.UNREACHABLE) from None
                response, reason = None, f"{type(error).__name__}: {error}"
            except httpx.TransportError as error:  # reset, timeouts: the server is not there (yet)
                response, reason = None, f"{type(error).__name__}: {error}"
            finally:
                for value in kwargs.get("files", {}).values() if isinstance(kwargs.get("files"), dict) else ():
                    _close(value)
            if response is not None:
                self.answered = True
            if reason is None:
                break
            delay = next(delays)
            if self.clock() + delay > deadline:
                if response is not None:
                    raise ClientError(f"{what}: {problem_line(problem_of(response))} (retried for {self.retry_for:.0f} s)", Exit.UNREACHABLE, problem_of(response))
                raise ClientError(f"{what}: cannot reach {self.url} ({reason}; retried for {self.retry_for:.0f} s)", Exit.UNREACHABLE)
            self.retries += 1
            self.say(f"{what}: {reason}; retrying in {delay:.1f} s")
            self.sleep(delay)
        if response.status_code >= 400 and response.status_code not in accept:
            problem = problem_of(response)
            raise ClientError(f"{what}: {problem_line(problem)}", exit_code_for_status(response.status_code), problem)
        return response


def _close(file_value: Any) -> None:
    """Close the handle of an httpx `files` entry: a handle, or a (name, handle[, type]) tuple."""
    handle = file_value[1] if isinstance(file_value, tuple) else file_value
    if hasattr(handle, "close"):
        handle.close()


def check_service_root(server: Server) -> None:
    """Raise ClientError (USAGE) when no crowdbake service answers at the server URL itself: a URL with a
    path the service does not have (`.../v1`, a proxy's other app) answers 404 to everything, which would
    otherwise read as the service rejecting the input."""
    answer = server.request("GET", "/health", "checking the server URL", accept=frozenset({404}))
    if answer.status_code == 404:
        raise ClientError(f"--server {server.url}: no crowdbake service answers there (GET {server.url.rstrip('/')}/health: 404); "
                          "give the service's root URL, such as http://HOST:8000, without /v1", Exit.USAGE)

