"""Morph targets: each primitive's POSITION (and NORMAL) displacements, the mesh's default weights, and
the animation's "weights" channels, kept so posing can apply them (crowdbake.bake.skinning).

A mesh's targets are named by `mesh.extras.targetNames` where the file gives them. What cannot be
applied is refused naming the mesh and target, never dropped: a target whose accessor count is not
its primitive's vertex count, primitives of one mesh with different target counts, targets on a
Draco-compressed primitive (Draco may reorder vertices, so the uncompressed displacements would land
on the wrong ones), and a weights channel whose output is not keys x targets. Target accessors are read
like every other accessor (sparse blocks included), inside the document's decode budget.
"""
from __future__ import annotations

import logging

import numpy as np

from crowdbake.formats.gltf.animation import sampler_keys
from crowdbake.formats.gltf.document import _Document
from crowdbake.formats.gltf.model import MorphTarget, WeightsChannel

logger = logging.getLogger(__name__)


def target_names(doc: _Document, mesh_index: int, count: int) -> list[str]:
    """The names of meshes[mesh_index]'s `count` targets: extras.targetNames where it lists that many
    strings, else "target<k>"."""
    extras = doc.item("meshes", mesh_index).extras
    names = extras.get("targetNames") if isinstance(extras, dict) else None
    if isinstance(names, list) and len(names) == count and all(isinstance(n, str) for n in names):
        return list(names)
    return [f"target{k}" for k in range(count)]


def _attribute(target, name: str):
    return target.get(name) if isinstance(target, dict) else getattr(target, name, None)


def primitive_targets(doc: _Document, primitive, mesh_index: int, where: str, count: int,
                      draco: bool) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """(position deltas (count, 3) float32, normal deltas (count, 3) float32 or None) per target of one
    primitive with `count` vertices. Raises ValueError naming the mesh and target it cannot apply."""
    targets = primitive.targets or []
    if not targets:
        return []
    names = target_names(doc, mesh_index, len(targets))
    if draco:
        raise ValueError(f"{where}: morph target {names[0]!r} of meshes[{mesh_index}] is on a Draco-compressed primitive, "
                         "whose decoded vertex order the target does not follow; export the character without Draco")
    out = []
    for k, target in enumerate(targets):
        deltas = []
        for name in ("POSITION", "NORMAL"):
            index = _attribute(target, name)
            if index is None:
                deltas.append(None)
                continue
            values = doc.accessor(index)
            if values.shape != (count, 3) or values.dtype.kind != "f":
                raise ValueError(f"{where}: morph target {names[k]!r} of meshes[{mesh_index}]: {name} is {values.shape} "
                                 f"{values.dtype}, expected ({count}, 3) floats (one per vertex of the primitive)")
            deltas.append(values.astype(np.float32))
        positions = deltas[0] if deltas[0] is not None else np.zeros((count, 3), np.float32)
        out.append((positions, deltas[1]))
    return out


def mesh_targets(doc: _Document, mesh_index: int, start: int,
                 parts: list[list[tuple[np.ndarray, np.ndarray | None]]], where: str) -> list[MorphTarget]:
    """The MorphTargets of one mesh from its primitives' targets (in primitive order, vertices from
    `start`). Every primitive must carry the same number of targets (glTF requires it)."""
    counts = {len(part) for part in parts}
    if counts == {0}:
        return []
    if len(counts) != 1:
        raise ValueError(f"{where}: the primitives of meshes[{mesh_index}] carry different numbers of morph targets "
                         f"({sorted(counts)}); glTF requires the same targets on every primitive of a mesh")
    names = target_names(doc, mesh_index, counts.pop())
    targets = []
    for k, name in enumerate(names):
        positions = np.concatenate([part[k][0] for part in parts])
        has_normals = any(part[k][1] is not None for part in parts)
        normals = (np.concatenate([part[k][1] if part[k][1] is not None else np.zeros_like(part[k][0]) for part in parts])
                   if has_normals else None)
        targets.append(MorphTarget(name, mesh_index, start, positions, normals))
    return targets


def default_weights(doc: _Document, mesh_index: int, count: int, where: str) -> np.ndarray:
    """meshes[mesh_index].weights as (count,) float32; zeros when the file gives none."""
    weights = doc.item("meshes", mesh_index).weights
    if weights is None:
        return np.zeros(count, np.float32)
    weights = np.asarray(weights, dtype=np.float64).reshape(-1)
    if weights.shape != (count,) or not np.isfinite(weights).all():
        raise ValueError(f"{where}: meshes[{mesh_index}].weights has {weights.size} values for {count} morph targets")
    return weights.astype(np.float32)


def read_weight_channels(doc: _Document, animation_index: int | None, node_targets: dict[int, tuple[int, int]]) -> list[WeightsChannel]:
    """The "weights" channels of the chosen animation on nodes whose mesh's targets were kept.

    node_targets: node index -> (index of its mesh's first target in Character.morph_targets, count)."""
    if animation_index is None:
        return []
    animation = doc.item("animations", animation_index)
    samplers = animation.samplers or []
    channels: list[WeightsChannel] = []
    for number, channel in enumerate(animation.channels or []):
        target = channel.target
        if target is None or target.path != "weights":
            continue
        where = f"{doc.where}: animations[{animation_index}].channels[{number}]"
        if target.node not in node_targets:
            logger.debug("%s: weights of node %s, whose mesh is not part of the character", where, target.node)
            continue
        first, count = node_targets[target.node]
        sampler = _sampler(samplers, channel.sampler, where)
        interpolation, times = sampler_keys(doc, sampler, where)
        values = doc.accessor(sampler.output)
        keys = 3 * len(times) if interpolation == "CUBICSPLINE" else len(times)
        if values.shape[1] != 1 or values.size != keys * count or values.dtype.kind != "f":
            raise ValueError(f"{where}: weights output has {values.size} values, expected {keys} keys x {count} morph targets "
                             f"of node {target.node}")
        values = values.astype(np.float32).reshape(keys, count)
        if interpolation == "CUBICSPLINE":
            values = values.reshape(len(times), 3, count)
        channels.append(WeightsChannel(first, count, times.astype(np.float32), values, interpolation))
    return channels


def _sampler(samplers: list, index, where: str):
    if not isinstance(index, int) or not 0 <= index < len(samplers):
        raise ValueError(f"{where}: sampler {index} does not exist")
    return samplers[index]
