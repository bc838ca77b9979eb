"""The animation: which one to read (by index or name) and its channels that target the skin's joints.

LINEAR, STEP and CUBICSPLINE samplers are kept as the file stores them (crowdbake.bake.skinning
evaluates them); channels on nodes above the skeleton are not followed (a warning says so).
"""
from __future__ import annotations

import logging

import numpy as np

from crowdbake.formats.gltf.document import _Document
from crowdbake.formats.gltf.model import AnimationChannel

logger = logging.getLogger(__name__)

INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
PATH_WIDTHS = {"translation": 3, "rotation": 4, "scale": 3}


def choose_animation(doc: _Document, animation: int | str) -> int | None:
    """The index of the chosen animation (by index or name); None when the file has none."""
    animations = doc.gltf.animations or []
    names = [a.name or f"animation{k}" for k, a in enumerate(animations)]
    if not animations:
        if isinstance(animation, str) or animation != 0:
            raise ValueError(f"{doc.where}: animation {animation!r} was asked for but the file has no animation")
        return None
    if isinstance(animation, str):
        if animation not in names:
            raise ValueError(f"{doc.where}: no animation named {animation!r}; the file has {', '.join(repr(n) for n in names)}")
        return names.index(animation)
    if not isinstance(animation, int) or not 0 <= animation < len(animations):
        raise ValueError(f"{doc.where}: animation {animation} does not exist; the file has {len(animations)}: {', '.join(repr(n) for n in names)}")
    if len(animations) > 1:
        logger.info("%s: %d animations (%s); using %r (choose another by name or index)", doc.where, len(animations),
                    ", ".join(repr(n) for n in names), names[animation])
    return animation


def sampler_keys(doc: _Document, sampler, where: str) -> tuple[str, np.ndarray]:
    """(interpolation, (K,) keyframe times in seconds) of an animation sampler, checked: a known
    interpolation, float scalar times, strictly increasing."""
    interpolation = sampler.interpolation or "LINEAR"
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"{where}: unknown interpolation {interpolation!r}")
    times = doc.accessor(sampler.input)
    if times.shape[1] != 1 or times.dtype.kind != "f":
        raise ValueError(f"{where}: sampler input must be float scalars")
    times = times[:, 0]
    if len(times) > 1 and not (np.diff(times) > 0).all():
        raise ValueError(f"{where}: keyframe times must increase strictly")
    return interpolation, times


def read_animation(doc: _Document, animation_index: int | None, node_to_joint: dict[int, int], joint_ancestors: set[int]):
    if animation_index is None:
        return [], 0.0
    animation = doc.item("animations", animation_index)
    samplers = animation.samplers or []
    channels: list[AnimationChannel] = []
    duration = 0.0
    for number, channel in enumerate(animation.channels or []):
        where = f"{doc.where}: animations[{animation_index}].channels[{number}]"
        target = channel.target
        path, node = (target.path, target.node) if target is not None else (None, None)
        sampler_index = channel.sampler
        if not isinstance(sampler_index, int) or not 0 <= sampler_index < len(samplers):
            raise ValueError(f"{where}: sampler {sampler_index} does not exist")
        sampler = samplers[sampler_index]
        interpolation, times = sampler_keys(doc, sampler, where)
        duration = max(duration, float(times[-1]))
        if node not in node_to_joint:
            if node in joint_ancestors and path in PATH_WIDTHS:
                logger.warning("%s: animates node %s above the skeleton; only its rest transform is used", where, node)
            continue
        if path not in PATH_WIDTHS:
            logger.debug("%s: ignoring %r channel", where, path)
            continue
        values = doc.accessor(sampler.output).astype(np.float32)
        width = PATH_WIDTHS[path]
        keys = 3 * len(times) if interpolation == "CUBICSPLINE" else len(times)
        if values.shape != (keys, width):
            raise ValueError(f"{where}: {path} output is {values.shape}, expected ({keys}, {width})")
        if interpolation == "CUBICSPLINE":
            values = values.reshape(len(times), 3, width)
        channels.append(AnimationChannel(node_to_joint[node], path, times.astype(np.float32), values, interpolation))
    return channels, duration
