"""Slow clients cannot hold the API: headers have a deadline, bodies a minimum rate and a deadline.

A connection that opens and sends half a request line, or a body at one byte every ten seconds, costs
the attacker nothing and the server a connection, a task and (for an upload) a staging file, for as
long as the client likes. Two guards:

* `HeaderTimeoutProtocol`, uvicorn's h11 protocol with a deadline (CROWDBAKE_HEADER_TIMEOUT_S) from the
  moment a connection opens, or a response completes, until a request's headers are in. uvicorn's own
  keep-alive timer does not cover this: it is not armed on a new connection and every byte resets it.
  Select it with `uvicorn --http crowdbake.api.slow_clients:HeaderTimeoutProtocol` (`crowdbake serve`
  and the deploy manifests do).
* `MinimumBodyRate`, an ASGI middleware around the app: each read of the request body waits at most
  until the body would fall below CROWDBAKE_BODY_MIN_BYTES_PER_S (after CROWDBAKE_BODY_GRACE_S), or
  past CROWDBAKE_BODY_MAX_SECONDS in all. Then the read raises a 408 (an HTTPException, which FastAPI
  passes on from its read of a JSON body, where any other error becomes a 400); the upload's reader
  discards its staging files on the way out (crowdbake.api.uploads.read_multipart), and the response
  closes the connection.
"""
from __future__ import annotations

import asyncio
import logging
import time

from starlette.exceptions import HTTPException
from uvicorn.protocols.http.h11_impl import H11Protocol

logger = logging.getLogger(__name__)


def body_deadline(received: int, min_bytes_per_s: float, grace_s: float, max_s: float) -> float:
    """Seconds after the body's first read by which `received` bytes must have grown: the grace period
    plus what the bytes so far buy at the minimum rate, never past `max_s`."""
    if min_bytes_per_s <= 0:
        return max_s
    return min(grace_s + received / min_bytes_per_s, max_s)


class MinimumBodyRate:
    """ASGI middleware: a request body slower than a minimum rate, or longer than a deadline, is a 408."""

    def __init__(self, app, min_bytes_per_s: float, grace_s: float, max_s: float):
        self.app = app
        self.min_bytes_per_s, self.grace_s, self.max_s = min_bytes_per_s, grace_s, max_s

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = time.monotonic()
        state = {"received": 0, "done": False}

        async def guarded_receive():
            if state["done"]:  # the body is in; later reads wait for a disconnect, which has no deadline
                return await receive()
            remaining = body_deadline(state["received"], self.min_bytes_per_s, self.grace_s, self.max_s) - (time.monotonic() - started)
            try:
                message = await asyncio.wait_for(receive(), max(remaining, 0.0))
            except asyncio.TimeoutError:
                elapsed = time.monotonic() - started
                logger.warning("%s %s: request body too slow (%d bytes in %.1f s); closing", scope["method"], scope["path"], state["received"], elapsed)
                raise HTTPException(
                    408,
                    f"the request body arrived too slowly: {state['received']} bytes in {elapsed:.0f} s "
                    f"(at least {self.min_bytes_per_s:.0f} bytes/s after {self.grace_s:.0f} s, all of it within {self.max_s:.0f} s)",
                    headers={"Connection": "close"},
                ) from None
            if message["type"] == "http.request":
                state["received"] += len(message.get("body", b""))
                state["done"] = not message.get("more_body", False)
            else:
                state["done"] = True
            return message

        return await self.app(scope, guarded_receive, send)


class HeaderTimeoutProtocol(H11Protocol):
    """uvicorn's h11 protocol, closing connections whose request headers do not arrive in time."""

    header_timeout_s: float | None = None  # None: read from the settings (CROWDBAKE_HEADER_TIMEOUT_S)

    def _arm_header_deadline(self) -> None:
        self._cancel_header_deadline()
        timeout = self.header_timeout_s
        if timeout is None:
            from crowdbake.settings import get_settings

            timeout = get_settings().header_timeout_s
        self._header_deadline = self.loop.call_later(timeout, self._header_deadline_passed)

    def _cancel_header_deadline(self) -> None:
        deadline = getattr(self, "_header_deadline", None)
        if deadline is not None:
            deadline.cancel()
            self._header_deadline = None

    def _header_deadline_passed(self) -> None:
        self._header_deadline = None
        if self.cycle is None or self.cycle.response_complete:  # still waiting for the headers
            if not self.transport.is_closing():
                logger.info("closing a connection from %s: no complete request headers in time", self.client)
                self.transport.close()

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_header_deadline()

    def connection_lost(self, exc) -> None:
        self._cancel_header_deadline()
        super().connection_lost(exc)

    def handle_events(self) -> None:
        before = self.cycle
        super().handle_events()
        if self.cycle is not before and self.cycle is not None:  # a request's headers arrived
            self._cancel_header_deadline()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and (self.cycle is None or self.cycle.response_complete):
            self._arm_header_deadline()
