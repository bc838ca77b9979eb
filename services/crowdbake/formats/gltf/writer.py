"""encode_character / write_character: a Character as a deterministic .glb (one mesh, one skin, its animation,
or several named ones).
A Character with morph targets is refused (they are not written).

The texture is embedded as PNG (Pillow); accessors are 4-byte aligned in one buffer.
"""
from __future__ import annotations

import io
import json
import os
import struct
from pathlib import Path
from typing import Sequence

import numpy as np

from crowdbake.formats.gltf.accessors import COMPONENT_TYPES
from crowdbake.formats.gltf.animation import PATH_WIDTHS
from crowdbake.formats.gltf.document import CHUNK_BIN, CHUNK_JSON, GLB_MAGIC, GLB_VERSION
from crowdbake.formats.gltf.meshes import MODE_TRIANGLES
from crowdbake.formats.gltf.model import AnimationChannel, Character

NamedAnimation = tuple[str, Sequence[AnimationChannel]]


class _BinaryBuilder:
    """Accumulates 4-byte aligned bufferViews and accessors for one GLB buffer."""

    def __init__(self) -> None:
        self.chunks: list[bytes] = []
        self.length = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        padding = (-self.length) % 4
        if padding:
            self.chunks.append(b"\0" * padding)
            self.length += padding
        view = {"buffer": 0, "byteOffset": self.length, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        self.chunks.append(data)
        self.length += len(data)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, component: int, target: int | None = None, bounds: bool = False) -> int:
        dtype = COMPONENT_TYPES[component]
        array = np.ascontiguousarray(array, dtype=dtype)
        count = array.shape[0]
        accessor = {"bufferView": self.view(array.tobytes(), target), "componentType": component, "count": count, "type": kind}
        if bounds:
            flat = array.reshape(count, -1)
            cast = float if dtype.kind == "f" else int
            accessor["min"] = [cast(v) for v in flat.min(axis=0)]
            accessor["max"] = [cast(v) for v in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def payload(self) -> bytes:
        return b"".join(self.chunks) + b"\0" * ((-self.length) % 4)


def _png_bytes(texture: np.ndarray) -> bytes:
    from PIL import Image

    texture = np.asarray(texture, dtype=np.uint8)
    if texture.ndim != 3 or texture.shape[2] != 4:
        raise ValueError(f"texture must be (H, W, 4) uint8, got {texture.shape}")
    out = io.BytesIO()
    Image.fromarray(texture, "RGBA").save(out, format="PNG", optimize=False, compress_level=6)
    return out.getvalue()


def encode_character(character: Character, animations: Sequence[NamedAnimation] | None = None) -> bytes:
    """GLB bytes for a Character: one mesh, one skin, the animations, the texture embedded as PNG.

    animations: (name, channels) pairs written in order as named glTF animations; None writes the
    character's own channels as one animation named "cycle".

    Joints become nodes 0..J-1 in joint order; a non-identity joint_parent_transforms[j] becomes a
    helper node with that matrix between joint j and its parent. The output is deterministic.
    """
    c = character
    vertex_count, joint_count = c.vertex_count, c.joint_count
    for name, array, shape in (
        ("normals", c.normals, (vertex_count, 3)),
        ("uvs", c.uvs, (vertex_count, 2)),
        ("joints", c.joints, (vertex_count, 4)),
        ("weights", c.weights, (vertex_count, 4)),
        ("inverse_bind_matrices", c.inverse_bind_matrices, (joint_count, 4, 4)),
        ("joint_parent_transforms", c.joint_parent_transforms, (joint_count, 4, 4)),
    ):
        if np.shape(array) != shape:
            raise ValueError(f"{name} must be {shape}, got {np.shape(array)}")
    faces = np.asarray(c.faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.max() >= vertex_count:
        raise ValueError("faces must be (T, 3) indices into the vertices")
    if np.asarray(c.joints).max() >= joint_count:
        raise ValueError("a joint index exceeds the joint count")
    if c.morph_targets:
        # Not silently dropped: the writer has one mesh and one animation of joint channels only.
        raise ValueError(f"the character has {len(c.morph_targets)} morph targets ({', '.join(t.name for t in c.morph_targets)}), "
                         "which encode_character does not write")

    builder = _BinaryBuilder()
    nodes: list[dict] = []
    for j in range(joint_count):
        node: dict = {"name": c.joint_names[j] if j < len(c.joint_names) else f"joint{j}"}
        t, r, s = c.rest_translations[j], c.rest_rotations[j], c.rest_scales[j]
        if np.any(t != 0):
            node["translation"] = [float(v) for v in t]
        if np.any(r != np.array([0, 0, 0, 1])):
            node["rotation"] = [float(v) for v in r]
        if np.any(s != 1):
            node["scale"] = [float(v) for v in s]
        nodes.append(node)
    scene_roots: list[int] = []
    for j in range(joint_count):
        attach = j
        if not np.allclose(c.joint_parent_transforms[j], np.eye(4), atol=0, rtol=0):
            nodes.append({"name": f"{nodes[j]['name']}_parent", "matrix": [float(v) for v in c.joint_parent_transforms[j].T.reshape(-1)], "children": [j]})
            attach = len(nodes) - 1
        parent = int(c.joint_parents[j])
        if parent < 0:
            scene_roots.append(attach)
        else:
            nodes[parent].setdefault("children", []).append(attach)

    ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
    index_component = 5123 if vertex_count <= 65535 else 5125
    attributes = {
        "POSITION": builder.accessor(c.positions, "VEC3", 5126, ARRAY_BUFFER, bounds=True),
        "NORMAL": builder.accessor(c.normals, "VEC3", 5126, ARRAY_BUFFER),
        "TEXCOORD_0": builder.accessor(c.uvs, "VEC2", 5126, ARRAY_BUFFER),
        "JOINTS_0": builder.accessor(c.joints, "VEC4", 5123, ARRAY_BUFFER),
        "WEIGHTS_0": builder.accessor(c.weights, "VEC4", 5126, ARRAY_BUFFER),
    }
    indices = builder.accessor(faces.reshape(-1), "SCALAR", index_component, ELEMENT_ARRAY_BUFFER)
    primitive: dict = {"attributes": attributes, "indices": indices, "mode": MODE_TRIANGLES}
    gltf: dict = {"asset": {"version": "2.0", "generator": "crowdbake"}}
    if c.texture is not None:
        image_view = builder.view(_png_bytes(c.texture))
        gltf["images"] = [{"bufferView": image_view, "mimeType": "image/png"}]
        # Nearest filtering keeps alpha region codes exact where a viewer samples them.
        gltf["samplers"] = [{"magFilter": 9728, "minFilter": 9984, "wrapS": 33071, "wrapT": 33071}]
        gltf["textures"] = [{"sampler": 0, "source": 0}]
        # alphaMode stays OPAQUE: alpha carries colour-region codes, not coverage.
        gltf["materials"] = [{"name": "body", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 0.9}}]
        primitive["material"] = 0
    inverse_bind = builder.accessor(np.asarray(c.inverse_bind_matrices).transpose(0, 2, 1).reshape(joint_count, 16), "MAT4", 5126)

    if animations is None:
        animations = [("cycle", c.channels)] if c.channels else []
    time_accessors: dict[bytes, int] = {}  # clips sampled at the same times share their input accessor
    written = []
    for name, clip_channels in animations:
        samplers, channels = [], []
        for channel in clip_channels:
            times = np.asarray(channel.times, dtype=np.float32)
            key = times.tobytes()
            if key not in time_accessors:
                time_accessors[key] = builder.accessor(times, "SCALAR", 5126, bounds=True)
            width = PATH_WIDTHS[channel.path]
            output = builder.accessor(np.asarray(channel.values, dtype=np.float32).reshape(-1, width), "VEC4" if width == 4 else "VEC3", 5126)
            samplers.append({"input": time_accessors[key], "output": output, "interpolation": channel.interpolation})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": int(channel.joint), "path": channel.path}})
        written.append({"name": name, "samplers": samplers, "channels": channels})
    if written:
        gltf["animations"] = written

    mesh_node = len(nodes)
    nodes.append({"name": c.name or "character", "mesh": 0, "skin": 0})
    gltf.update(
        {
            "scene": 0,
            "scenes": [{"nodes": scene_roots + [mesh_node]}],
            "nodes": nodes,
            "meshes": [{"name": c.name or "character", "primitives": [primitive]}],
            "skins": [{"joints": list(range(joint_count)), "inverseBindMatrices": inverse_bind}],
            "accessors": builder.accessors,
            "bufferViews": builder.views,
            "buffers": [{"byteLength": builder.length}],
        }
    )
    if len(scene_roots) == 1:
        gltf["skins"][0]["skeleton"] = scene_roots[0]
    json_bytes = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    json_bytes += b" " * ((-len(json_bytes)) % 4)
    binary = builder.payload()
    total = 12 + 8 + len(json_bytes) + 8 + len(binary)
    return b"".join(
        [
            struct.pack("<4sII", GLB_MAGIC, GLB_VERSION, total),
            struct.pack("<II", len(json_bytes), CHUNK_JSON),
            json_bytes,
            struct.pack("<II", len(binary), CHUNK_BIN),
            binary,
        ]
    )


def write_character(path: str | os.PathLike, character: Character, animations: Sequence[NamedAnimation] | None = None) -> None:
    """Write a Character as a .glb (see encode_character)."""
    Path(path).write_bytes(encode_character(character, animations))
