"""One character LOD as a glTF 2.0 binary (.glb), written with pygltflib.

Each mesh part (body, garments) is a node with one mesh and one primitive: frame 0's positions and
normals, quantized (KHR_mesh_quantization: int16 positions on a 14-bit grid that the node's scale and
translation dequantize, int8 normals; quantize_part), the texture coordinates (TEXCOORD_0, the bundle's
convention is glTF's) and each vertex's VAT texel (TEXCOORD_1, see crowdbake.export.vat). Every pose
frame of the bundle (all its clips and transitions) plays three ways:

- morph targets: the base is the mean pose and target k holds frame k minus it (positions and
  normals, quantized alike; a normal turned past about 90 degrees from the mean only approached:
  normal_deltas) for k = 0..F-1; one glTF animation per clip and per transition
  (crowdbake.export.animations: a v1 bundle's one `cycle`) keys the weights one-hot, key j at
  t = j / fps weighing the target of the pose frame it shows, with LINEAR interpolation, so any glTF
  viewer plays the cloth; the mesh's default weights show frame 0;
- bones, for a garment given GlbPart.bones (crowdbake.export.cloth_bones): a skinned mesh (float
  positions, JOINTS_0, WEIGHTS_0) whose joints the same animations key at the same times;
- a skin, for a body given GlbPart.skin (a skinned pose cache, crowdbake.export.body_skin): its rest mesh
  (float), the bundle's four influences a vertex (unorm16 weights), one joint node per joint whose
  translation, rotation and scale the animations key at the same times, and a corrective morph target
  for each pose frame that a blend of two poses left sheared;
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
from crowdbake.export.animations import AnimationPlan, animation_plans, gltf_extras
from crowdbake.export.body_skin import GltfSkin, hemisphere_continuous
from crowdbake.export.morph_normals import normal_deltas
from crowdbake.export.cloth_bones import ClothBones
from crowdbake.formats.ranges import Clip, Ranges

VARIANTS_EXTENSION = "KHR_materials_variants"
QUANTIZATION_EXTENSION = "KHR_mesh_quantization"
_INT16_MAX = 32767
_INT8_MAX = 127
# Positions and their morph deltas lie on a 14-bit grid inside the int16s (every 4th value, as gltfpack's
# default): a step of scale / 8191, 0.1 mm over a 1.8 m character, and two low bits that are always zero
# deflate away in the zip.
POSITION_GRID = 4


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
    bones: ClothBones | None = None  # a garment played by bones (crowdbake.export.cloth_bones) instead of morph targets
    skin: GltfSkin | None = None  # a body played as a glTF skin (crowdbake.export.body_skin) instead of morph targets


@dataclass(frozen=True)
class GlbMaterial:
    """One bundle material: per variant (GlbVariant, in order) its base-colour image as (media type, where):
    image/png or image/jpeg, the two every glTF reader takes; where: the encoded bytes, embedded in the
    .glb, or a URI relative to it (a file the LODs share)."""

    name: str
    looks: list[tuple[str, bytes | str]]


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

    def accessor(self, array: np.ndarray, kind: str, target: int | None = g.ARRAY_BUFFER, bounds: bool = False, normalized: bool = False) -> int:
        """An accessor over `array` ((N,) or (N, k) float32/uint16/uint32); min/max where glTF asks for them;
        normalized: unsigned integers read as c / max (unorm16 weights)."""
        component = {np.dtype(np.float32): g.FLOAT, np.dtype(np.uint16): g.UNSIGNED_SHORT, np.dtype(np.uint32): g.UNSIGNED_INT}[array.dtype]
        view = self.view(np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<")).tobytes(), target)
        accessor = g.Accessor(bufferView=view, componentType=component, count=int(array.shape[0]), type=kind, normalized=normalized or None)
        if bounds:
            flat = array.reshape(array.shape[0], -1)
            accessor.min = [float(v) for v in flat.min(axis=0)]
            accessor.max = [float(v) for v in flat.max(axis=0)]
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    def packed(self, array: np.ndarray, bounds: bool = False) -> int:
        """A normalized VEC3 accessor over (N, 4) int16 or int8 rows whose fourth component is padding:
        glTF wants every vertex element on a 4-byte boundary, so the view's stride is 8 or 4 bytes.
        min/max (POSITION asks for them) are the stored integers, as glTF and its validator want them."""
        component = {np.dtype(np.int16): g.SHORT, np.dtype(np.int8): g.BYTE}[array.dtype]
        if array.ndim != 2 or array.shape[1] != 4:
            raise ValueError(f"packed: expected (N, 4) rows, got {array.shape}")
        view = self.view(np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<")).tobytes(), g.ARRAY_BUFFER)
        self.gltf.bufferViews[view].byteStride = array.dtype.itemsize * 4
        accessor = g.Accessor(bufferView=view, componentType=component, normalized=True, count=int(array.shape[0]), type=g.VEC3)
        if bounds:
            values = array[:, :3]
            accessor.min = [int(v) for v in values.min(axis=0)]
            accessor.max = [int(v) for v in values.max(axis=0)]
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1


@dataclass(frozen=True)
class QuantizedPart:
    """One part's frames as KHR_mesh_quantization stores them: int16 positions and position deltas (on the
    POSITION_GRID), int8 normals and normal deltas, each (…, V, 4) with a zero pad component. The base is
    the loop's mean pose and target k holds frame k (k = 0..F-1). Dequantized position of frame k:
    offset + scale · (positions[0] + position_deltas[k]) / 32767 (the node's translation and scale)."""

    positions: np.ndarray  # (1, V, 4) int16: the mean pose
    position_deltas: np.ndarray  # (F, V, 4) int16: frame k minus the mean pose
    normals: np.ndarray  # (1, V, 4) int8: the mean normals, normalised (frame 0's where they cancel out)
    normal_deltas: np.ndarray  # (F, V, 4) int8: normal_deltas(), frame k's normal (scaled) minus the base's
    offset: np.ndarray  # (3,) float64 metres
    scale: float  # metres per unit of the normalized int16

    @property
    def max_position_error_m(self) -> float:
        """The largest error of a dequantized position per axis, metres: half a grid step for the base and
        for the delta, rounded apart."""
        return self.scale * POSITION_GRID / _INT16_MAX


def quantize_part(positions: np.ndarray, normals: np.ndarray) -> QuantizedPart:
    """positions, normals: (F, V, 3) float, metres and unit vectors -> QuantizedPart.

    The base is the mean pose rather than frame 0: a normalized int8 delta holds a normal turned at most
    about 90 degrees from the base's (normal_deltas), and cloth turns less far from its mean direction
    (on the sample's skirt no normal turns past 90 degrees from its mean, 1.3 % from frame 0; on the long
    skirt 9 % against 23 %). One scale for the base and the deltas (node_transform).
    """
    positions = np.asarray(positions, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or normals.shape != positions.shape or positions.shape[1] == 0:
        raise ValueError(f"positions and normals must be (F, V, 3) alike with V > 0, got {positions.shape} and {normals.shape}")
    base = positions.mean(axis=0)
    offset, scale = node_transform(positions)
    deltas = positions - base
    unit = _unit(normals).astype(np.float64)
    mean = unit.mean(axis=0)
    lengths = np.linalg.norm(mean, axis=1, keepdims=True)
    base_normals = np.where(lengths > _MIN_MEAN_NORMAL, mean / np.maximum(lengths, _MIN_MEAN_NORMAL), unit[0])

    def pad(values: np.ndarray, limit: int, dtype, grid: int = 1) -> np.ndarray:
        out = np.zeros(values.shape[:-1] + (4,), dtype)
        out[..., :3] = np.clip(np.rint(values * limit / grid) * grid, -limit, limit)
        return out

    return QuantizedPart(
        positions=pad((base - offset)[None] / scale, _INT16_MAX, np.int16, POSITION_GRID),
        position_deltas=pad(deltas / scale, _INT16_MAX, np.int16, POSITION_GRID),
        normals=pad(base_normals[None], _INT8_MAX, np.int8),
        normal_deltas=pad(normal_deltas(base_normals, unit), _INT8_MAX, np.int8),
        offset=offset,
        scale=scale,
    )


# A vertex whose normals cancel out over the loop (turning evenly round) has no mean direction: frame 0's.
_MIN_MEAN_NORMAL = 1e-3


def node_transform(positions: np.ndarray) -> tuple[np.ndarray, float]:
    """(F, V, 3) metres -> the part node's (translation (3,), uniform scale) that dequantizes its mesh: the
    centre of the mean pose's box, and the larger of that pose's half extent round it and the largest
    delta of a frame from it."""
    positions = np.asarray(positions, dtype=np.float64)
    base = positions.mean(axis=0)
    offset = (base.min(axis=0) + base.max(axis=0)) / 2
    deltas = positions - base
    return offset, float(max(np.abs(base - offset).max(), np.abs(deltas).max() if deltas.size else 0.0, 1e-9))


def _unit(vectors: np.ndarray) -> np.ndarray:
    """(..., 3) float64 -> unit float32; glTF-Validator checks NORMAL lengths to 5e-4."""
    vectors = np.asarray(vectors, dtype=np.float64)
    return (vectors / np.maximum(np.linalg.norm(vectors, axis=-1, keepdims=True), 1e-12)).astype(np.float32)


def build_glb(parts: list[GlbPart], materials: list[GlbMaterial], variants: list[GlbVariant], frames_per_second: float,
              root_extras: dict[str, Any], animations: list[AnimationPlan] | None = None) -> bytes:
    """The .glb bytes of one LOD: a root node holding one node per part, one glTF animation per plan
    (crowdbake.export.animations; None: one looping `cycle` over every frame), and a glTF material per
    (bundle material, sidedness, variant), the variants mapped on every primitive."""
    if not parts:
        raise ValueError("a character LOD needs at least one part")
    frame_counts = {part.positions.shape[0] for part in parts}
    if len(frame_counts) != 1:
        raise ValueError(f"all parts must have the same frame count, got {sorted(frame_counts)}")
    (frame_count,) = frame_counts
    if animations is None:
        animations = [whole_loop(frame_count)]
    for plan in animations:
        if plan.keys.size and (plan.keys.min() < 0 or plan.keys.max() >= frame_count):
            raise ValueError(f"animation {plan.name!r} keys pose frames outside 0..{frame_count - 1}")
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
                mime_type, where = source.looks[v]
                name = f"{source.name}_{variant.name}"
                gltf.images.append(g.Image(uri=where, name=name) if isinstance(where, str) else g.Image(bufferView=blob.view(where), mimeType=mime_type, name=name))
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
    gltf.extensionsUsed = [VARIANTS_EXTENSION, QUANTIZATION_EXTENSION]
    gltf.extensionsRequired = [QUANTIZATION_EXTENSION]
    gltf.extensions = {VARIANTS_EXTENSION: {"variants": [{"name": variant.name} for variant in variants]}}

    root = g.Node(name="character", children=[], extras=root_extras)
    gltf.nodes.append(root)
    scene_nodes = [0]
    targets_per_mesh = frame_count
    morph_nodes, bone_tracks = [], []  # nodes whose weights the animations key; (joint node, rotations, translations)
    skin_tracks: list[tuple[int | None, list[int], GltfSkin]] = []  # (node of its corrective targets, joint nodes, skin)
    for part in parts:
        indices = np.asarray(part.indices).reshape(-1)
        index_type = np.uint16 if part.positions.shape[1] <= 65535 else np.uint32
        mappings = [{"material": material_index[(part.material, part.kind == "garment", v)], "variants": [v]} for v in range(len(variants))]
        if part.skin is not None:
            attributes, targets = _skin_attributes(blob, part.skin)
        elif part.bones is None:
            quantized = quantize_part(part.positions, part.normals)
            attributes = g.Attributes(POSITION=blob.packed(quantized.positions[0], bounds=True), NORMAL=blob.packed(quantized.normals[0]))
            targets = [
                g.Attributes(POSITION=blob.packed(quantized.position_deltas[k], bounds=True), NORMAL=blob.packed(quantized.normal_deltas[k]))
                for k in range(targets_per_mesh)
            ]
        else:
            # Skinned (crowdbake.export.cloth_bones): frame 0 in metres, posed by its bones; no morph targets.
            attributes = g.Attributes(
                POSITION=blob.accessor(np.asarray(part.positions[0], dtype=np.float32), g.VEC3, bounds=True),
                NORMAL=blob.accessor(_unit(part.normals[0]), g.VEC3),
                JOINTS_0=blob.accessor(np.asarray(part.bones.joints, dtype=np.uint16), g.VEC4),
                WEIGHTS_0=blob.accessor(np.asarray(part.bones.weights, dtype=np.float32), g.VEC4),
            )
            targets = []
        attributes.TEXCOORD_0 = blob.accessor(np.asarray(part.uvs, dtype=np.float32), g.VEC2)
        attributes.TEXCOORD_1 = blob.accessor(np.asarray(part.vat_uvs, dtype=np.float32), g.VEC2)
        primitive = g.Primitive(
            attributes=attributes,
            indices=blob.accessor(indices.astype(index_type), g.SCALAR, target=g.ELEMENT_ARRAY_BUFFER),
            material=material_index[(part.material, part.kind == "garment", 0)],
            mode=g.TRIANGLES,
            targets=targets or None,
            extensions={VARIANTS_EXTENSION: {"mappings": mappings}},
        )
        target_frames = part.skin.corrected.tolist() if part.skin is not None else list(range(frame_count))
        extras = {"crowdbake": part.extras} | ({"targetNames": [f"frame_{frame}" for frame in target_frames]} if targets else {})
        # Default weights show frame 0, for a viewer that does not play the animation.
        gltf.meshes.append(g.Mesh(name=part.name, primitives=[primitive], weights=[float(frame == 0) for frame in target_frames] if targets else None,
                                  extras=extras))
        if part.skin is not None:
            skin_tracks.append(_add_skin(gltf, root, scene_nodes, part.name, part.skin, len(gltf.meshes) - 1, blob, bool(targets)))
            continue
        if part.bones is None:
            # The quantization's dequantization (KHR_mesh_quantization): node scale and translation.
            gltf.nodes.append(g.Node(name=part.name, mesh=len(gltf.meshes) - 1, translation=quantized.offset.tolist(), scale=[quantized.scale] * 3))
            root.children.append(len(gltf.nodes) - 1)
            if targets:
                morph_nodes.append(len(gltf.nodes) - 1)
            continue
        # The bones are children of the character, so they move with it; the skinned mesh's node is a scene
        # root, as glTF ignores a skinned mesh node's own transform. Bind pose: identity (frame 0).
        joints = []
        for bone in range(part.bones.bone_count):
            gltf.nodes.append(g.Node(name=f"{part.name}_bone_{bone}", rotation=part.bones.rotations[0, bone].tolist(),
                                     translation=part.bones.translations[0, bone].tolist()))
            joints.append(len(gltf.nodes) - 1)
            root.children.append(joints[-1])
            bone_tracks.append((joints[-1], part.bones.rotations[:, bone], part.bones.translations[:, bone]))
        gltf.skins.append(g.Skin(name=f"{part.name}_bones", joints=joints, skeleton=0))
        gltf.nodes.append(g.Node(name=part.name, mesh=len(gltf.meshes) - 1, skin=len(gltf.skins) - 1))
        scene_nodes.append(len(gltf.nodes) - 1)

    if morph_nodes or bone_tracks or skin_tracks:
        times_of: dict[int, int] = {}  # key count -> the time accessor, shared by animations of one length
        for plan in animations:
            _add_animation(gltf, blob, plan, frame_count, frames_per_second, morph_nodes, bone_tracks, times_of, skin_tracks)

    gltf.scenes.append(g.Scene(name="crowdbake", nodes=scene_nodes))
    gltf.scene = 0
    blob.data += b"\0" * (-len(blob.data) % 4)
    gltf.buffers.append(g.Buffer(byteLength=len(blob.data)))
    gltf.set_binary_blob(bytes(blob.data))
    return b"".join(gltf.save_to_bytes())


def whole_loop(frame_count: int) -> AnimationPlan:
    """One looping clip `cycle` over pose frames 0..frame_count-1 (a v1 bundle's one animation)."""
    return animation_plans(Ranges(frame_count, (Clip("cycle", 0, frame_count, 0, frame_count, "none", 0.0, 0.0),), ()))[0]


def _skin_attributes(blob: _Blob, skin: GltfSkin) -> tuple[g.Attributes, list[g.Attributes]]:
    """A skinned body's attributes (rest mesh in float, JOINTS_0, unorm16 WEIGHTS_0) and its corrective
    targets (float position deltas, int8 normal deltas), one per skin.corrected frame."""
    # A joint a vertex does not weigh is 0, as glTF asks of unused influences.
    joints = np.where(skin.weight_codes > 0, skin.joints, 0).astype(np.uint16)
    attributes = g.Attributes(
        POSITION=blob.accessor(np.asarray(skin.rest_positions, dtype=np.float32), g.VEC3, bounds=True),
        NORMAL=blob.accessor(_unit(skin.rest_normals), g.VEC3),
        JOINTS_0=blob.accessor(joints, g.VEC4),
        WEIGHTS_0=blob.accessor(np.asarray(skin.weight_codes, dtype=np.uint16), g.VEC4, normalized=True),
    )
    targets = []
    for row in range(skin.corrected.size):
        normals = np.zeros((skin.normal_deltas.shape[1], 4), np.int8)
        normals[:, :3] = np.clip(np.rint(skin.normal_deltas[row] * _INT8_MAX), -_INT8_MAX, _INT8_MAX)
        targets.append(g.Attributes(POSITION=blob.accessor(np.asarray(skin.position_deltas[row], dtype=np.float32), g.VEC3, bounds=True),
                                    NORMAL=blob.packed(normals)))
    return attributes, targets


def _add_skin(gltf: g.GLTF2, root: g.Node, scene_nodes: list[int], name: str, skin: GltfSkin, mesh: int, blob: _Blob,
              corrective: bool) -> tuple[int | None, list[int], GltfSkin]:
    """The joint nodes (children of the character, at pose frame 0), the glTF skin (identity inverse binds:
    a joint's TRS is its skinning matrix) and the skinned mesh's node (a scene root: glTF ignores a skinned
    mesh node's own transform). Returns what _add_animation keys: (the mesh node when it has corrective
    targets, the joint nodes, the skin)."""
    joints = []
    for joint in range(skin.joint_count):
        gltf.nodes.append(g.Node(name=f"{name}_joint_{joint}", translation=skin.translations[0, joint].tolist(),
                                 rotation=skin.rotations[0, joint].tolist(), scale=skin.scales[0, joint].tolist()))
        joints.append(len(gltf.nodes) - 1)
        root.children.append(joints[-1])
    inverse_binds = np.tile(np.eye(4, dtype=np.float32).reshape(1, 16), (skin.joint_count, 1))
    gltf.skins.append(g.Skin(name=f"{name}_skin", joints=joints, skeleton=0, inverseBindMatrices=blob.accessor(inverse_binds, g.MAT4, target=None)))
    gltf.nodes.append(g.Node(name=name, mesh=mesh, skin=len(gltf.skins) - 1))
    scene_nodes.append(len(gltf.nodes) - 1)
    return (len(gltf.nodes) - 1 if corrective else None), joints, skin


def _add_animation(gltf: g.GLTF2, blob: _Blob, plan: AnimationPlan, target_count: int, frames_per_second: float, morph_nodes: list[int],
                   bone_tracks: list[tuple[int, np.ndarray, np.ndarray]], times_of: dict[int, int],
                   skin_tracks: list[tuple[int | None, list[int], GltfSkin]] = ()) -> None:
    """One glTF animation playing `plan`: key j at t = j / fps shows pose frame plan.keys[j], LINEAR between.
    Morph nodes: every morph target's weight (glTF keys them all together), target keys[j] alone at key j,
    so each animation plays its own range of the targets every animation shares. Bones: each joint's
    rotation and translation at those frames. Skins: each weighted joint's translation, rotation and scale
    at those frames, and the corrective target of a key's frame (if it has one) weighing 1."""
    if plan.key_count not in times_of:
        times = (np.arange(plan.key_count) / frames_per_second).astype(np.float32)
        times_of[plan.key_count] = blob.accessor(times, g.SCALAR, target=None, bounds=True)
    time_accessor = times_of[plan.key_count]
    animation = g.Animation(name=plan.name, samplers=[], channels=[], extras={"crowdbake": gltf_extras(plan)})
    if morph_nodes:
        weights = np.zeros((plan.key_count, target_count), dtype=np.float32)
        weights[np.arange(plan.key_count), plan.keys] = 1.0
        animation.samplers.append(g.AnimationSampler(input=time_accessor, output=blob.accessor(weights.reshape(-1), g.SCALAR, target=None),
                                                     interpolation="LINEAR"))
        for node in morph_nodes:
            animation.channels.append(g.AnimationChannel(sampler=0, target=g.AnimationChannelTarget(node=node, path="weights")))
    for node, rotations, translations in bone_tracks:
        for path, values, kind in (("rotation", rotations, g.VEC4), ("translation", translations, g.VEC3)):
            keyed = np.asarray(values[plan.keys], dtype=np.float32)
            animation.samplers.append(g.AnimationSampler(input=time_accessor, output=blob.accessor(keyed, kind, target=None), interpolation="LINEAR"))
            animation.channels.append(g.AnimationChannel(sampler=len(animation.samplers) - 1, target=g.AnimationChannelTarget(node=node, path=path)))
    for mesh_node, joints, skin in skin_tracks:
        if mesh_node is not None:
            weights = (skin.corrected[None, :] == plan.keys[:, None]).astype(np.float32)  # (K, C) one-hot or all 0
            animation.samplers.append(g.AnimationSampler(input=time_accessor, output=blob.accessor(weights.reshape(-1), g.SCALAR, target=None),
                                                         interpolation="LINEAR"))
            animation.channels.append(g.AnimationChannel(sampler=len(animation.samplers) - 1, target=g.AnimationChannelTarget(node=mesh_node, path="weights")))
        rotations = hemisphere_continuous(skin.rotations[plan.keys])
        for joint in skin.animated:
            for path, values, kind in (("translation", skin.translations, g.VEC3), ("rotation", rotations, g.VEC4), ("scale", skin.scales, g.VEC3)):
                keyed = np.asarray(values[:, joint] if path == "rotation" else values[plan.keys, joint], dtype=np.float32)
                animation.samplers.append(g.AnimationSampler(input=time_accessor, output=blob.accessor(keyed, kind, target=None), interpolation="LINEAR"))
                animation.channels.append(g.AnimationChannel(sampler=len(animation.samplers) - 1,
                                                             target=g.AnimationChannelTarget(node=joints[joint], path=path)))
    gltf.animations.append(animation)
