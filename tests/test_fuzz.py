"""Fuzzing, bounded and deterministic (hypothesis with derandomize=True: the same examples every run).

* The readers (crowdbake.formats: read_pc2, read_obj, load_character for .glb and .gltf, the bundle's
  decode_pose_cache and decode_texture_array) and the OBJ-sequence zip converter: whatever bytes they
  get, they return a result or raise ValueError (FormatError and UploadRejected are the named kinds),
  never another exception, and never allocate much more than they were given (tracemalloc peak, which
  numpy reports into, under READER_MEMORY_FACTOR x input + READER_MEMORY_FLOOR). Inputs are mutations
  of valid files written by the project's own writers (header fields set to extreme values, bytes
  flipped, truncations, JSON values replaced) plus raw bytes, so most examples get past the magic.
* The API against its own OpenAPI document (schemathesis): every operation, valid and invalid
  requests, API_EXAMPLES each: no 5xx, every status documented, responses match their schema, errors
  are problem documents, invalid data is refused, and no staging file is left behind.

Regressions this fuzzing found (fixed; the corpus in tests/corpus.py keeps a case of each): the glTF
reader raised TypeError/AttributeError/RecursionError on JSON of the wrong shape (500s through the
API); zipfile's NotImplementedError, IndexError (empty entry name) and OSError (seek before the
file) escaped the zip converter; asset times had no UTC offset (test below); a body that does not
decode (400) and an unknown problem type (404) were answers the OpenAPI document did not list.
"""
from __future__ import annotations

import atexit
import io
import json
import os
import shutil
import struct
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from corpus import make_glb, split_glb
from crowdbake.formats.binary import decode_pose_cache, decode_texture_array, encode_pose_cache, encode_texture_array
from crowdbake.formats.skinned_cache import decode_skinned_pose_cache, encode_skinned_pose_cache
from crowdbake.formats.gltf import load_character
from crowdbake.formats.obj import read_obj
from crowdbake.formats.pc2 import read_pc2
from crowdbake.ingest.obj_sequence import ZipLimits, convert_obj_sequence
from crowdbake.ingest.uploads import UploadRejected
from service_fixtures import obj_bytes, obj_sequence_zip, pc2_bytes, tiny_character_glb, tiny_cloth

# A reader may hold a few copies of its input as arrays or Python objects (an OBJ line of 8 bytes
# becomes three floats in a list: ~20x); anything beyond this is an allocation the input asked for.
READER_MEMORY_FACTOR = 64
READER_MEMORY_FLOOR = 32 << 20
READER_EXAMPLES = int(os.environ.get("CROWDBAKE_FUZZ_EXAMPLES", "300"))
API_EXAMPLES = 25
FUZZ = settings(max_examples=READER_EXAMPLES, derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])

INTERESTING_U32 = [0, 1, 2, 3, 4, 7, 255, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF, 1 << 24, 1 << 28]
INTERESTING_F32 = [0.0, -0.0, 1.0, -1.0, float("nan"), float("inf"), float("-inf"), 1e-45, 3.4e38, -3.4e38]

SCRATCH = Path(tempfile.mkdtemp(prefix="crowdbake-fuzz-"))
atexit.register(shutil.rmtree, SCRATCH, ignore_errors=True)


def contained(read, data: bytes, name: str):
    """Run read(path of `data`) and check the contract: a result or ValueError, and a bounded peak."""
    path = SCRATCH / name
    path.write_bytes(data)
    tracemalloc.start()
    try:
        read(path)
    except ValueError:
        pass  # FormatError and UploadRejected's callers' ValueErrors: the named ways to refuse
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert peak <= READER_MEMORY_FACTOR * len(data) + READER_MEMORY_FLOOR, f"{name}: {peak} bytes allocated for {len(data)} bytes of input"


def test_the_memory_bound_catches_a_reader_that_trusts_a_declared_size():
    """The harness itself: a reader that allocates what a header declares is caught."""
    def trusting_reader(path: Path):
        declared = struct.unpack("<I", path.read_bytes()[:4])[0]
        return np.ones(declared, np.uint8)

    contained(trusting_reader, struct.pack("<I", 1000), "small.bin")  # 1000 bytes asked: fine
    try:
        contained(trusting_reader, struct.pack("<I", 200 << 20), "liar.bin")
    except AssertionError as error:
        assert "allocated" in str(error)
    else:
        raise AssertionError("a 200 MiB allocation for 4 bytes of input went unnoticed")


@st.composite
def mutated(draw, seed: bytes, fields: list[tuple[int, str]]) -> bytes:
    """`seed` with some of: header `fields` ((offset, '<I' or '<i' or '<f')) set to extreme values,
    bytes overwritten, a truncation or an extension."""
    data = bytearray(seed)
    for offset, kind in draw(st.lists(st.sampled_from(fields), max_size=3)) if fields else []:
        if kind == "<f":
            value = draw(st.sampled_from(INTERESTING_F32) | st.floats(width=32))
        else:
            value = draw(st.sampled_from(INTERESTING_U32) | st.integers(0, 0xFFFFFFFF))
            if kind == "<i":
                value = value - (1 << 32) if value >= 1 << 31 else value
        struct.pack_into(kind, data, offset, value)
    for _ in range(draw(st.integers(0, 4))):
        if data:
            position = draw(st.integers(0, len(data) - 1))
            data[position] = draw(st.integers(0, 255))
    cut = draw(st.one_of(st.none(), st.integers(0, len(data))))
    if cut is not None:
        del data[cut:]
    return bytes(data) + draw(st.binary(max_size=16))


# ------------------------------------------------------------------------------------------- PC2

_POINTS, _FACES = tiny_cloth(frames=6)
PC2_SEED = pc2_bytes(_POINTS)
PC2_FIELDS = [(12, "<i"), (16, "<i"), (20, "<f"), (24, "<f"), (28, "<i"), (40, "<f")]


@FUZZ
@given(data=mutated(PC2_SEED, PC2_FIELDS) | st.binary(max_size=200))
def test_read_pc2_refuses_cleanly(data):
    contained(read_pc2, data, "cache.pc2")


# ------------------------------------------------------------------------------------------- OBJ

_number = st.sampled_from(["0", "1", "-1", "1e39", "-1e39", "nan", "inf", "1e-46", "0x10", "1_0", "", "١"]) | st.floats().map(repr)
_index = st.sampled_from(["0", "1", "2", "-1", "-9", "9", "99999999999999999999", "x", "", "1.5"]) | st.integers(-20, 20).map(str)
_corner = st.tuples(_index, st.sampled_from(["", "/", "//"]), _index, st.sampled_from(["", "/"]), _index).map(lambda parts: "".join(parts))
_line = st.one_of(
    st.lists(_number, max_size=8).map(lambda values: " ".join(["v", *values])),
    st.lists(_number, max_size=4).map(lambda values: " ".join(["vt", *values])),
    st.lists(_corner, max_size=6).map(lambda corners: " ".join(["f", *corners])),
    st.sampled_from(["# comment", "g group", "usemtl x", "s off", "vn 0 0 1", "o", ""]),
    st.text(max_size=20),
)
OBJ_SEED = obj_bytes(_POINTS[0], _FACES, SCRATCH)


@FUZZ
@given(lines=st.lists(_line, max_size=30), prefix=st.booleans(), raw=st.binary(max_size=64))
def test_read_obj_refuses_cleanly(lines, prefix, raw):
    text = "\n".join(lines).encode("utf-8", "surrogatepass")
    contained(read_obj, (OBJ_SEED if prefix else b"") + text + raw, "mesh.obj")


# ---------------------------------------------------------------------------------------- glTF

GLB_SEED = tiny_character_glb()
GLTF_DOCUMENT, GLTF_BINARY = split_glb(GLB_SEED)
_json_value = st.recursive(
    st.none() | st.booleans() | st.sampled_from([0, 1, -1, 2, 3, 4, 5123, 5126, 2**31, 2**63, 10**30, 0.5, -0.0, "", "VEC3", "SCALAR", "MAT4", "data:,", "a.bin"])
    | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.sampled_from(["count", "bufferView", "byteOffset", "type", "componentType", "uri", "byteLength", "joints", "children"]), children, max_size=3),
    max_leaves=6,
)


def _paths(node, prefix=()):
    """Every (path) into a JSON document, for choosing what to replace."""
    yield prefix
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, prefix + (key,))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _paths(value, prefix + (index,))


GLTF_PATHS = [path for path in _paths(GLTF_DOCUMENT) if path]


@st.composite
def mutated_gltf(draw) -> dict:
    document = json.loads(json.dumps(GLTF_DOCUMENT))
    for path in draw(st.lists(st.sampled_from(GLTF_PATHS), min_size=1, max_size=3)):
        parent = document
        try:
            for key in path[:-1]:
                parent = parent[key]
            if draw(st.booleans()) and isinstance(parent, dict):
                parent.pop(path[-1], None)
            else:
                parent[path[-1]] = draw(_json_value)
        except (KeyError, IndexError, TypeError):
            continue  # an earlier replacement removed this path
    return document


@FUZZ
@given(document=mutated_gltf(), binary=mutated(GLTF_BINARY, []))
def test_load_character_refuses_cleanly_glb(document, binary):
    contained(load_character, make_glb(document, binary), "character.glb")


@FUZZ
@given(data=mutated(GLB_SEED, [(8, "<I"), (12, "<I"), (16, "<I")]) | st.binary(max_size=64).map(lambda tail: b"glTF" + tail))
def test_load_character_refuses_cleanly_glb_bytes(data):
    contained(load_character, data, "character.glb")


@FUZZ
@given(document=mutated_gltf())
def test_load_character_refuses_cleanly_gltf(document):
    import base64

    document = json.loads(json.dumps(document))
    for buffer in document.get("buffers", []) if isinstance(document.get("buffers"), list) else []:
        if isinstance(buffer, dict) and "uri" not in buffer:
            buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(GLTF_BINARY).decode()
    contained(load_character, json.dumps(document).encode(), "character.gltf")


# ------------------------------------------------------------------------------- bundle binaries

POSE_SEED = encode_pose_cache(_FACES, np.zeros((len(_POINTS[0]), 2)), _POINTS[:2], np.tile([0.0, 0.0, 1.0], (2, len(_POINTS[0]), 1)), 24.0)
POSE_FIELDS = [(4, "<I"), (8, "<I"), (12, "<I"), (16, "<I"), (20, "<I"), (24, "<I"), (28, "<I"), (32, "<f"), (36, "<f"), (48, "<f"), (60, "<I")]
TEXTURE_SEED = encode_texture_array(8, 8, "bc1", [bytes(32), bytes(32)])
TEXTURE_FIELDS = [(4, "<I"), (8, "<I"), (12, "<I"), (16, "<I"), (20, "<I"), (24, "<I"), (28, "<I")]


@FUZZ
@given(data=mutated(POSE_SEED, POSE_FIELDS) | st.binary(max_size=128).map(lambda tail: b"CBPC" + tail))
def test_decode_pose_cache_refuses_cleanly(data):
    contained(lambda path: decode_pose_cache(path.read_bytes()), data, "pose.cbpc")


SKINNED_SEED = encode_skinned_pose_cache(_FACES, np.zeros((len(_POINTS[0]), 2)), _POINTS[0], np.tile([0.0, 0.0, 1.0], (len(_POINTS[0]), 1)),
                                         np.zeros((len(_POINTS[0]), 4), int), np.tile([1.0, 0.0, 0.0, 0.0], (len(_POINTS[0]), 1)),
                                         np.tile(np.eye(4)[:3], (2, 1, 1, 1)), 24.0)


@FUZZ
@given(data=mutated(SKINNED_SEED, POSE_FIELDS) | st.binary(max_size=128).map(lambda tail: b"CBSK" + tail))
def test_decode_skinned_pose_cache_refuses_cleanly(data):
    contained(lambda path: decode_skinned_pose_cache(path.read_bytes()), data, "pose.cbsk")


@FUZZ
@given(data=mutated(TEXTURE_SEED, TEXTURE_FIELDS) | st.binary(max_size=128).map(lambda tail: b"CBTX" + tail))
def test_decode_texture_array_refuses_cleanly(data):
    contained(lambda path: decode_texture_array(path.read_bytes()), data, "texture.cbtx")


# ---------------------------------------------------------------------------------- OBJ-sequence zip

ZIP_SEED = obj_sequence_zip(_POINTS, _FACES, SCRATCH)
_CENTRAL = ZIP_SEED.index(b"PK\x01\x02")
# Central directory fields of the first entry (APPNOTE 4.3.12): flags, method, sizes, name length, attributes.
ZIP_FIELDS = [(_CENTRAL + 8, "<I"), (_CENTRAL + 20, "<I"), (_CENTRAL + 24, "<I"), (_CENTRAL + 28, "<I"), (_CENTRAL + 38, "<I"), (_CENTRAL + 42, "<I"), (26, "<I"), (18, "<I")]
ZIP_LIMITS = ZipLimits(max_entries=64, max_uncompressed_bytes=8 << 20, max_ratio=50.0)


class _Sink(io.BytesIO):
    pass


@FUZZ
@given(data=mutated(ZIP_SEED, ZIP_FIELDS))
def test_convert_obj_sequence_refuses_cleanly(data):
    def convert(path):
        try:
            convert_obj_sequence(path, "frames.zip", ZIP_LIMITS, _Sink(), _Sink(), cycle_frames=3)
        except UploadRejected as rejected:
            raise ValueError(rejected.detail) from None

    contained(convert, data, "frames.zip")


# ------------------------------------------------------------------------------------------- API


@pytest.mark.slow  # tens of seconds; runs in CI (CROWDBAKE_SLOW_TESTS=1)
def test_the_api_against_its_openapi_document(tmp_path):
    import schemathesis
    from hypothesis.errors import Unsatisfiable
    from schemathesis import GenerationMode
    from schemathesis.checks import (
        content_type_conformance,
        negative_data_rejection,
        not_a_server_error,
        response_schema_conformance,
        status_code_conformance,
    )

    from service_fixtures import make_api, publish_vector_bundle

    api = make_api(tmp_path, max_upload_bytes=1 << 20)
    publish_vector_bundle(api, public=True)
    schema = schemathesis.openapi.from_asgi("/openapi.json", api.client.app)
    checks = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance, negative_data_rejection]
    failures: dict[tuple[str, str, str], str] = {}
    operations = 0
    for result in schema.get_all_operations():
        operation = result.ok()
        operations += 1
        for mode in GenerationMode:

            @given(case=operation.as_strategy(generation_mode=mode))
            @settings(max_examples=API_EXAMPLES, derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck))
            def fuzz(case):
                case.headers = {**(case.headers or {}), "Authorization": f"Bearer {api.keys['all']}"}
                response = case.call()
                try:
                    case.validate_response(response, checks=checks)
                    if response.status_code >= 400:
                        content_type = response.headers.get("content-type")
                        content_type = content_type[0] if isinstance(content_type, list) else content_type
                        assert content_type == "application/problem+json", content_type
                        assert {"type", "title", "status", "detail"} <= set(response.json())
                except BaseException as error:  # schemathesis raises a BaseExceptionGroup of its checks
                    failures.setdefault((operation.method.upper(), operation.path, mode.value), f"{case.as_curl_command()}\n{error}"[:1500])

            try:
                fuzz()
            except Unsatisfiable:
                pass  # negative mode of an operation without parameters: nothing can be invalid
    assert operations >= 19
    assert not failures, "\n\n".join(f"{key}: {text}" for key, text in failures.items())
    assert list((Path(api.settings.blob_dir) / ".incoming").iterdir()) == []


def test_asset_times_are_rfc3339_date_times(tmp_path):
    """Regression found by the API fuzz: an asset's created_at came back from SQLite without an offset
    ("2026-11-21T21:36:18.760754"), which is not the RFC 3339 date-time the OpenAPI document promises.
    AssetPublic now marks stored times as UTC, as the bake and bundle records already did."""
    import datetime as dt

    from service_fixtures import make_api, png_bytes

    api = make_api(tmp_path)
    created = api.client.post("/v1/assets/textures", files={"file": ("diffuse_0.png", png_bytes())}, headers=api.auth("upload"))
    listed = api.client.get("/v1/assets", headers=api.auth("upload")).json()["data"][0]
    fetched = api.client.get(f"/v1/assets/{listed['id']}", headers=api.auth("upload")).json()
    for stamp in (created.json()["created_at"], listed["created_at"], fetched["created_at"]):
        assert dt.datetime.fromisoformat(stamp).utcoffset() == dt.timedelta(0), stamp
