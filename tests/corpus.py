"""A corpus of broken uploads and requests, generated in code from the project's own writers (nothing
third-party is committed): truncated and garbled GLB, PC2 whose counts lie, OBJ with out-of-range
indices, NaN vertices, huge declared sizes, zip bombs, zip entries that escape their folder, wrong
formats and content types, oversize bodies.

Each `Case` is one request and what a correct server answers: a 4xx status (a set when several are
right) and the problem type. `corpus(tmp)` builds them all; tests/test_bad_input.py sends each one
and checks that nothing was stored.
"""
from __future__ import annotations

import io
import json
import stat
import struct
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from service_fixtures import obj_bytes, obj_sequence_zip, pc2_bytes, png_bytes, tiny_character_glb, tiny_cloth

# Limits the corpus is built against (tests/test_bad_input.py configures the app with them).
MAX_UPLOAD_BYTES = 1 << 20
MAX_ZIP_ENTRIES = 40
MAX_ZIP_UNCOMPRESSED_BYTES = 8 << 20
MAX_ZIP_RATIO = 50.0
MAX_TEXTURE_PIXELS = 256 * 256
FRAMES = 12  # the tiny cloth's frames: two cycles of 6


@dataclass
class Case:
    """One bad request: multipart `files` (field -> (filename, bytes[, content type])) and `data`, or a
    JSON body, or raw `content` with `headers`; the answer must be `status` and `problem`."""

    name: str
    path: str
    status: int | frozenset[int]
    problem: str | None = None
    files: dict[str, tuple] | None = None
    data: dict[str, str] | None = None
    json_body: Any = None
    content: bytes | None = None
    headers: dict[str, str] = field(default_factory=dict)
    method: str = "POST"

    @property
    def statuses(self) -> frozenset[int]:
        return self.status if isinstance(self.status, frozenset) else frozenset({self.status})


# ------------------------------------------------------------------------------------------- GLB


def split_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, BIN chunk) of a GLB written by crowdbake.formats.gltf.encode_character."""
    json_length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20 : 20 + json_length])
    bin_offset = 20 + json_length
    bin_length = struct.unpack_from("<I", data, bin_offset)[0]
    return document, data[bin_offset + 8 : bin_offset + 8 + bin_length]


def make_glb(document: dict, binary: bytes, declared_length: int | None = None) -> bytes:
    """A GLB from a JSON document and a BIN chunk (padded as the spec says)."""
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    total = 12 + len(body)
    return b"glTF" + struct.pack("<II", 2, total if declared_length is None else declared_length) + body


def _position_accessor(document: dict) -> dict:
    primitive = document["meshes"][0]["primitives"][0]
    return document["accessors"][primitive["attributes"]["POSITION"]]


def glb_cases() -> list[tuple[str, bytes, str]]:
    """(name, bytes, problem) of broken characters."""
    good = tiny_character_glb()
    document, binary = split_glb(good)
    cases: list[tuple[str, bytes, str]] = []
    # Truncations: the header, inside the JSON chunk, inside the BIN chunk, one byte short.
    for cut in sorted({4, 11, 12, 19, 20, 40, len(good) // 2, len(good) - 9, len(good) - 1}):
        cases.append((f"glb truncated to {cut} bytes", good[:cut], "invalid-file"))
    cases.append(("glb with a bad magic", b"glTX" + good[4:], "invalid-file"))
    cases.append(("glb version 1", good[:4] + struct.pack("<I", 1) + good[8:], "invalid-file"))
    cases.append(("glb whose length field says 2 GiB", good[:8] + struct.pack("<I", 0x7FFFFFFF) + good[12:], "invalid-file"))
    cases.append(("glb whose JSON chunk claims 2 GiB", good[:12] + struct.pack("<I", 0x7FFFFFF0) + good[16:], "invalid-file"))
    garbled = bytearray(good)
    garbled[20:60] = b"\xff" * 40
    cases.append(("glb with garbage in its JSON", bytes(garbled), "invalid-file"))
    cases.append(("glb whose JSON is a list", make_glb([1, 2, 3], binary), "invalid-file"))  # type: ignore[arg-type]

    def edited(name: str, edit) -> None:
        copy = json.loads(json.dumps(document))
        edit(copy)
        cases.append((name, make_glb(copy, binary), "invalid-file"))

    edited("glb with an accessor count of 10^9", lambda d: _position_accessor(d).update(count=10**9))
    edited("glb with a buffer of 2^40 bytes", lambda d: d["buffers"][0].update(byteLength=1 << 40))
    edited("glb with a bufferView past its buffer", lambda d: d["bufferViews"][0].update(byteOffset=1 << 30))
    edited("glb with a negative accessor offset", lambda d: _position_accessor(d).update(byteOffset=-64))
    edited("glb with a string accessor count", lambda d: _position_accessor(d).update(count="4"))
    edited("glb whose accessors are not a list", lambda d: d.update(accessors={"0": 1}))
    edited("glb whose skin names a missing node", lambda d: d["skins"][0].update(joints=[999]))
    edited("glb with a node cycle", lambda d: d["nodes"][0].update(children=[0]))
    edited("glb with an external buffer uri", lambda d: d["buffers"][0].update(uri="../../../etc/passwd"))
    edited("glb with no meshes", lambda d: d.pop("meshes"))
    edited("glb with asset version 1.0", lambda d: d["asset"].update(version="1.0"))
    edited("glb whose nodes are null", lambda d: d.update(nodes=None))
    edited("glb whose skin joints are a list of lists", lambda d: d["skins"][0].update(joints=[[0]]))
    edited("glb whose first accessor is a string", lambda d: d["accessors"].__setitem__(0, "POSITION"))

    # NaN vertex positions: the POSITION accessor's floats in the BIN chunk overwritten with NaN.
    accessor = _position_accessor(document)
    view = document["bufferViews"][accessor["bufferView"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    poisoned = bytearray(binary)
    poisoned[start : start + 12] = np.full(3, np.nan, "<f4").tobytes()
    cases.append(("glb with NaN vertex positions", make_glb(document, bytes(poisoned)), "invalid-file"))
    # An index past the vertices: the indices accessor's first element in the BIN chunk set to 999.
    indices = document["accessors"][document["meshes"][0]["primitives"][0]["indices"]]
    view = document["bufferViews"][indices["bufferView"]]
    start = view.get("byteOffset", 0) + indices.get("byteOffset", 0)
    width = {5121: 1, 5123: 2, 5125: 4}[indices["componentType"]]
    out_of_range = bytearray(binary)
    out_of_range[start : start + width] = min(999, 256**width - 1).to_bytes(width, "little")
    cases.append(("glb with an index past the vertices", make_glb(document, bytes(out_of_range)), "invalid-file"))
    return cases


# ---------------------------------------------------------------------------------------- cloth


def pc2_header(points: int, samples: int, start: float = 0.0, rate: float = 1.0, magic: bytes = b"POINTCACHE2\0", version: int = 1) -> bytes:
    return struct.pack("<12siiffi", magic, version, points, start, rate, samples)


def cloth_cases(tmp: Path) -> list[tuple[str, dict[str, tuple], str]]:
    """(name, multipart files, problem) of broken cloth uploads (PC2 + OBJ)."""
    points, faces = tiny_cloth(frames=FRAMES)
    cache = pc2_bytes(points)
    mesh = obj_bytes(points[0], faces, tmp)
    payload = cache[32:]
    vertices = points.shape[1]
    cases: list[tuple[str, bytes, bytes, str]] = [
        ("pc2 truncated in its header", cache[:20], mesh, "invalid-file"),
        ("pc2 one float short", cache[:-4], mesh, "invalid-file"),
        ("pc2 with trailing bytes", cache + b"\0" * 12, mesh, "invalid-file"),
        ("pc2 that promises 2^31-1 samples", pc2_header(vertices, 2**31 - 1) + payload, mesh, "invalid-file"),
        ("pc2 that promises 2^24 points", pc2_header(1 << 24, FRAMES) + payload, mesh, "invalid-file"),
        ("pc2 with a negative point count", pc2_header(-vertices, FRAMES) + payload, mesh, "invalid-file"),
        ("pc2 whose counts multiply to the size but lie", pc2_header(vertices * FRAMES, 1) + payload, mesh, "invalid-file"),
        ("pc2 with a zero sample rate", pc2_header(vertices, FRAMES, rate=0.0) + payload, mesh, "invalid-file"),
        ("pc2 with an infinite start frame", pc2_header(vertices, FRAMES, start=float("inf")) + payload, mesh, "invalid-file"),
        ("pc2 version 2", pc2_header(vertices, FRAMES, version=2) + payload, mesh, "invalid-file"),
        ("pc2 with a NaN point", cache[:-4] + np.float32(np.nan).tobytes(), mesh, "invalid-file"),
        ("pc2 with an infinite point", cache[:40] + np.float32(np.inf).tobytes() + cache[44:], mesh, "invalid-file"),
        ("pc2 with one point fewer than the OBJ", pc2_bytes(points[:, :-1]), mesh, "invalid-file"),
        ("pc2 with too few frames for two cycles", pc2_bytes(points[:3]), mesh, "invalid-file"),
        ("obj with a face index past the vertices", cache, mesh + b"f 1 2 999\n", "invalid-file"),
        ("obj with a face index 0", cache, mesh + b"f 0 1 2\n", "invalid-file"),
        ("obj with a negative index before the start", cache, mesh + b"f -1 -2 -999\n", "invalid-file"),
        ("obj with a texture index out of range", cache, mesh + b"f 1/7 2/7 3/7\n", "invalid-file"),
        ("obj with a non-integer index", cache, mesh + b"f 1 2 x\n", "invalid-file"),
        ("obj with a two-corner face", cache, mesh + b"f 1 2\n", "invalid-file"),
        ("obj with a NaN vertex", cache, b"v nan 0 0\n" + mesh, "invalid-file"),
        ("obj with an infinite vertex", cache, b"v inf 0 0\n" + mesh, "invalid-file"),
        ("obj with a vertex that overflows float32", cache, b"v 1e39 0 0\n" + mesh, "invalid-file"),
        ("obj with a 2^63 index", cache, mesh + b"f 1 2 9223372036854775808\n", "invalid-file"),
        ("obj with no faces", cache, b"".join(line + b"\n" for line in mesh.splitlines() if not line.startswith(b"f ")), "invalid-file"),
        ("obj that is binary garbage", cache, b"v 0 0 0\n\x00\xff\xfe" * 50, "invalid-file"),
    ]
    files = [(name, {"cache": ("cloth.pc2", pc2), "mesh": ("cloth.obj", obj)}, problem) for name, pc2, obj, problem in cases]
    files.append(("a PNG named .pc2", {"cache": ("cloth.pc2", png_bytes()), "mesh": ("cloth.obj", mesh)}, "format-mismatch"))
    files.append(("a PC2 named .obj", {"cache": ("cloth.pc2", cache), "mesh": ("cloth.obj", cache)}, "format-mismatch"))
    files.append(("an empty OBJ", {"cache": ("cloth.pc2", cache), "mesh": ("cloth.obj", b"")}, "invalid-file"))
    # Alembic is a cloth format now: a PC2 named .abc is caught by its content.
    files.append(("a PC2 named .abc", {"cache": ("cloth.abc", cache), "mesh": ("cloth.obj", mesh)}, "format-mismatch"))
    return files


# ------------------------------------------------------------------------------------------ zips


def _zip(entries: list[tuple[Any, bytes]], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression) as archive:
        for info, data in entries:
            archive.writestr(info, data)
    return buffer.getvalue()


def _patch_central_directory(data: bytes, offset_in_entry: int, value: bytes, which: int = 0) -> bytes:
    """Overwrite a field of the `which`-th central directory entry (offsets per APPNOTE 4.3.12)."""
    position = -1
    for _ in range(which + 1):
        position = data.index(b"PK\x01\x02", position + 1)
    return data[: position + offset_in_entry] + value + data[position + offset_in_entry + len(value) :]


def zip_cases(tmp: Path) -> list[tuple[str, bytes, str]]:
    """(name, zip bytes, problem) of broken OBJ-sequence uploads."""
    points, faces = tiny_cloth(frames=FRAMES)
    frames = [(f"frames/frame{index}.obj", obj_bytes(frame, faces, tmp)) for index, frame in enumerate(points)]
    good = obj_sequence_zip(points, faces, tmp)
    cases: list[tuple[str, bytes, str]] = []
    for name in ("../evil.obj", "frames/../../evil.obj", "/etc/evil.obj", "C:/evil.obj", "frames\\..\\evil.obj"):
        cases.append((f"zip entry {name!r}", _zip(frames + [(name, frames[0][1])]), "unsafe-archive"))
    link = zipfile.ZipInfo("frames/link.obj")
    link.external_attr = (stat.S_IFLNK | 0o777) << 16
    cases.append(("zip with a symbolic link", _zip(frames + [(link, b"/etc/passwd")]), "unsafe-archive"))
    bomb = b"\0" * (4 << 20)  # deflates ~1000:1, well over MAX_ZIP_RATIO and over 1 MiB
    cases.append(("zip bomb by ratio", _zip(frames + [("frames/zeros.obj", bomb)]), "unsafe-archive"))
    # The central directory declares a 4 GiB first frame: over MAX_ZIP_UNCOMPRESSED_BYTES before anything inflates.
    cases.append(("zip bomb by declared total size", _patch_central_directory(good, 24, struct.pack("<I", 0xFFFFFF00)), "unsafe-archive"))
    cases.append(("zip with too many entries", _zip(frames + [(f"frames/extra{k}.txt", b"x") for k in range(MAX_ZIP_ENTRIES)]), "unsafe-archive"))
    # The central directory says the first frame is 10 bytes; it inflates to far more.
    cases.append(("zip entry expanding past its declared size", _patch_central_directory(good, 24, struct.pack("<I", 10)), frozenset({"unsafe-archive", "invalid-file"})))
    encrypted = bytearray(_patch_central_directory(good, 8, struct.pack("<H", 0x1)))
    cases.append(("zip with an encrypted entry", bytes(encrypted), "invalid-file"))
    corrupt = bytearray(good)
    first_data = 30 + len(frames[0][0])
    corrupt[first_data : first_data + 16] = b"\xff" * 16
    cases.append(("zip with a corrupt deflate stream", bytes(corrupt), "invalid-file"))
    # Compression method 99 (AES, as WinZip writes) is one Python's zipfile cannot read.
    unknown = _patch_central_directory(good, 10, struct.pack("<H", 99))
    unknown = unknown[:8] + struct.pack("<H", 99) + unknown[10:]
    cases.append(("zip with an unsupported compression method", unknown, "invalid-file"))
    cases.append(("zip truncated in half", good[: len(good) // 2], "invalid-file"))
    # Central directory fields zipfile trips over: strong encryption (flag bit 6), a local header
    # offset past the file's end, a version above what it reads, an empty entry name.
    cases.append(("zip with strong encryption", _patch_central_directory(good, 8, struct.pack("<H", 0x40)), "invalid-file"))
    cases.append(("zip with a header offset past its end", _patch_central_directory(good, 42, struct.pack("<I", 0xFFFFFFF0)), "invalid-file"))
    cases.append(("zip needing version 6.4", _patch_central_directory(good, 6, struct.pack("<H", 64)), "invalid-file"))
    name_length = struct.unpack_from("<H", good, good.index(b"PK\x01\x02") + 28)[0]
    empty_name = _patch_central_directory(good, 28, struct.pack("<H", 0))
    position = empty_name.index(b"PK\x01\x02")
    empty_name = empty_name[: position + 46] + empty_name[position + 46 + name_length :]
    end = empty_name.index(b"PK\x05\x06")  # the end record's directory size shrinks by the name
    size = struct.unpack_from("<I", empty_name, end + 12)[0]
    empty_name = empty_name[: end + 12] + struct.pack("<I", size - name_length) + empty_name[end + 16 :]
    cases.append(("zip entry with an empty name", empty_name, frozenset({"unsafe-archive", "invalid-file"})))
    cases.append(("zip with one frame", _zip(frames[:1]), "invalid-file"))
    moved = [(name, data if index < 6 else data + b"v 9 9 9\n") for index, (name, data) in enumerate(frames)]
    cases.append(("zip whose topology changes", _zip(moved), "invalid-file"))
    cases.append(("zip of a NaN frame", _zip(frames[:-1] + [(frames[-1][0], b"v nan 0 0\n" + frames[-1][1])]), "invalid-file"))
    return cases


# ---------------------------------------------------------------------------------------- images


def png_with_size(width: int, height: int) -> bytes:
    """A PNG whose IHDR declares width x height (with a valid CRC) and holds one row of data."""
    signature = b"\x89PNG\r\n\x1a\n"

    def chunk(kind: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload) & 0xFFFFFFFF)

    header = chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0))
    return signature + header + chunk(b"IDAT", zlib.compress(b"\0" * (1 + 4 * min(width, 64)))) + chunk(b"IEND", b"")


def texture_cases() -> list[tuple[str, tuple, str]]:
    good = png_bytes()
    bad_crc = bytearray(good)
    bad_crc[29] ^= 0xFF  # inside IHDR's CRC
    return [
        ("png declaring 100000 x 100000 pixels", ("diffuse_0.png", png_with_size(100_000, 100_000)), "invalid-file"),
        ("png declaring 2^31 x 1 pixels", ("diffuse_0.png", png_with_size(2**31 - 1, 1)), "invalid-file"),
        ("png declaring 0 x 0 pixels", ("diffuse_0.png", png_with_size(0, 0)), "invalid-file"),
        ("png truncated", ("diffuse_0.png", good[: len(good) // 2]), "invalid-file"),
        ("png with a bad CRC", ("diffuse_0.png", bytes(bad_crc)), "invalid-file"),
        ("png without IHDR", ("diffuse_0.png", good[:8] + b"\0" * 40), "invalid-file"),
        ("a GLB named .png", ("diffuse_0.png", tiny_character_glb()), "format-mismatch"),
        # JPEG variations are accepted; one whose data does not decode is not.
        ("a .jpg that does not decode", ("diffuse_0.jpg", b"\xff\xd8\xff\xe0" + b"\0" * 64), "invalid-file"),
        ("an .svg", ("diffuse_0.svg", b"<svg xmlns='http://www.w3.org/2000/svg'/>"), "unsupported-format"),
    ]


# --------------------------------------------------------------------------------------- hostile
# Inputs that are well-formed enough to reach the readers but ask them for unbounded work: each is
# small on the wire and large (or slow) once parsed. `hostile_inputs` builds them at full size for
# services/benchmarks/bench_hostile.py; the corpus below holds versions that fit its 1 MiB bodies.


def glb_zero_filled_accessor(count: int, accessor_type: str = "MAT4") -> bytes:
    """The tiny character whose POSITION accessor has no bufferView (zero-filled by the spec) and
    `count` elements of `accessor_type`: 200 bytes of JSON that ask for count x 64 bytes."""
    document, binary = split_glb(tiny_character_glb())
    accessor = _position_accessor(document)
    accessor.pop("bufferView", None)
    accessor.pop("byteOffset", None)
    accessor.pop("min", None)
    accessor.pop("max", None)
    accessor.update(count=count, type=accessor_type)
    return make_glb(document, binary)


def glb_node_chain(nodes: int) -> bytes:
    """The tiny character plus `nodes` extra nodes, each the only child of the one before (a chain)."""
    document, binary = split_glb(tiny_character_glb())
    first = len(document["nodes"])
    document["nodes"] += [{"name": f"n{k}", "children": [first + k + 1]} for k in range(nodes - 1)] + [{"name": f"n{nodes - 1}"}]
    document["scenes"][document.get("scene", 0)]["nodes"].append(first)
    return make_glb(document, binary)


def big_png(width: int, height: int, rows_of_data: int | None = None) -> bytes:
    """A valid RGBA PNG of width x height black pixels (deflate makes it ~1000:1 small), or with only
    `rows_of_data` rows of pixel data (header-only checks refuse it just the same)."""
    signature = b"\x89PNG\r\n\x1a\n"

    def chunk(kind: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload) & 0xFFFFFFFF)

    compressor = zlib.compressobj(9)
    row = b"\0" * (1 + 4 * width)
    data = b"".join(compressor.compress(row) for _ in range(height if rows_of_data is None else rows_of_data)) + compressor.flush()
    header = chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0))
    return signature + header + chunk(b"IDAT", data) + chunk(b"IEND", b"")


def glb_with_image(png: bytes) -> bytes:
    """The tiny character with a base colour texture whose embedded image is `png`."""
    import dataclasses

    from crowdbake.formats.gltf import encode_character
    from service_fixtures import tiny_character

    character = dataclasses.replace(tiny_character(), texture=np.full((4, 4, 4), 200, np.uint8))
    document, binary = split_glb(encode_character(character))
    binary += b"\0" * (-len(binary) % 4)
    document["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)})
    document["images"][0] = {"bufferView": len(document["bufferViews"]) - 1, "mimeType": "image/png"}
    binary += png
    document["buffers"][0]["byteLength"] = len(binary)
    return make_glb(document, binary)


def obj_faces_over_few_vertices(faces: int) -> bytes:
    """Three positions and `faces` copies of the one triangle over them (8 bytes a face)."""
    return b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * faces


def obj_many_vertices(target_bytes: int) -> bytes:
    """A valid OBJ of `target_bytes`: as many positions as fit, one triangle (the memory of the parse)."""
    line = b"v 0.123456 0.654321 0.111111\n"
    return line * (target_bytes // len(line)) + b"f 1 2 3\n"


def zip_of_small_frames(entries: int, entry_bytes: int) -> bytes:
    """`entries` OBJ frames of exactly `entry_bytes` each (under the per-entry ratio check's 1 MiB), every
    one a valid frame of entry_bytes / 8 positions: ~1000:1 as a whole archive."""
    vertex = b"v 0 0 0\n"
    frame = vertex * (entry_bytes // len(vertex) - 1) + b"f 1 2 3\n"
    return _zip([(f"frames/frame{k}.obj", frame) for k in range(entries)])


def hostile_inputs() -> list[tuple[str, str, dict[str, tuple]]]:
    """(name, route, multipart files) of the full-size hostile inputs (bench_hostile.py sends them to a
    server with the default limits)."""
    return [
        ("glb: POSITION without bufferView, count 10^7 MAT4", "/v1/assets/characters", {"file": ("c.glb", glb_zero_filled_accessor(10**7))}),
        ("glb: POSITION without bufferView, count 4x10^8 MAT4", "/v1/assets/characters", {"file": ("c.glb", glb_zero_filled_accessor(4 * 10**8))}),
        ("glb: a chain of 16,000 nodes", "/v1/assets/characters", {"file": ("c.glb", glb_node_chain(16_000))}),
        ("glb: an embedded 12000x12000 PNG (144 Mpx)", "/v1/assets/characters", {"file": ("c.glb", glb_with_image(big_png(12_000, 12_000)))}),
        ("png: 12000x12000 texture upload", "/v1/assets/textures", {"file": ("diffuse_0.png", big_png(12_000, 12_000))}),
        ("zip: 200 OBJ frames of 1 MiB each", "/v1/assets/cloth", {"sequence": ("frames.zip", zip_of_small_frames(200, 1 << 20))}),
        ("obj: 3 vertices, 4.2 M faces (32 MiB)", "/v1/assets/cloth",
         {"cache": ("c.pc2", pc2_header(3, 12) + bytes(12 * 3 * 12)), "mesh": ("c.obj", obj_faces_over_few_vertices(4_200_000))}),
        ("obj: 32 MiB of vertices, PC2 of the wrong count", "/v1/assets/cloth",
         {"cache": ("c.pc2", pc2_header(3, 12) + bytes(12 * 3 * 12)), "mesh": ("c.obj", obj_many_vertices(32 << 20))}),
    ]


def hostile_cases() -> list[Case]:
    """The hostile inputs at sizes that fit the corpus's limits (1 MiB bodies, 40 zip entries)."""
    cloth_pc2 = ("c.pc2", pc2_header(3, FRAMES) + bytes(12 * 3 * FRAMES))
    return [
        Case("glb whose accessor has no bufferView and count 10^7 of MAT4", "/v1/assets/characters", 422, "invalid-file",
             files={"file": ("c.glb", glb_zero_filled_accessor(10**7))}),
        Case("glb whose accessor has no bufferView and count 4x10^8 of MAT4", "/v1/assets/characters", 422, "invalid-file",
             files={"file": ("c.glb", glb_zero_filled_accessor(4 * 10**8))}),
        Case("glb with an embedded PNG declaring 12000 x 12000 pixels", "/v1/assets/characters", 422, "invalid-file",
             files={"file": ("c.glb", glb_with_image(big_png(12_000, 12_000, rows_of_data=1)))}),
        Case("zip of 30 frames of 256 KiB (whole-archive ratio)", "/v1/assets/cloth", 422, "unsafe-archive",
             files={"sequence": ("frames.zip", zip_of_small_frames(30, 256 << 10))}),
        Case("obj with 100,000 faces over 3 vertices", "/v1/assets/cloth", 422, "invalid-file",
             files={"cache": cloth_pc2, "mesh": ("c.obj", obj_faces_over_few_vertices(100_000))}),
    ]


# ---------------------------------------------------------------------------------------- corpus


def multipart_body(parts: list[tuple[str, str | None, bytes]], boundary: str = "x") -> bytes:
    """A multipart/form-data body from (field, filename or None, bytes) parts, written by hand so
    that text-only bodies stay multipart."""
    body = b""
    for name, filename, data in parts:
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename is not None else "")
        body += f"--{boundary}\r\nContent-Disposition: {disposition}\r\n\r\n".encode() + data + b"\r\n"
    return body + f"--{boundary}--\r\n".encode()


MULTIPART = {"Content-Type": "multipart/form-data; boundary=x"}


def corpus(tmp: Path) -> list[Case]:
    """Every case. Bodies stay under MAX_UPLOAD_BYTES except the oversize ones."""
    cases: list[Case] = []
    for name, data, problem in glb_cases():
        cases.append(Case(name, "/v1/assets/characters", 422, problem, files={"file": ("character.glb", data)}))
    gltf = json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "file:///etc/passwd", "byteLength": 10}]}).encode()
    cases.append(Case("gltf with a file:// buffer", "/v1/assets/characters", 422, "invalid-file", files={"file": ("character.gltf", gltf)}))
    cases.append(Case("a PNG named .glb", "/v1/assets/characters", 422, "format-mismatch", files={"file": ("character.glb", png_bytes())}))
    cases.append(Case("an .fbx", "/v1/assets/characters", 415, "unsupported-format", files={"file": ("character.fbx", b"Kaydara FBX Binary  \0")}))
    cases.append(Case("an empty .glb", "/v1/assets/characters", 422, "invalid-file", files={"file": ("character.glb", b"")}))
    cases.append(Case("a .gltf nested 100000 lists deep", "/v1/assets/characters", 422, "invalid-file",
                      files={"file": ("character.gltf", b'{"asset":' + b"[" * 100_000 + b"]" * 100_000 + b"}")}))
    for name, files, problem in cloth_cases(tmp):
        cases.append(Case(name, "/v1/assets/cloth", 422 if problem != "unsupported-format" else 415, problem, files=files))
    for name, data, problem in zip_cases(tmp):
        problems = problem if isinstance(problem, frozenset) else None
        cases.append(Case(name, "/v1/assets/cloth", 422, problem if problems is None else None, files={"sequence": ("frames.zip", data)}))
    cases.append(Case("a zip plus a pc2", "/v1/assets/cloth", 400, "malformed-request",
                      files={"sequence": ("frames.zip", b"PK\x05\x06" + b"\0" * 18), "cache": ("cloth.pc2", b"x")}))
    cases.append(Case("cycle_frames that is not a number", "/v1/assets/cloth", 422, "validation-error",
                      files={"sequence": ("frames.zip", b"PK\x05\x06" + b"\0" * 18)}, data={"cycle_frames": "many"}))
    for name, file, problem in texture_cases():
        cases.append(Case(name, "/v1/assets/textures", 415 if problem == "unsupported-format" else 422, problem, files={"file": file}))

    # Wrong content types and malformed multipart.
    glb = tiny_character_glb()
    cases.append(Case("a JSON body to an upload", "/v1/assets/characters", 415, "unsupported-format",
                      content=b'{"file": "x"}', headers={"Content-Type": "application/json"}))
    cases.append(Case("a raw GLB body to an upload", "/v1/assets/characters", 415, "unsupported-format",
                      content=glb, headers={"Content-Type": "model/gltf-binary"}))
    cases.append(Case("multipart without a boundary", "/v1/assets/characters", 400, "malformed-request",
                      content=b"--x\r\n", headers={"Content-Type": "multipart/form-data"}))
    cases.append(Case("multipart that never ends", "/v1/assets/characters", 400, "malformed-request",
                      content=b'--x\r\nContent-Disposition: form-data; name="file"; filename="c.glb"\r\n\r\n' + glb[:100],
                      headers={"Content-Type": "multipart/form-data; boundary=x"}))
    cases.append(Case("a part without a name", "/v1/assets/characters", 400, "malformed-request",
                      content=b"--x\r\nContent-Disposition: form-data\r\n\r\nabc\r\n--x--\r\n", headers={"Content-Type": "multipart/form-data; boundary=x"}))
    cases.append(Case("the file field twice", "/v1/assets/characters", 400, "malformed-request",
                      content=b"".join(b'--x\r\nContent-Disposition: form-data; name="file"; filename="c.glb"\r\n\r\n' + glb + b"\r\n" for _ in range(2)) + b"--x--\r\n",
                      headers={"Content-Type": "multipart/form-data; boundary=x"}))
    cases.append(Case("an unexpected file field", "/v1/assets/characters", 400, "malformed-request", files={"other": ("c.glb", glb)}))
    cases.append(Case("no file at all", "/v1/assets/characters", 400, "malformed-request",
                      content=multipart_body([("note", None, b"x")]), headers=MULTIPART))
    cases.append(Case("an empty multipart body", "/v1/assets/characters", 400, "malformed-request", content=b"--x--\r\n", headers=MULTIPART))
    cases.append(Case("a text field over 1 KiB", "/v1/assets/cloth", 400, "malformed-request",
                      content=multipart_body([("cycle_frames", None, b"1" * 2000)]), headers=MULTIPART))
    cases.append(Case("17 parts", "/v1/assets/cloth", 400, "malformed-request",
                      content=multipart_body([("cycle_frames", None, b"2")] * 17), headers=MULTIPART))
    cases.append(Case("a filename with a NUL and ../", "/v1/assets/characters", 415, "unsupported-format",
                      content=multipart_body([("file", "../../x\0.glb.sh", glb)]), headers=MULTIPART))

    # Oversize bodies: declared (refused before reading) and not declared (cut off while streaming).
    big = b"\0" * (MAX_UPLOAD_BYTES + 1)
    cases.append(Case("a body declaring more than the limit", "/v1/assets/characters", 413, "payload-too-large", files={"file": ("c.glb", big)}))
    cases.append(Case("a Content-Length that is not a number", "/v1/assets/characters", frozenset({400}), "malformed-request",
                      content=b"--x--\r\n", headers={"Content-Type": "multipart/form-data; boundary=x", "Content-Length": "lots"}))

    # JSON bodies of bakes: wrong types, huge numbers, names that would be paths.
    def bake(name: str, body: Any, status: int = 422, problem: str | None = "validation-error", **headers: str) -> None:
        content = body if isinstance(body, bytes) else None
        cases.append(Case(name, "/v1/bakes", status, problem, json_body=None if content is not None else body, content=content,
                          headers=headers or ({"Content-Type": "application/json"} if content is not None else {})))

    base = {"name": "walker", "version": "1.0.0", "character": "as_missing", "cloth": "as_missing"}
    bake("a bake body that is not JSON", b"{name: walker")
    bake("a bake body that is a list", [base])
    bake("a bake body sent as a form", b"name=walker&version=1", **{"Content-Type": "application/x-www-form-urlencoded"})
    for name in ("../escape", "..", "a/b", "%2e%2e", "/abs", "A", "walker\0", "x" * 65, "", "latest/.."):
        bake(f"bake name {name[:20]!r}", dict(base, name=name))
    for version in ("../1", "1/2", "..", "latest", "1.0\0", "v" * 65, "%2e%2e%2f"):
        bake(f"bake version {version[:20]!r}", dict(base, version=version))
    bake("a texture named ../x.png", dict(base, textures={"../x.png": "as_missing"}))
    bake("a texture named /etc/passwd", dict(base, textures={"/etc/passwd": "as_missing"}))
    bake("a tile size of 10^12", dict(base, params={"tile_size": 10**12}))
    bake("a tile size of 1e400", b'{"name":"walker","version":"1","character":"a","cloth":"b","params":{"tile_size":1e400}}')
    bake("an impostor frame count as a string", dict(base, params={"impostor_frames": "ten"}))
    bake("elevations of NaN", b'{"name":"walker","version":"1","character":"a","cloth":"b","params":{"elevations_deg":[NaN]}}')
    bake("1000 elevations", dict(base, params={"elevations_deg": list(range(-500, 500))}))
    bake("assets that do not exist", base)
    cases += hostile_cases()
    return cases
