"""The sample humanoid's gaits in place, walk and run, as glTF keyframe channels.

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

The run (RUN) is the same machinery with a faster cadence (RUN_CADENCE: fewer frames a cycle), a longer
stride, more knee, arm and elbow bend and a forward lean; both feet stay on the ground (no flight phase:
the hips ride on the longer leg as in the walk), which is what a skirt's simulation needs to be driven.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.formats.gltf import AnimationChannel
from crowdbake.sample.humanoid import ANKLE_HEIGHT, JOINT_INDEX, SHIN_LENGTH, STANDARD, THIGH_LENGTH, Build, joint_rest_positions

FPS = 24.0
DEFAULT_CYCLE_FRAMES = 40
MIN_CYCLE_FRAMES, MAX_CYCLE_FRAMES = 8, 240

PHASE_OFFSET = np.pi / 2  # frame 0 = double support, left leg forward


@dataclass(frozen=True)
class Gait:
    """The amplitudes of a gait (radians unless stated). Positive hip flexion = thigh forward."""

    hip_flexion: float  # peak thigh swing either way
    knee_stance: float
    knee_swing: float  # extra flexion at mid-swing
    arm_swing: float
    elbow_bend: float  # the elbow bends between 1x and 2x this
    pelvis_yaw: float
    pelvis_roll: float
    spine_yaw: float
    pelvis_sway: float  # metres toward the stance leg
    knee_sharpness: float  # the swing bump's exponent (below)
    lean: float = 0.0  # the spine pitched forward


WALK = Gait(
    hip_flexion=np.radians(21.0), knee_stance=np.radians(4.0), knee_swing=np.radians(52.0), arm_swing=np.radians(17.0),
    elbow_bend=np.radians(12.0), pelvis_yaw=np.radians(5.0), pelvis_roll=np.radians(2.5), spine_yaw=np.radians(3.5),
    pelvis_sway=0.015, knee_sharpness=4.0,
)
# A jog in place: a longer stride (32 degrees a side), the swing knee bent to 85 degrees and a broader
# swing bump (sharpness 2), arms bent 45-90 degrees swinging twice as far, the trunk leaning 6 degrees.
RUN = Gait(
    hip_flexion=np.radians(26.0), knee_stance=np.radians(8.0), knee_swing=np.radians(65.0), arm_swing=np.radians(30.0),
    elbow_bend=np.radians(45.0), pelvis_yaw=np.radians(7.0), pelvis_roll=np.radians(3.0), spine_yaw=np.radians(5.0),
    pelvis_sway=0.01, knee_sharpness=2.0, lean=np.radians(6.0),
)
# Frames of a run cycle per frame of the walk's: a faster cadence (40 walk frames -> 24 run frames, 1.0 s a
# stride at 24 fps, 120 steps a minute).
RUN_CADENCE = 0.7


def run_cycle_frames(walk_cycle_frames: int) -> int:
    """Frames of the run cycle that goes with a walk of walk_cycle_frames (at least MIN_CYCLE_FRAMES)."""
    return max(MIN_CYCLE_FRAMES, int(round(walk_cycle_frames * RUN_CADENCE)))


# Knee flexion follows ((1 + cos)/2)^knee_sharpness of the swing phase: a smooth bump that is 1 at mid-swing
# and under 7 % of it anywhere in stance (a near-straight stance knee, as in a real walk).
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


def gait_angles(phase: np.ndarray, gait: Gait = WALK) -> dict[str, np.ndarray]:
    """Joint angles (radians) of the gait at phases (F,). Positive hip flexion = thigh forward."""
    hip_l = gait.hip_flexion * np.sin(phase)
    hip_r = -hip_l
    # Swing is when the thigh moves forward (d hip / d phase > 0), peaking at mid-swing.
    knee_l = gait.knee_stance + gait.knee_swing * ((1.0 + np.cos(phase)) / 2.0) ** gait.knee_sharpness
    knee_r = gait.knee_stance + gait.knee_swing * ((1.0 - np.cos(phase)) / 2.0) ** gait.knee_sharpness
    return {
        "hip_l": hip_l,
        "hip_r": hip_r,
        "knee_l": knee_l,
        "knee_r": knee_r,
        "arm_l": -gait.arm_swing * np.sin(phase),  # against the same-side leg
        "arm_r": gait.arm_swing * np.sin(phase),
        # Extra bend when the arm swings forward: a smooth bump, not max(-sin, 0) and its corners.
        "elbow_l": gait.elbow_bend * (1.0 + ((1.0 - np.sin(phase)) / 2.0) ** 2),
        "elbow_r": gait.elbow_bend * (1.0 + ((1.0 + np.sin(phase)) / 2.0) ** 2),
    }


def leg_height(hip: np.ndarray, knee: np.ndarray, build: Build = STANDARD) -> np.ndarray:
    """Vertical hip-to-ankle extent of a leg with thigh angle `hip` and knee bend `knee` (radians)."""
    thigh, shin = THIGH_LENGTH * build.height, SHIN_LENGTH * build.height
    return thigh * np.cos(hip) + shin * np.cos(hip - knee)


def smooth_max(a: np.ndarray, b: np.ndarray, width: float) -> np.ndarray:
    """A max(a, b) without a corner: (a + b)/2 + sqrt(((a - b)/2)^2 + width^2), in [max, max + width]."""
    half_difference = 0.5 * (np.asarray(a) - np.asarray(b))
    return 0.5 * (np.asarray(a) + np.asarray(b)) + np.sqrt(half_difference**2 + width**2)


def walk_channels(cycle_frames: int = DEFAULT_CYCLE_FRAMES, fps: float = FPS, build: Build = STANDARD) -> tuple[list[AnimationChannel], float]:
    """Keyframe channels of one walk-in-place cycle and its duration (cycle_frames / fps seconds)."""
    return gait_channels(WALK, cycle_frames, fps, build)


def run_channels(cycle_frames: int = run_cycle_frames(DEFAULT_CYCLE_FRAMES), fps: float = FPS,
                 build: Build = STANDARD) -> tuple[list[AnimationChannel], float]:
    """Keyframe channels of one run-in-place cycle and its duration (cycle_frames / fps seconds)."""
    return gait_channels(RUN, cycle_frames, fps, build)


def gait_channels(gait: Gait, cycle_frames: int, fps: float = FPS, build: Build = STANDARD) -> tuple[list[AnimationChannel], float]:
    """Keyframe channels of one cycle of `gait` in place for a build's legs, and its duration (cycle_frames / fps seconds)."""
    if not MIN_CYCLE_FRAMES <= cycle_frames <= MAX_CYCLE_FRAMES:
        raise ValueError(f"cycle_frames {cycle_frames} must lie in {MIN_CYCLE_FRAMES}..{MAX_CYCLE_FRAMES}")
    keys = np.arange(cycle_frames + 1)
    times = (keys / fps).astype(np.float32)
    phase = 2.0 * np.pi * (keys % cycle_frames) / cycle_frames + PHASE_OFFSET  # key l == key 0 exactly
    angles = gait_angles(phase, gait)

    # Hips: low enough that the longer (stance) leg's ankle sits at ANKLE_HEIGHT.
    stance = smooth_max(
        leg_height(angles["hip_l"], angles["knee_l"], build), leg_height(angles["hip_r"], angles["knee_r"], build), HIP_HEIGHT_SMOOTHING
    )
    rest = joint_rest_positions(build)
    hips_rest = rest[JOINT_INDEX["hips"]]
    thigh_drop = hips_rest[1] - rest[JOINT_INDEX["thigh_l"]][1]
    hips_y = ANKLE_HEIGHT * build.height + stance + thigh_drop
    # Weight over the stance leg: left stance when the left thigh moves back (cos(phase) < 0).
    hips_x = -gait.pelvis_sway * np.cos(phase)
    hips_translation = np.stack([hips_x, hips_y, np.full_like(hips_y, hips_rest[2])], axis=1)
    pelvis = quaternion_multiply(axis_angle(Y_AXIS, -gait.pelvis_yaw * np.sin(phase)), axis_angle(Z_AXIS, gait.pelvis_roll * np.cos(phase)))

    rotations = {
        "hips": pelvis,
        "spine": axis_angle(Y_AXIS, gait.spine_yaw * np.sin(phase)),
        "chest": axis_angle(Y_AXIS, gait.spine_yaw * np.sin(phase)),
        "head": axis_angle(Y_AXIS, -0.5 * gait.spine_yaw * np.sin(phase)),
    }
    if gait.lean:
        # Lean from the waist (+X tilts the spine's top forward); the head looks ahead again.
        forward = np.full_like(phase, gait.lean)
        rotations["spine"] = quaternion_multiply(axis_angle(X_AXIS, forward), rotations["spine"])
        rotations["head"] = quaternion_multiply(axis_angle(X_AXIS, -forward), rotations["head"])
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
