"""The sample humanoid standing idle, as glTF keyframe channels: a slow weight shift and a breath.

One cycle is one shift of the weight from the left leg to the right and back, with one breath: the hips
sway sideways while both feet stay planted (the thighs tilt under the hips by exactly the sway, the feet
tilt back level), the unweighted knee softens, the pelvis drops a little on that side, the chest rises
and falls, the arms swing slightly behind the sway and the head turns a few degrees. Every curve is a
smooth periodic function of the phase (the walk's rule: no corners), so the clip loops; keys are written at
every frame with the last key equal to the first, as walk.gait_channels does.
"""
from __future__ import annotations

import numpy as np

from crowdbake.formats.gltf import AnimationChannel
from crowdbake.sample.humanoid import ANKLE_HEIGHT, JOINT_INDEX, SHIN_LENGTH, STANDARD, THIGH_LENGTH, Build, joint_rest_positions
from crowdbake.sample.walk import (
    FPS,
    HIP_HEIGHT_SMOOTHING,
    MAX_CYCLE_FRAMES,
    MIN_CYCLE_FRAMES,
    X_AXIS,
    Y_AXIS,
    Z_AXIS,
    _loop,
    axis_angle,
    leg_height,
    quaternion_multiply,
    smooth_max,
)

# Frames of an idle cycle per frame of the walk's: 40 walk frames -> 80 idle frames, a 3.3 s breath
# (18 a minute, a person at rest) and weight shift.
IDLE_CADENCE = 2.0
SWAY = 0.025  # metres the hips move sideways either way
UNWEIGHTED_KNEE = np.radians(9.0)  # the relaxed leg's knee bend at the far end of the sway
PELVIS_DROP = np.radians(1.5)  # roll of the pelvis toward the relaxed leg
BREATH = np.radians(2.0)  # the chest tilts back this much at full breath
ARM_SWAY = np.radians(3.0)
ELBOW_REST = np.radians(10.0)
HEAD_TURN = np.radians(4.0)


def idle_cycle_frames(walk_cycle_frames: int) -> int:
    """Frames of the idle cycle that goes with a walk of walk_cycle_frames (within the cycle limits)."""
    return int(min(MAX_CYCLE_FRAMES, max(MIN_CYCLE_FRAMES, round(walk_cycle_frames * IDLE_CADENCE))))


def idle_channels(cycle_frames: int = idle_cycle_frames(40), fps: float = FPS, build: Build = STANDARD) -> tuple[list[AnimationChannel], float]:
    """Keyframe channels of one idle cycle in place for a build's legs and its duration (cycle_frames / fps seconds)."""
    if not MIN_CYCLE_FRAMES <= cycle_frames <= MAX_CYCLE_FRAMES:
        raise ValueError(f"cycle_frames {cycle_frames} must lie in {MIN_CYCLE_FRAMES}..{MAX_CYCLE_FRAMES}")
    keys = np.arange(cycle_frames + 1)
    times = (keys / fps).astype(np.float32)
    phase = 2.0 * np.pi * (keys % cycle_frames) / cycle_frames
    shift = np.sin(phase)  # +1: the weight on the left leg (the hips over +x)
    sway = SWAY * shift
    # The relaxed knee bends and its thigh comes forward by half as much, which keeps its foot under it.
    knees = {"l": UNWEIGHTED_KNEE * ((1.0 - shift) / 2.0) ** 2, "r": UNWEIGHTED_KNEE * ((1.0 + shift) / 2.0) ** 2}
    hips_flexion = {side: 0.5 * knee for side, knee in knees.items()}
    roll = PELVIS_DROP * shift  # +Z lifts the left side: the right (relaxed) side drops
    # Tilt the legs under the moved hips so the ankles stay where they stood: sin(tilt) = -sway / leg.
    tilt = -np.arcsin(sway / ((THIGH_LENGTH + SHIN_LENGTH) * build.height))

    stance = smooth_max(leg_height(hips_flexion["l"], knees["l"], build), leg_height(hips_flexion["r"], knees["r"], build),
                        HIP_HEIGHT_SMOOTHING)
    rest = joint_rest_positions(build)
    hips_rest = rest[JOINT_INDEX["hips"]]
    thigh_drop = hips_rest[1] - rest[JOINT_INDEX["thigh_l"]][1]
    hips_y = ANKLE_HEIGHT * build.height + stance * np.cos(tilt) + thigh_drop
    hips_translation = np.stack([sway, hips_y, np.full_like(hips_y, hips_rest[2])], axis=1)

    breath = (1.0 - np.cos(phase)) / 2.0  # 0 at rest, 1 at full breath, smooth both ways
    rotations = {
        "hips": axis_angle(Z_AXIS, roll),
        "spine": axis_angle(X_AXIS, 0.5 * BREATH * breath),
        "chest": axis_angle(X_AXIS, -1.5 * BREATH * breath),
        "head": quaternion_multiply(axis_angle(Y_AXIS, HEAD_TURN * np.sin(phase + 0.6)), axis_angle(X_AXIS, BREATH * breath)),
    }
    for side, sign in (("l", 1.0), ("r", -1.0)):
        # The thigh's world tilt is the pelvis roll plus its own; the foot undoes both to stay level.
        rotations[f"thigh_{side}"] = quaternion_multiply(axis_angle(Z_AXIS, tilt - roll), axis_angle(X_AXIS, -hips_flexion[side]))
        rotations[f"shin_{side}"] = axis_angle(X_AXIS, knees[side])
        rotations[f"foot_{side}"] = quaternion_multiply(axis_angle(X_AXIS, hips_flexion[side] - knees[side]), axis_angle(Z_AXIS, -tilt))
        # Arms lag the sway by a quarter cycle (they hang and follow), and open a little at full breath.
        rotations[f"upperarm_{side}"] = quaternion_multiply(axis_angle(Z_AXIS, sign * 0.5 * BREATH * breath),
                                                            axis_angle(X_AXIS, ARM_SWAY * np.cos(phase)))
        rotations[f"forearm_{side}"] = axis_angle(X_AXIS, -(ELBOW_REST + 0.5 * ARM_SWAY * (1.0 + np.cos(phase))))

    channels = [AnimationChannel(JOINT_INDEX["hips"], "translation", times, _loop(hips_translation))]
    for name, quaternion in rotations.items():
        channels.append(AnimationChannel(JOINT_INDEX[name], "rotation", times.copy(), _loop(quaternion)))
    return channels, cycle_frames / fps
