"""One character LOD as a glTF 2.0 binary (.glb), written with pygltflib.

Each mesh part (body, garments) is a node with one mesh and one primitive: frame 0's positions and
normals, the texture coordinates (TEXCOORD_0, the bundle's convention is glTF's) and each vertex's
VAT texel (TEXCOORD_1, see crowdbake.export.vat). The cycle plays two ways:

- morph targets: target k-1 holds frame k minus frame 0 (positions and normals) for k = 1..F-1, and
  the animation `cycle` keys the weights one-hot at t = k / fps, all zero at t = 0 and t = F / fps
  (frame F is frame 0 again), with LINEAR interpolation, so any glTF viewer plays the cloth;
- vertex-animation textures, named in the mesh's `extras.crowdbake.vat` (docs/export.md), for
  engines that would rather not hold F morph targets.

Materials are metallic-roughness, roughness 1. Their looks are glTF variants (KHR_materials_variants,
read by three.js, Babylon.js and Blender): variant k is a diffuse variation with an outfit's colours
baked into its base-colour image (RGB: the bundle's diffuse alpha holds region codes, not opacity, so
the colours a shader would apply are multiplied in here), and variant 0 is also each primitive's
default material, so a viewer without the extension shows the first look. Garments are double-sided
because a skirt shows its inside.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pygltflib as g

from crowdbake import __version__

VARIANTS_EXTENSION = "KHR_materials_variants"


@dataclass(frozen=True)
class GlbPart:
    """One mesh part. positions, normals: (F, V, 3) float; uvs, vat_uvs: (V, 2); indices: (T, 3) int."""

    name: str
    kind: str  # "body" or "garment"
    material: int  # index into the materials passed with it
    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    vat_uvs: np.ndarray
    indices: np.ndarray
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class GlbMaterial:
    """One bundle material: per variant (GlbVariant, in order) its base-colour image, encoded."""

    name: str
    looks: list[bytes]
    mime_type: str = "image/jpeg"


@dataclass(frozen=True)
class GlbVariant:
    """One KHR_materials_variants variant: its name and what it shows (diffuse variation, outfit)."""

    name: str
    variation: int
    outfit: int


class _Blob:
    """The binary chunk: appends arrays as buffer views, each 4-byte aligned (glTF's accessor rule)."""

    def __init__(self, gltf: g.GLTF2):
        self.gltf = gltf
        self.data = bytearray()

    def view(self, payload: bytes, target: int | None = None) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        self.gltf.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(payload), target=target))
        self.data += payload
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array: np.ndarray, kind: str, target: int | None = g.ARRAY_BUFFER, bounds: bool = False) -> int:
        """An accessor over `array` ((N,) or (N, k) float32/uint16/uint32); min/max where glTF asks for them."""
        component = {np.dtype(np.float32): g.FLOAT, np.dtype(np.uint16): g.UNSIGNED_SHORT, np.dtype(np.uint32): g.UNSIGNED_INT}[array.dtype]
        view = self.view(np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<")).tobytes(), target)
        accessor = g.Accessor(bufferView=view, componentType=component, count=int(array.shape[0]), type=kind)
        if bounds:
            flat = array.reshape(array.shape[0], -1)
            accessor.min = [float(v) for v in flat.min(axis=0)]
            accessor.max = [float(v) for v in flat.max(axis=0)]
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1


def _unit(vectors: np.ndarray) -> np.ndarray:
    """(..., 3) float64 -> unit float32; glTF-Validator checks NORMAL lengths to 5e-4."""
    vectors = np.asarray(vectors, dtype=np.float64)
    return (vectors / np.maximum(np.linalg.norm(vectors, axis=-1, keepdims=True), 1e-12)).astype(np.float32)


def build_glb(parts: list[GlbPart], materials: list[GlbMaterial], variants: list[GlbVariant], frames_per_second: float,
              root_extras: dict[str, Any]) -> bytes:
    """The .glb bytes of one LOD: a root node holding one node per part, the `cycle` animation, and a glTF
    material per (bundle material, sidedness, variant), the variants mapped on every primitive."""
    if not parts:
        raise ValueError("a character LOD needs at least one part")
    frame_counts = {part.positions.shape[0] for part in parts}
    if len(frame_counts) != 1:
        raise ValueError(f"all parts must have the same frame count, got {sorted(frame_counts)}")
    (frame_count,) = frame_counts
    gltf = g.GLTF2(asset=g.Asset(version="2.0", generator=f"crowdbake {__version__}"))
    blob = _Blob(gltf)

    gltf.samplers.append(g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.REPEAT, wrapT=g.REPEAT))
    if not variants or any(len(m.looks) != len(variants) for m in materials):
        raise ValueError(f"every material needs one look per variant ({len(variants)})")
    texture_of: dict[tuple[int, int], int] = {}  # (bundle material, variant) -> texture, one image each
    material_index: dict[tuple[int, bool, int], int] = {}  # (bundle material, double-sided, variant) -> glTF material
    for part in parts:
        for v, variant in enumerate(variants):
            key = (part.material, part.kind == "garment", v)
            if key in material_index:
                continue
            source = materials[part.material]
            if (part.material, v) not in texture_of:
                gltf.images.append(g.Image(bufferView=blob.view(source.looks[v]), mimeType=source.mime_type, name=f"{source.name}_{variant.name}"))
                gltf.textures.append(g.Texture(sampler=0, source=len(gltf.images) - 1))
                texture_of[(part.material, v)] = len(gltf.textures) - 1
            gltf.materials.append(
                g.Material(
                    name=f"{source.name}{'_double_sided' if key[1] else ''}_{variant.name}",
                    pbrMetallicRoughness=g.PbrMetallicRoughness(
                        baseColorTexture=g.TextureInfo(index=texture_of[(part.material, v)]), metallicFactor=0.0, roughnessFactor=1.0
                    ),
                    doubleSided=key[1],
                )
            )
            material_index[key] = len(gltf.materials) - 1
    gltf.extensionsUsed = [VARIANTS_EXTENSION]
    gltf.extensions = {VARIANTS_EXTENSION: {"variants": [{"name": variant.name} for variant in variants]}}

    root = g.Node(name="character", children=[], extras=root_extras)
    gltf.nodes.append(root)
    targets_per_mesh = frame_count - 1
    for part in parts:
        base_positions = np.asarray(part.positions[0], dtype=np.float32)
        base_normals = _unit(part.normals[0])
        indices = np.asarray(part.indices).reshape(-1)
        index_type = np.uint16 if base_positions.shape[0] <= 65535 else np.uint32
        attributes = g.Attributes(
            POSITION=blob.accessor(base_positions, g.VEC3, bounds=True),
            NORMAL=blob.accessor(base_normals, g.VEC3),
            TEXCOORD_0=blob.accessor(np.asarray(part.uvs, dtype=np.float32), g.VEC2),
            TEXCOORD_1=blob.accessor(np.asarray(part.vat_uvs, dtype=np.float32), g.VEC2),
        )
        targets = []
        for frame in range(1, frame_count):
            position_delta = (np.asarray(part.positions[frame], dtype=np.float32) - base_positions).astype(np.float32)
            normal_delta = (_unit(part.normals[frame]) - base_normals).astype(np.float32)
            targets.append(
                g.Attributes(
                    POSITION=blob.accessor(position_delta, g.VEC3, bounds=True),
                    NORMAL=blob.accessor(normal_delta, g.VEC3),
                )
            )
        primitive = g.Primitive(
            attributes=attributes,
            indices=blob.accessor(indices.astype(index_type), g.SCALAR, target=g.ELEMENT_ARRAY_BUFFER),
            material=material_index[(part.material, part.kind == "garment", 0)],
            mode=g.TRIANGLES,
            targets=targets or None,
            extensions={VARIANTS_EXTENSION: {"mappings": [
                {"material": material_index[(part.material, part.kind == "garment", v)], "variants": [v]} for v in range(len(variants))
            ]}},
        )
        extras = {"targetNames": [f"frame_{frame}" for frame in range(1, frame_count)], "crowdbake": part.extras}
        gltf.meshes.append(
            g.Mesh(name=part.name, primitives=[primitive], weights=[0.0] * targets_per_mesh if targets else None, extras=extras)
        )
        gltf.nodes.append(g.Node(name=part.name, mesh=len(gltf.meshes) - 1))
        root.children.append(len(gltf.nodes) - 1)

    if targets_per_mesh:
        # Keys at every frame and once more at the cycle's end (frame F = frame 0: all weights 0).
        times = (np.arange(frame_count + 1) / frames_per_second).astype(np.float32)
        weights = np.zeros((frame_count + 1, targets_per_mesh), dtype=np.float32)
        weights[np.arange(1, frame_count), np.arange(targets_per_mesh)] = 1.0
        time_accessor = blob.accessor(times, g.SCALAR, target=None, bounds=True)
        weight_accessor = blob.accessor(weights.reshape(-1), g.SCALAR, target=None)
        animation = g.Animation(name="cycle", samplers=[g.AnimationSampler(input=time_accessor, output=weight_accessor, interpolation="LINEAR")])
        for node in root.children:
            animation.channels.append(g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=node, path="weights")))
        gltf.animations.append(animation)

    gltf.scenes.append(g.Scene(name="crowdbake", nodes=[0]))
    gltf.scene = 0
    blob.data += b"\0" * (-len(blob.data) % 4)
    gltf.buffers.append(g.Buffer(byteLength=len(blob.data)))
    gltf.set_binary_blob(bytes(blob.data))
    return b"".join(gltf.save_to_bytes())
