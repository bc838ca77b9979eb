"""Work for a request ends when its client leaves.

`run_until_disconnect(request, function, *args)` runs `function(*args, cancel=event)` in the thread pool
like Starlette's `run_in_threadpool`, and meanwhile listens on the request's ASGI channel. The body is
read by then, so the next message the server sends is `http.disconnect`, when the client closes its
connection; the event is then set, the function is expected to stop (an Alembic read kills its Blender
child's process group and removes its temp folder: crowdbake.formats.alembic), and once the thread has
returned the route raises Starlette's `ClientDisconnect`, answered by nobody (crowdbake.api.problems).

Without it, a client that uploads a hostile file and leaves still holds a thread and a child process for
the reader's whole deadline (300 s for Alembic).
"""
from __future__ import annotations

import asyncio
import logging
import threading
from functools import partial
from typing import Any, Callable, TypeVar

from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request

logger = logging.getLogger(__name__)

T = TypeVar("T")


async def _client_left(request: Request) -> None:
    """Returns when the server reports the client gone (call once the body has been read whole)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


async def run_until_disconnect(request: Request, function: Callable[..., T], *args: Any) -> T:
    """`function(*args, cancel=threading.Event())` in the thread pool; its result, or ClientDisconnect once
    it has returned after the client left (the event set). Call after the request body has been read."""
    cancel = threading.Event()
    work = asyncio.ensure_future(run_in_threadpool(partial(function, *args, cancel=cancel)))
    listener = asyncio.ensure_future(_client_left(request))
    try:
        await asyncio.wait({work, listener}, return_when=asyncio.FIRST_COMPLETED)
        if work.done():
            return work.result()
        logger.info("%s %s: the client left; cancelling %s", request.method, request.url.path, getattr(function, "__name__", function))
        cancel.set()
        await asyncio.wait({work})  # the thread ends its work (and children) before the route cleans up
        work.exception()  # retrieved: the cancellation's own exception is expected and not the answer
        raise ClientDisconnect()
    finally:
        cancel.set()  # the route's own task cancelled (server shutdown): the work stops too
        listener.cancel()
