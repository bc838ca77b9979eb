"""Round three's hostile uploads against the in-process API (crowdbake's real app, filesystem broker):
status, seconds and the API process's peak resident memory above its level before each request (VmHWM,
reset per request through /proc/self/clear_refs). Run: PYTHONPATH=services:services/tests python
services/benchmarks/bench_hostile_round3.py"""
from __future__ import annotations

import json
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _rss_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def glb_eight_views_of_one_stream(claim: int = 256 << 20, stream: int = 4 << 20) -> bytes:
    """Eight EXT_meshopt_compression views, each read by an accessor, all on one `stream`-byte stream,
    each claiming `claim` decoded bytes."""
    stride, count = 16, claim // 16
    views = [{"buffer": 1, "byteLength": claim, "byteStride": stride,
              "extensions": {"EXT_meshopt_compression": {"buffer": 0, "byteOffset": 0, "byteLength": stream,
                                                         "byteStride": stride, "count": count, "mode": "ATTRIBUTES"}}} for _ in range(8)]
    accessors = [{"bufferView": k, "componentType": 5126, "count": count, "type": "VEC4"} for k in range(8)]
    document = {"asset": {"version": "2.0"}, "extensionsUsed": ["EXT_meshopt_compression"], "extensionsRequired": ["EXT_meshopt_compression"],
                "buffers": [{"byteLength": stream}, {"byteLength": claim, "extensions": {"EXT_meshopt_compression": {"fallback": True}}}],
                "bufferViews": views, "accessors": accessors,
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}], "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    blob = bytes(stream)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def abc_claiming(samples: int) -> bytes:
    from test_alembic_hostile import _rewrite_animated_sampling

    source = Path("/work/shared/assets/long_skirt/long_skirt.abc")
    target = Path(tempfile.mkdtemp()) / "claims.abc"
    return _rewrite_animated_sampling(source, target, max_samples=samples).read_bytes()


def main() -> int:
    from service_fixtures import make_api, obj_bytes, tiny_cloth
    from test_studio_inputs import _mdd_bytes

    folder = Path(tempfile.mkdtemp(prefix="bench-round3-"))
    api = make_api(folder, max_upload_bytes=64 << 20)
    points, faces = tiny_cloth(frames=12)
    cycle = {"start_frame": 2, "cycle_frames": 6, "end_frame": 8, "closing": {"method": "crossfade"}}
    cases = [
        ("glb: 8 meshopt views of one 4 MB stream, 256 MiB each", "/v1/assets/characters", {"file": ("c.glb", glb_eight_views_of_one_stream())}),
        ("abc: time sampling claiming 2^32-1 samples", "/v1/assets/cloth", {"cache": ("c.abc", abc_claiming(2**32 - 1))}),
        ("abc: 2,000 samples claimed", "/v1/assets/cloth", {"cache": ("c.abc", abc_claiming(2_000))}),
        ("cycle.json: input.fps NaN", "/v1/assets/cycles", {"cycle": ("cycle.json", json.dumps({**cycle, "input": {"fps": float("nan")}}).encode())}),
        ("cycle.json: a 5,000-digit start_frame", "/v1/assets/cycles", {"cycle": ("cycle.json", b'{"start_frame": ' + b"9" * 5000 + b', "cycle_frames": 6}')}),
        ("mdd: 1e30 fps", "/v1/assets/cloth", {"cache": ("c.mdd", _mdd_bytes(points, 1e30, folder)), "mesh": ("c.obj", obj_bytes(points[0], faces, folder))}),
        ("mdd: 1e-30 fps", "/v1/assets/cloth", {"cache": ("c.mdd", _mdd_bytes(points, 1e-30, folder)), "mesh": ("c.obj", obj_bytes(points[0], faces, folder))}),
    ]
    print("| input | status | seconds | peak MiB |")
    for name, route, files in cases:
        Path("/proc/self/clear_refs").write_text("5")
        before = _rss_kib("VmRSS")
        start = time.perf_counter()
        response = api.client.post(route, files=files, headers=api.auth("upload"))
        seconds = time.perf_counter() - start
        peak = (_rss_kib("VmHWM") - before) / 1024
        where = (response.json().get("errors") or [{}])[0] if response.headers.get("content-type", "").startswith("application/problem") else {}
        print(f"| {name} | {response.status_code} | {seconds:.2f} | +{peak:.1f} | {where.get('where', '')} {where.get('message', '')[:90]}")
    leftovers = list(Path(tempfile.gettempdir()).glob("crowdbake-abc-*"))
    print("temp folders left:", leftovers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
