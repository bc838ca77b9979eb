"""The export's animations: one per clip and one per transition of a bundle (SPEC.md "Playback"), each as the
pose frames it shows at its keys, shared by the glTF (morph weights, bone tracks), the VAT shaders and
export.json.

Key j of an animation sits at t = j / fps and shows one pose frame:

- a clip of n frames loops: keys 0..n show pose frames first, first+1, ..., first+n-1, first (the last
  key is the first again, so a looping player has no seam);
- a transition of n frames plays once and carries both its joins: key 0 shows the from-clip's
  `leave_frame`, keys 1..n the transition's frames, key n+1 the to-clip's `arrive_frame`. Start it when
  the from-clip is at leave_frame / fps; when it ends, (n + 1) / fps later, play the to-clip from
  arrive_frame / fps. Every step between keys is then one frame of the simulation.

A v1 bundle has one clip, `cycle`, over all its frames: the export's one animation, as ever.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from crowdbake.formats.ranges import Clip, Ranges


@dataclass(frozen=True)
class AnimationPlan:
    """One clip or transition as an animation. keys: (K,) int pose frames, key j at t = j / fps."""

    name: str
    loop: bool
    keys: np.ndarray
    first_frame: int  # the range's first pose frame
    frames: int  # the range's frame count
    before_frame: int  # pose frame shown before the range: the clip's last, the transition's leave pose
    after_frame: int  # pose frame shown after the range: the clip's first, the transition's arrive pose
    from_clip: str | None = None
    to_clip: str | None = None
    leave_frame: int | None = None  # loop frames of from_clip and to_clip (transitions only)
    arrive_frame: int | None = None

    @property
    def key_count(self) -> int:
        return int(self.keys.shape[0])


def transition_name(from_clip: str, to_clip: str) -> str:
    """"FROM -> TO", the name the bake's reports give a transition (texture_memory.json)."""
    return f"{from_clip} -> {to_clip}"


def animation_plans(ranges: Ranges) -> list[AnimationPlan]:
    """Every clip (in order) then every transition (in order) of `ranges` as an AnimationPlan. Names are
    unique: a name already taken (a second transition between the same clips) gets " (2)", " (3)", ..."""
    plans, taken = [], set()

    def unique(name: str) -> str:
        candidate, k = name, 1
        while candidate in taken:
            k += 1
            candidate = f"{name} ({k})"
        taken.add(candidate)
        return candidate

    for clip in ranges.clips:
        frames = clip.first_frame + np.arange(clip.frames + 1) % clip.frames
        plans.append(AnimationPlan(unique(clip.name), True, frames.astype(np.int64), clip.first_frame, clip.frames,
                                   clip.first_frame + clip.frames - 1, clip.first_frame))
    for transition in ranges.transitions:
        source: Clip = ranges.clips[transition.from_clip]
        target: Clip = ranges.clips[transition.to_clip]
        before = source.first_frame + transition.leave_frame
        after = target.first_frame + transition.arrive_frame
        keys = np.concatenate([[before], transition.first_frame + np.arange(transition.frames), [after]]).astype(np.int64)
        plans.append(AnimationPlan(unique(transition_name(source.name, target.name)), False, keys, transition.first_frame, transition.frames,
                                   before, after, source.name, target.name, transition.leave_frame, transition.arrive_frame))
    return plans


def vat_range_uniforms(plan: AnimationPlan) -> dict[str, int]:
    """The values the VAT shaders (shaders/vat.glsl and the engine setups) take to play `plan`: its pose
    frames (first, count), 1 to loop or 0 to play once, and the pose frames before and after it."""
    return {"first_frame": plan.first_frame, "frames": plan.frames, "loop": int(plan.loop), "before_frame": plan.before_frame,
            "after_frame": plan.after_frame}


def sidecar_animations(plans: list[AnimationPlan], frames_per_second: float) -> list[dict[str, Any]]:
    """export.json's `animations`: per plan its glTF animation (name, index), keys, seconds, loop or once,
    the VAT range uniforms, and for a transition its clips and loop frames."""
    entries = []
    for index, plan in enumerate(plans):
        entry: dict[str, Any] = {
            "name": plan.name, "gltf_animation": index, "kind": "clip" if plan.loop else "transition",
            "playback": "loop" if plan.loop else "once", "keys": plan.key_count,
            "seconds": (plan.key_count - 1) / frames_per_second, "vat": vat_range_uniforms(plan),
        }
        if not plan.loop:
            entry |= {"from": plan.from_clip, "to": plan.to_clip, "leave_frame": plan.leave_frame, "arrive_frame": plan.arrive_frame}
        entries.append(entry)
    return entries


def gltf_extras(plan: AnimationPlan) -> dict[str, Any]:
    """A glTF animation's `extras.crowdbake`: how to play it (module docstring)."""
    extras: dict[str, Any] = {"kind": "clip" if plan.loop else "transition", "playback": "loop" if plan.loop else "once",
                              "first_frame": plan.first_frame, "frames": plan.frames}
    if not plan.loop:
        extras |= {"from": plan.from_clip, "to": plan.to_clip, "leave_frame": plan.leave_frame, "arrive_frame": plan.arrive_frame,
                   "starts": "at the from clip's leave_frame pose: start it when that clip is at leave_frame / fps",
                   "ends": "at the to clip's arrive_frame pose: play that clip on from arrive_frame / fps"}
    return extras


def vat_shader_twin(frame: np.ndarray, uniforms: dict[str, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The numpy twin of the VAT shaders (for tests): what they compute from an animation's frame (t · fps, any real) and vat_range_uniforms:
    (pose frame f0, pose frame f1, weight of f1), each shaped like `frame`; the shader blends the two.

    A loop wraps round its frames. A once-played range (a transition) clamps to its keys 0..frames+1,
    key 0 being before_frame and key frames+1 after_frame, as the glTF animation keys it."""
    frame = np.asarray(frame, dtype=np.float64)
    first, count = uniforms["first_frame"], uniforms["frames"]
    if uniforms["loop"]:
        x = np.mod(frame, count)
        j0 = np.minimum(np.floor(x).astype(np.int64), count - 1)
        j1 = j0 + 1
        return first + j0, np.where(j1 < count, first + j1, uniforms["after_frame"]), x - j0
    x = np.clip(frame, 0.0, count + 1.0)
    j0 = np.minimum(np.floor(x).astype(np.int64), count)
    j1 = j0 + 1

    def pose(j: np.ndarray) -> np.ndarray:
        return np.where(j <= 0, uniforms["before_frame"], np.where(j > count, uniforms["after_frame"], first + j - 1))

    return pose(j0), pose(j1), x - j0
