"""A procedural walk-in-place cycle for the sample humanoid, as glTF keyframe channels.

The gait is written as functions of the cycle phase phi in [0, 2 pi): hip flexion is a sine, the
knee bends during swing, the ankle keeps the foot roughly level, the pelvis turns and sways, the
spine counter-rotates and the arms swing against the legs. The hips' height is chosen each frame so
that the lower foot touches the ground (which is what makes the body bob twice per cycle). Every curve
is smooth in the phase (no max(), no fractional powers of a clipped cosine): a corner in a joint curve
is a velocity kink, an acceleration spike every cloth vertex near it feels and a loop search sees. Like
CesiumMan, the character walks in place: the stance foot slides back as on a treadmill.

Phase 0 of the cycle is double support (both knees almost straight), so a garment starting from
rest around the frame-0 pose is not cut by a bent leg.

Keys are written at every frame, k / fps for k = 0..cycle_frames, with key cycle_frames equal to
key 0 bit for bit, so the animation lasts exactly cycle_frames / fps seconds and loops.
"""
from __future__ import annotations

import numpy as np

from crowdbake.formats.gltf import AnimationChannel
from crowdbake.sample.humanoid import ANKLE_HEIGHT, JOINT_INDEX, JOINT_REST_POSITIONS, SHIN_LENGTH, THIGH_LENGTH

FPS = 24.0
DEFAULT_CYCLE_FRAMES = 40
MIN_CYCLE_FRAMES, MAX_CYCLE_FRAMES = 8, 240

HIP_FLEXION = np.radians(21.0)  # peak thigh swing either way
KNEE_STANCE = np.radians(4.0)
KNEE_SWING = np.radians(52.0)  # extra flexion at mid-swing
ARM_SWING = np.radians(17.0)
ELBOW_BEND = np.radians(12.0)
PELVIS_YAW = np.radians(5.0)
PELVIS_ROLL = np.radians(2.5)
SPINE_YAW = np.radians(3.5)
PELVIS_SWAY = 0.015  # metres toward the stance leg
PHASE_OFFSET = np.pi / 2  # frame 0 = double support, left leg forward
# Knee flexion follows ((1 + cos)/2)^KNEE_SHARPNESS of the swing phase: a smooth bump that is 1 at mid-swing
# and under 7 % of it anywhere in stance (a near-straight stance knee, as in a real walk).
KNEE_SHARPNESS = 4.0
# The hips ride on the longer leg: max(a, b) smoothed as (a + b)/2 + sqrt(((a - b)/2)^2 + w^2), so the
# hips' height has no corner when the legs swap (a walk's double support). w in metres: larger is
# smoother; the smoothed max lies between max(a, b) and max(a, b) + w, equal to the max once the legs
# differ by a few w, so both feet lift at most w off the floor around the swap, and only then.
HIP_HEIGHT_SMOOTHING = 0.01


def axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) for rotations of angle (F,) radians about a unit axis (3,) -> (F, 4)."""
    angle = np.asarray(angle, dtype=np.float64)
    half = angle / 2.0
    return np.concatenate([np.sin(half)[:, None] * np.asarray(axis, dtype=np.float64)[None], np.cos(half)[:, None]], axis=1)


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (F, 4) quaternions (x, y, z, w): rotate by b, then by a."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=1,
    )


X_AXIS, Y_AXIS, Z_AXIS = np.eye(3)


def gait_angles(phase: np.ndarray) -> dict[str, np.ndarray]:
    """Joint angles (radians) of the gait at phases (F,). Positive hip flexion = thigh forward."""
    hip_l = HIP_FLEXION * np.sin(phase)
    hip_r = -hip_l
    # Swing is when the thigh moves forward (d hip / d phase > 0), peaking at mid-swing.
    knee_l = KNEE_STANCE + KNEE_SWING * ((1.0 + np.cos(phase)) / 2.0) ** KNEE_SHARPNESS
    knee_r = KNEE_STANCE + KNEE_SWING * ((1.0 - np.cos(phase)) / 2.0) ** KNEE_SHARPNESS
    return {
        "hip_l": hip_l,
        "hip_r": hip_r,
        "knee_l": knee_l,
        "knee_r": knee_r,
        "arm_l": -ARM_SWING * np.sin(phase),  # against the same-side leg
        "arm_r": ARM_SWING * np.sin(phase),
        # Extra bend when the arm swings forward: a smooth bump, not max(-sin, 0) and its corners.
        "elbow_l": ELBOW_BEND * (1.0 + ((1.0 - np.sin(phase)) / 2.0) ** 2),
        "elbow_r": ELBOW_BEND * (1.0 + ((1.0 + np.sin(phase)) / 2.0) ** 2),
    }


def leg_height(hip: np.ndarray, knee: np.ndarray) -> np.ndarray:
    """Vertical hip-to-ankle extent of a leg with thigh angle `hip` and knee bend `knee` (radians)."""
    return THIGH_LENGTH * np.cos(hip) + SHIN_LENGTH * np.cos(hip - knee)


def smooth_max(a: np.ndarray, b: np.ndarray, width: float) -> np.ndarray:
    """A max(a, b) without a corner: (a + b)/2 + sqrt(((a - b)/2)^2 + width^2), in [max, max + width]."""
    half_difference = 0.5 * (np.asarray(a) - np.asarray(b))
    return 0.5 * (np.asarray(a) + np.asarray(b)) + np.sqrt(half_difference**2 + width**2)


def walk_channels(cycle_frames: int = DEFAULT_CYCLE_FRAMES, fps: float = FPS) -> tuple[list[AnimationChannel], float]:
    """Keyframe channels of one walk-in-place cycle and its duration (cycle_frames / fps seconds)."""
    if not MIN_CYCLE_FRAMES <= cycle_frames <= MAX_CYCLE_FRAMES:
        raise ValueError(f"cycle_frames {cycle_frames} must lie in {MIN_CYCLE_FRAMES}..{MAX_CYCLE_FRAMES}")
    keys = np.arange(cycle_frames + 1)
    times = (keys / fps).astype(np.float32)
    phase = 2.0 * np.pi * (keys % cycle_frames) / cycle_frames + PHASE_OFFSET  # key l == key 0 exactly
    angles = gait_angles(phase)

    # Hips: low enough that the longer (stance) leg's ankle sits at ANKLE_HEIGHT.
    stance = smooth_max(
        leg_height(angles["hip_l"], angles["knee_l"]), leg_height(angles["hip_r"], angles["knee_r"]), HIP_HEIGHT_SMOOTHING
    )
    hips_rest = JOINT_REST_POSITIONS[JOINT_INDEX["hips"]]
    thigh_drop = hips_rest[1] - JOINT_REST_POSITIONS[JOINT_INDEX["thigh_l"]][1]
    hips_y = ANKLE_HEIGHT + stance + thigh_drop
    # Weight over the stance leg: left stance when the left thigh moves back (cos(phase) < 0).
    hips_x = -PELVIS_SWAY * np.cos(phase)
    hips_translation = np.stack([hips_x, hips_y, np.full_like(hips_y, hips_rest[2])], axis=1)
    pelvis = quaternion_multiply(axis_angle(Y_AXIS, -PELVIS_YAW * np.sin(phase)), axis_angle(Z_AXIS, PELVIS_ROLL * np.cos(phase)))

    rotations = {
        "hips": pelvis,
        "spine": axis_angle(Y_AXIS, SPINE_YAW * np.sin(phase)),
        "chest": axis_angle(Y_AXIS, SPINE_YAW * np.sin(phase)),
        "head": axis_angle(Y_AXIS, -0.5 * SPINE_YAW * np.sin(phase)),
    }
    for side in ("l", "r"):
        # A positive rotation about +X swings a downward limb backwards, so flexion is negative.
        rotations[f"thigh_{side}"] = axis_angle(X_AXIS, -angles[f"hip_{side}"])
        rotations[f"shin_{side}"] = axis_angle(X_AXIS, angles[f"knee_{side}"])
        # Keep the sole roughly level, with a little push-off.
        rotations[f"foot_{side}"] = axis_angle(X_AXIS, 0.8 * (angles[f"hip_{side}"] - angles[f"knee_{side}"]))
        rotations[f"upperarm_{side}"] = axis_angle(X_AXIS, -angles[f"arm_{side}"])
        rotations[f"forearm_{side}"] = axis_angle(X_AXIS, -angles[f"elbow_{side}"])

    channels = [AnimationChannel(JOINT_INDEX["hips"], "translation", times, _loop(hips_translation))]
    for name, quaternion in rotations.items():
        channels.append(AnimationChannel(JOINT_INDEX[name], "rotation", times.copy(), _loop(quaternion)))
    return channels, cycle_frames / fps


def _loop(values: np.ndarray) -> np.ndarray:
    """float32 keys whose last key is the first, bit for bit (the animation loops seamlessly)."""
    values = np.asarray(values, dtype=np.float32).copy()
    values[-1] = values[0]
    return values
