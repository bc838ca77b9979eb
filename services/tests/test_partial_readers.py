"""Readers that take one frame of a CBPC or one layer of a CBTX without reading the rest
(crowdbake.formats.binary.read_pose_frame, read_texture_layer) check the header like the full
decoders: a wrong magic, a future version or a truncated file is a FormatError, never a misread."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from crowdbake.formats.binary import (
    decode_pose_cache,
    decode_texture_array,
    encode_pose_cache,
    encode_quantized_pose_cache,
    encode_texture_array,
    read_pose_frame,
    read_texture_layer,
)
from crowdbake.formats.errors import FormatError


def pose_cache_bytes(frames: int = 3, encode=encode_pose_cache) -> bytes:
    rng = np.random.default_rng(4)
    positions = rng.normal(size=(frames, 4, 3)).astype(np.float32)
    normals = rng.normal(size=(frames, 4, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    uvs = rng.random((4, 2)).astype(np.float32)
    return encode(np.array([[0, 1, 2], [0, 2, 3]]), uvs, positions, normals.astype(np.float32), 24.0)


@pytest.mark.parametrize("encode", [encode_pose_cache, encode_quantized_pose_cache])
def test_one_frame_equals_that_frame_of_the_whole_cache(tmp_path, encode):
    data = pose_cache_bytes(encode=encode)
    path = tmp_path / "part.cbpc"
    path.write_bytes(data)
    whole = decode_pose_cache(data)
    for frame in range(whole.frame_count):
        indices, uvs, positions, normals = read_pose_frame(path, frame)
        assert np.array_equal(indices, whole.indices) and np.array_equal(uvs, whole.uvs)
        assert np.array_equal(positions, whole.positions[frame]) and np.array_equal(normals, whole.normals[frame])
    with pytest.raises(IndexError):
        read_pose_frame(path, whole.frame_count)


@pytest.mark.parametrize("change,code", [
    (lambda d: b"XBPC" + d[4:], "bad_magic"),
    (lambda d: d[:4] + struct.pack("<I", 3) + d[8:], "unsupported_version"),
    (lambda d: d[:-1], "truncated"),
    (lambda d: d[:20], "truncated"),
])
def test_a_broken_pose_cache_header_is_refused(tmp_path, change, code):
    path = tmp_path / "broken.cbpc"
    path.write_bytes(change(pose_cache_bytes()))
    with pytest.raises(FormatError) as caught:
        read_pose_frame(path, 0)
    assert caught.value.code == code


def test_one_layer_equals_that_layer_of_the_whole_array(tmp_path):
    layers = [bytes(range(k, k + 64)) for k in range(3)]
    data = encode_texture_array(4, 4, "rgba8", layers)
    path = tmp_path / "t.cbtx"
    path.write_bytes(data)
    whole = decode_texture_array(data)
    for layer in range(3):
        assert read_texture_layer(path, layer) == ("rgba8", 4, 4, 3, whole.layers[layer])
    with pytest.raises(IndexError):
        read_texture_layer(path, 3)
    path.write_bytes(b"CBPC" + data[4:])
    with pytest.raises(FormatError) as caught:
        read_texture_layer(path, 0)
    assert caught.value.code == "bad_magic"
    path.write_bytes(data[:-1])
    with pytest.raises(FormatError):
        read_texture_layer(path, 2)
