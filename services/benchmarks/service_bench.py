"""What the service benchmarks (bench_throughput.py, load_service.py) share: a free loopback port,
the bake states that end a bake, and the small bake they submit."""
from __future__ import annotations

import socket

# Bake states after which nothing more happens to a bake.
FINAL_STATES = ("succeeded", "failed", "cancelled")

# A bake of seconds, not minutes: 2 impostor frames x 4 azimuths x 2 elevations of 32² tiles, so a
# benchmark measures the service (queueing, fan-out, storage) rather than the renderer.
SMALL_BAKE_PARAMS = {"impostor_frames": 2, "azimuths": 4, "elevations_deg": [0, 30], "tile_size": 32,
                     "candidates": 2, "cycle_views": 2}


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS picks it)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]
