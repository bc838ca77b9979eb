"""One character LOD as a glTF 2.0 binary (.glb), written with pygltflib.

Each mesh part (body, garments) is a node with one mesh and one primitive: frame 0's positions and
normals, quantized (KHR_mesh_quantization: int16 positions on a 13-bit grid that the node's scale and
translation dequantize, int8 normals; quantize_part), the texture coordinates (TEXCOORD_0, the bundle's
convention is glTF's) and each vertex's VAT texel (TEXCOORD_1, see crowdbake.export.vat). Every pose
frame of the bundle (all its clips and transitions) plays three ways:

- morph targets: the base is the mean pose and target k holds frame k minus its parent frame in a tree
  of the frames (positions and normals, quantized alike; QuantizedPart), for k = 0..F-1; one glTF
  animation per clip and per transition (crowdbake.export.animations: a v1 bundle's one `cycle`) keys
  the weights, key j at t = j / fps weighing 1 the targets on the path of the pose frame it shows, with
  LINEAR interpolation, so any glTF viewer plays the cloth; the mesh's default weights show frame 0;
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
from crowdbake.export.cloth_bones import ClothBones
from crowdbake.formats.ranges import Clip, Ranges

VARIANTS_EXTENSION = "KHR_materials_variants"
QUANTIZATION_EXTENSION = "KHR_mesh_quantization"
_INT16_MAX = 32767
_INT8_MAX = 127
# Positions and their morph deltas lie on a 13-bit grid inside the int16s (every 8th value): a step of
# scale / 4095, and three low bits that are always zero deflate away in the zip. Every frame is rounded
# once onto the grid (its targets are differences of rounded frames), so it lies within half a step:
# 0.18 mm on the robot's cape, 0.05 mm on the sample's skirt (the 14-bit grid rounded base and delta
# apart: a whole step of the finer grid, the same bound in 0.3 MB more of the robot's zip).
POSITION_GRID = 8


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
        """An accessor over `array` ((N,) or (N, k) float32/uint8/int16/uint16/uint32); min/max where glTF asks
        for them; normalized: integers read as c / max (unorm16 weights, unorm8 keyed morph weights, snorm16
        keyed rotations)."""
        component = {np.dtype(np.float32): g.FLOAT, np.dtype(np.uint8): g.UNSIGNED_BYTE, np.dtype(np.int16): g.SHORT,
                     np.dtype(np.uint16): g.UNSIGNED_SHORT, np.dtype(np.uint32): g.UNSIGNED_INT}[array.dtype]
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
    POSITION_GRID), int8 normals and normal deltas, each (…, V, 4) with a zero pad component.

    The base is the loop's mean pose (with the normals of the frame nearest it). Target k holds pose frame k minus its parent: pose frame parents[k],
    or the base where parents[k] is -1. The parents form a tree over the frames (morph_tree), so frame k is
    the base plus every target on its path (path_weights): a player keys those weights 1 and the rest 0,
    and between two keys blends the two frames exactly, as glTF's weighted sum is linear. Neighbouring
    frames differ by little, so the deltas are small numbers that deflate to about two thirds of what
    differences from the mean pose take. Dequantized position of frame k:
    offset + scale · (positions[0] + Σ_path position_deltas) / 32767 (the node's translation and scale)."""

    positions: np.ndarray  # (1, V, 4) int16: the mean pose
    position_deltas: np.ndarray  # (F, V, 4) int16: frame k minus frame parents[k] (the base for -1)
    normals: np.ndarray  # (1, V, 4) int8: the normals of the base's first child frame (morph_tree)
    normal_deltas: np.ndarray  # (F, V, 4) int8: what takes the parent's summed normal to frame k's
    parents: np.ndarray  # (F,) int64: each target's parent pose frame, -1 for the base
    offset: np.ndarray  # (3,) float64 metres
    scale: float  # metres per unit of the normalized int16

    @property
    def max_position_error_m(self) -> float:
        """The largest error of a dequantized position per axis, metres: half a grid step (the base plus the
        frame's summed deltas is the frame's own position rounded once onto the grid)."""
        return self.scale * POSITION_GRID / (2 * _INT16_MAX)

    def path_weights(self, frames: np.ndarray) -> np.ndarray:
        """(K,) pose frames -> (K, F) float32 morph weights showing each: 1 on the targets of its path."""
        return path_weights(self.parents, frames)

    def played(self) -> tuple[np.ndarray, np.ndarray]:
        """(positions (F, V, 3) metres, normals (F, V, 3) unit): every frame as a glTF player shows it at full
        weights (for tests and reports)."""
        weights = self.path_weights(np.arange(self.parents.size)).astype(np.float64)
        summed = self.positions[0, :, :3].astype(np.float64) + np.einsum("kf,fvi->kvi", weights, self.position_deltas[..., :3].astype(np.float64))
        normals = self.normals[0, :, :3].astype(np.float64) + np.einsum("kf,fvi->kvi", weights, self.normal_deltas[..., :3].astype(np.float64))
        normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
        return self.offset + self.scale * summed / _INT16_MAX, normals


def path_weights(parents: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """parents (F,) of a morph tree (morph_tree), (K,) pose frames -> (K, F) float32: 1 where a target lies on
    the frame's path to the base (the frame's own target, its parent's, ...), else 0."""
    parents = np.asarray(parents, dtype=np.int64)
    on_path = np.zeros((parents.size, parents.size), dtype=np.float32)
    for frame in _root_first(parents):
        if parents[frame] >= 0:
            on_path[frame] = on_path[parents[frame]]
        on_path[frame, frame] = 1.0
    return on_path[np.asarray(frames, dtype=np.int64)]


def _root_first(parents: np.ndarray) -> list[int]:
    """The frames of a morph tree, every parent before its children."""
    children: dict[int, list[int]] = {}
    for frame, parent in enumerate(parents.tolist()):
        children.setdefault(parent, []).append(frame)
    order, stack = [], list(reversed(children.get(-1, [])))
    while stack:
        frame = stack.pop()
        order.append(frame)
        stack.extend(reversed(children.get(frame, [])))
    if len(order) != parents.size:
        raise ValueError("the morph parents do not form a tree rooted at the base (-1)")
    return order


def morph_tree(codes: np.ndarray, limit: int) -> np.ndarray:
    """codes (F, N) int: each frame's quantized difference from the base -> parents (F,) int64 of a tree whose
    one child of the base (-1) is the frame nearest it, the others linked by a minimum spanning tree by
    squared distance between codes, using only edges whose every component fits within ±limit (a frame no
    such edge reaches links to the base, which every code is within ±limit of).

    A spanning tree of least total distance makes the targets (the differences along its edges) as small
    as the frames allow: consecutive frames of a clip link up, and the first frame of a range links to
    whichever earlier or later pose it is nearest (Prim's algorithm, O(F²)). One child of the base lets the
    base carry that frame's normals, so no normal has to turn from a mean direction."""
    codes = np.asarray(codes, dtype=np.float64)
    frame_count = codes.shape[0]
    squares = (codes ** 2).sum(axis=1)
    distances = squares[:, None] + squares[None, :] - 2.0 * codes @ codes.T  # (F, F) squared distances
    np.fill_diagonal(distances, np.inf)
    banned = np.zeros((frame_count, frame_count), dtype=bool)
    first = int(np.argmin(squares))
    while True:
        cost = np.where(banned, np.inf, distances)
        parents = np.full(frame_count, -1, dtype=np.int64)
        best = np.full(frame_count, np.inf)
        best[first] = 0.0
        linked = np.zeros(frame_count, dtype=bool)
        for _ in range(frame_count):
            frame = int(np.argmin(np.where(linked, np.inf, best)))
            if not np.isfinite(best[frame]):
                parents[frame] = -1  # out of every linked frame's reach: from the base
            linked[frame] = True
            closer = ~linked & (cost[frame] < best)
            best[closer] = cost[frame][closer]
            parents[closer] = frame
        child = np.flatnonzero(parents >= 0)
        too_far = np.abs(codes[child] - codes[parents[child]]).max(axis=1) > limit
        if not too_far.any():
            return parents
        banned[child[too_far], parents[child[too_far]]] = True
        banned[parents[child[too_far]], child[too_far]] = True


# Lengths (in int8 units) of the summed normal a morph step aims at, the first winning ties. The player
# normalises the sum, so any length shows the direction; at 63 a normal that flips within one step of the tree
# (a fold passing) is still within an int8 delta's reach (-2 · 63 >= -127), for a rounding of at most 0.8
# degrees (0.45 at 127). The shorter ones serve a step from the base's full-length (unit) normal.
_NORMAL_AIMS = (63.0, 32.0, 16.0)


def normal_step(start: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """start (V, 3) int summed normal codes, normals (V, 3) unit -> (V, 3) int deltas within ±127: of
    clip(round(length · n) - start) for the lengths of _NORMAL_AIMS, per vertex the one whose sum points
    closest to n."""
    best, best_cosine = None, None
    for length in _NORMAL_AIMS:
        delta = np.clip(np.rint(length * normals) - start, -_INT8_MAX, _INT8_MAX).astype(np.int64)
        summed = (start + delta).astype(np.float64)
        norms = np.linalg.norm(summed, axis=-1)
        cosine = np.where(norms > 0, (summed * normals).sum(-1) / np.maximum(norms, 1e-12), -1.0)
        if best is None:
            best, best_cosine = delta, cosine
            continue
        better = cosine > best_cosine + 1e-9
        best = np.where(better[:, None], delta, best)
        best_cosine = np.maximum(best_cosine, cosine)
    return best


def quantize_part(positions: np.ndarray, normals: np.ndarray) -> QuantizedPart:
    """positions, normals: (F, V, 3) float, metres and unit vectors -> QuantizedPart.

    Positions: each frame rounded onto the grid, less the mean pose's grid codes (node_transform's scale
    holds every such difference), and the targets the differences of those codes along morph_tree's edges,
    exact in integers: a frame is its own position rounded once, within half a grid step.
    Normals: a target holds what takes its parent's summed int8 code to frame k's unit normal × 127, within an
    int8 (normal_step: a normal that flips in one step is aimed at shorter), and the frame's children start
    from the sum it reached, so an error never accumulates.
    """
    positions = np.asarray(positions, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or normals.shape != positions.shape or positions.shape[1] == 0:
        raise ValueError(f"positions and normals must be (F, V, 3) alike with V > 0, got {positions.shape} and {normals.shape}")
    base = positions.mean(axis=0)
    offset, scale = node_transform(positions)
    unit = _unit(normals).astype(np.float64)

    def on_grid(values: np.ndarray) -> np.ndarray:  # values in units of node_transform's scale -> int codes on the grid
        return (np.rint(values * _INT16_MAX / POSITION_GRID) * POSITION_GRID).astype(np.int64)

    # Both within ±32767 by node_transform: the mean pose within its extent, a frame's rounded difference from it
    # within the largest difference plus a step.
    base_codes = on_grid((base - offset) / scale)
    codes = on_grid((positions - offset) / scale) - base_codes  # (F, V, 3): each frame's difference from the base
    parents = morph_tree(codes.reshape(codes.shape[0], -1), _INT16_MAX)
    parent_codes = np.where((parents >= 0)[:, None, None], codes[np.maximum(parents, 0)], 0)
    # The base's normals are those of the frame the tree starts from (its child nearest the mean pose).
    base_normal_codes = np.rint(unit[int(np.flatnonzero(parents < 0)[0])] * _INT8_MAX).astype(np.int64)
    summed = np.zeros(unit.shape, np.int64)  # each frame's base normal code plus its path's deltas
    normal_steps = np.zeros_like(summed)
    for frame in _root_first(parents):
        start = summed[parents[frame]] if parents[frame] >= 0 else base_normal_codes
        normal_steps[frame] = normal_step(start, unit[frame])
        summed[frame] = start + normal_steps[frame]

    def pad(values: np.ndarray, dtype) -> np.ndarray:
        out = np.zeros(values.shape[:-1] + (4,), dtype)
        out[..., :3] = values
        return out

    return QuantizedPart(
        positions=pad(base_codes[None], np.int16),
        position_deltas=pad(codes - parent_codes, np.int16),
        normals=pad(base_normal_codes[None], np.int8),
        normal_deltas=pad(normal_steps, np.int8),
        parents=parents,
        offset=offset,
        scale=scale,
    )


# What a morph part's `morph_parents` (its mesh's extras.crowdbake) mean.
_MORPH_MEANING = ("target k holds pose frame k minus pose frame morph_parents[k] (-1: minus the base, the mean pose); "
                  "pose frame k is the base plus every target on its path to the base, each weighing 1")
def node_transform(positions: np.ndarray) -> tuple[np.ndarray, float]:
    """(F, V, 3) metres -> the part node's (translation (3,), uniform scale) that dequantizes its mesh: the
    centre of the mean pose's box, and the larger of that pose's half extent round it and the largest
    delta of a frame from it, stretched so that the largest value, and a frame's grid code less the mean
    pose's (two roundings onto the grid, POSITION_GRID), stay inside the int16."""
    positions = np.asarray(positions, dtype=np.float64)
    base = positions.mean(axis=0)
    offset = (base.min(axis=0) + base.max(axis=0)) / 2
    deltas = positions - base
    extent = max(np.abs(base - offset).max(), np.abs(deltas).max() if deltas.size else 0.0, 1e-9)
    return offset, float(extent * _INT16_MAX / (_INT16_MAX - _INT16_MAX % POSITION_GRID - POSITION_GRID))


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
    morph_nodes, bone_tracks = [], []  # (node, its targets' parents) whose weights the animations key; (joint node, rotations, translations)
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
            # Every target's positions, then every target's normals: deflate's Huffman blocks see one kind of number at a time.
            position_targets = [blob.packed(quantized.position_deltas[k], bounds=True) for k in range(targets_per_mesh)]
            targets = [g.Attributes(POSITION=position, NORMAL=blob.packed(quantized.normal_deltas[k])) for k, position in enumerate(position_targets)]
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
        if part.skin is None and part.bones is None:
            extras["crowdbake"] = part.extras | {"morph_parents": quantized.parents.tolist(), "morph_targets": _MORPH_MEANING}
            default_weights = quantized.path_weights(np.array([0]))[0].tolist()
        else:
            default_weights = [float(frame == 0) for frame in target_frames]
        # Default weights show frame 0, for a viewer that does not play the animation.
        gltf.meshes.append(g.Mesh(name=part.name, primitives=[primitive], weights=default_weights if targets else None, extras=extras))
        if part.skin is not None:
            skin_tracks.append(_add_skin(gltf, root, scene_nodes, part.name, part.skin, len(gltf.meshes) - 1, blob, bool(targets)))
            continue
        if part.bones is None:
            # The quantization's dequantization (KHR_mesh_quantization): node scale and translation.
            gltf.nodes.append(g.Node(name=part.name, mesh=len(gltf.meshes) - 1, translation=quantized.offset.tolist(), scale=[quantized.scale] * 3))
            root.children.append(len(gltf.nodes) - 1)
            if targets:
                morph_nodes.append((len(gltf.nodes) - 1, quantized.parents))
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
            _add_animation(gltf, blob, plan, frames_per_second, morph_nodes, bone_tracks, times_of, skin_tracks)

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


def _add_animation(gltf: g.GLTF2, blob: _Blob, plan: AnimationPlan, frames_per_second: float, morph_nodes: list[tuple[int, np.ndarray]],
                   bone_tracks: list[tuple[int, np.ndarray, np.ndarray]], times_of: dict[int, int],
                   skin_tracks: list[tuple[int | None, list[int], GltfSkin]] = ()) -> None:
    """One glTF animation playing `plan`: key j at t = j / fps shows pose frame plan.keys[j], LINEAR between.
    Morph nodes: every morph target's weight (glTF keys them all together), at key j those on the path of
    pose frame keys[j] (QuantizedPart.path_weights), so each animation plays its own frames of the targets
    every animation shares. Bones: each joint's
    rotation and translation at those frames. Skins: each weighted joint's translation, rotation and scale
    at those frames, and the corrective target of a key's frame (if it has one) weighing 1."""
    if plan.key_count not in times_of:
        times = (np.arange(plan.key_count) / frames_per_second).astype(np.float32)
        times_of[plan.key_count] = blob.accessor(times, g.SCALAR, target=None, bounds=True)
    time_accessor = times_of[plan.key_count]
    animation = g.Animation(name=plan.name, samplers=[], channels=[], extras={"crowdbake": gltf_extras(plan)})
    for node, parents in morph_nodes:
        weights = path_weights(parents, plan.keys)  # (K, F): key j weighs the targets on its frame's path
        animation.samplers.append(g.AnimationSampler(input=time_accessor, output=_keyed_weights(blob, weights), interpolation="LINEAR"))
        animation.channels.append(g.AnimationChannel(sampler=len(animation.samplers) - 1, target=g.AnimationChannelTarget(node=node, path="weights")))

    def track(node: int, path: str, keyed: np.ndarray) -> None:
        """A joint's channel; rotations as normalized int16 (glTF lets a rotation sampler's output be snorm16),
        each component within 1 / 65534 of the float, at half its bytes."""
        if path == "rotation":
            output = blob.accessor(np.rint(np.clip(keyed, -1.0, 1.0) * _INT16_MAX).astype(np.int16), g.VEC4, target=None, normalized=True)
        else:
            output = blob.accessor(np.asarray(keyed, dtype=np.float32), g.VEC3, target=None)
        animation.samplers.append(g.AnimationSampler(input=time_accessor, output=output, interpolation="LINEAR"))
        animation.channels.append(g.AnimationChannel(sampler=len(animation.samplers) - 1, target=g.AnimationChannelTarget(node=node, path=path)))

    for node, rotations, translations in bone_tracks:
        track(node, "rotation", hemisphere_continuous(rotations[plan.keys]))
        track(node, "translation", translations[plan.keys])
    for mesh_node, joints, skin in skin_tracks:
        if mesh_node is not None:
            weights = skin.corrected[None, :] == plan.keys[:, None]  # (K, C) one-hot or all 0
            animation.samplers.append(g.AnimationSampler(input=time_accessor, output=_keyed_weights(blob, weights), interpolation="LINEAR"))
            animation.channels.append(g.AnimationChannel(sampler=len(animation.samplers) - 1, target=g.AnimationChannelTarget(node=mesh_node, path="weights")))
        rotations = hemisphere_continuous(skin.rotations[plan.keys])
        for joint in skin.animated:
            track(joints[joint], "translation", skin.translations[plan.keys, joint])
            track(joints[joint], "rotation", rotations[:, joint])
            track(joints[joint], "scale", skin.scales[plan.keys, joint])
    gltf.animations.append(animation)


def _keyed_weights(blob: _Blob, weights: np.ndarray) -> int:
    """The output accessor of a weights channel whose (K, F) keys are each 0 or 1: unsigned bytes, normalized
    (glTF lets a weights sampler's output be unorm8), the same values at a quarter of the float32 bytes."""
    if not np.isin(weights, (0, 1)).all():
        raise ValueError("keyed morph weights must each be 0 or 1")
    return blob.accessor(np.asarray(weights, dtype=np.uint8).reshape(-1) * np.uint8(255), g.SCALAR, target=None, normalized=True)
