"""The procedural sample humanoid: skeleton, body mesh with UVs and skin weights (its collision capsules
are in crowdbake.sample.colliders).

Coordinates: metres, Y up, the character faces +Z, its left is +X, feet on y = 0 (glTF's
conventions, so the .glb needs no root transform). Rest pose: standing, arms slightly away from
the body (14 degrees) so hanging hands clear a skirt.

The body is a mannequin of smooth closed "tubes" (torso, head with neck, arms with hands, legs,
feet): each tube sweeps an elliptical cross-section along a polyline and closes at both ends on a
pole vertex. Each part owns one rectangle of the shared texture (BODY_UV_RECTS); u runs around the
tube starting at its back (so seams face away from the viewer), v runs along the axis. The garment
uses GARMENT_UV_RECT of the same texture.

Skin weights blend at most two joints per vertex, piecewise linear along each tube's axis.
Collision capsules are attached to joints. Most have radii fitted to the rest-pose mesh so they
enclose the body surface they stand in for; at the waist, where a skirt's waistband sits on the
skin, a belt of capsules follows the torso's surface within a few millimetres instead (test_sample
checks both).

Builds (BUILDS): the standard figure (what every module constant below describes) and others with other
proportions: height scales every rest height and limb length, shoulder and hip width the shoulders' and
hips' spacing and the torso's width there, girth every cross-section of trunk and limbs. A build is a
pure function of its numbers: joint_rest_positions(build), part_specs(build), build_body(build).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from crowdbake.formats.gltf import Character
from crowdbake.geometry import vertex_normals

# Shared texture layout in glTF UV convention (u right, v down), as (u0, v0, u1, v1).
# The body uses the top three quarters, the simulated garment the bottom quarter.
BODY_UV_RECTS: dict[str, tuple[float, float, float, float]] = {
    "torso": (0.0, 0.0, 0.5, 0.4),
    "head": (0.5, 0.0, 0.75, 0.2),
    "arm_l": (0.5, 0.2, 0.75, 0.4),
    "arm_r": (0.75, 0.2, 1.0, 0.4),
    "leg_l": (0.0, 0.4, 0.25, 0.75),
    "leg_r": (0.25, 0.4, 0.5, 0.75),
    "foot_l": (0.5, 0.4, 0.625, 0.55),
    "foot_r": (0.625, 0.4, 0.75, 0.55),
}
GARMENT_UV_RECT = (0.0, 0.75, 1.0, 1.0)
# UVs stay this fraction of a rectangle away from its border so that filtering and mip levels
# sample the part's own texels, not its neighbour's.
UV_INSET = 0.01

ARM_ABDUCTION_DEGREES = 14.0
_ARM_DIRECTION = np.array([np.sin(np.radians(ARM_ABDUCTION_DEGREES)), -np.cos(np.radians(ARM_ABDUCTION_DEGREES)), 0.0])
_UPPER_ARM, _FOREARM, _HAND = 0.27, 0.25, 0.17


@dataclass(frozen=True)
class Build:
    """Body proportions as factors of the standard figure's (1.0: as built). See the module docstring."""

    name: str
    height: float = 1.0
    shoulder_width: float = 1.0
    hip_width: float = 1.0
    girth: float = 1.0


BUILDS: dict[str, Build] = {
    "standard": Build("standard"),
    # Stockier: 3 % shorter, shoulders 8 % and hips 12 % wider, 15 % more girth (trunk and limbs). More (hips
    # 18 %, girth 22 %) pressed the thighs into the loose skirt's cut over the hips: 48 % edge stretch there.
    "heavy": Build("heavy", height=0.97, shoulder_width=1.08, hip_width=1.12, girth=1.15),
    # Lankier: 5 % taller, narrower shoulders and hips, 15 % less girth.
    "slim": Build("slim", height=1.05, shoulder_width=0.93, hip_width=0.90, girth=0.85),
}
BUILD_NAMES = tuple(BUILDS)
STANDARD = BUILDS["standard"]
# The torso's width follows the hip width up to the hips' top and the shoulder width from the chest up
# (heights in the standard figure, metres), blending linearly between.
_HIPS_TOP_Y, _CHEST_Y = 1.0, 1.3


def _joint_table(build: Build = STANDARD) -> list[tuple[str, str | None, np.ndarray]]:
    """(name, parent name, rest world position) for every joint, parents first."""
    h = build.height
    shoulder = np.array([0.175 * build.shoulder_width, 1.42 * h, 0.0])
    table: list[tuple[str, str | None, np.ndarray]] = [
        ("hips", None, np.array([0.0, 0.95 * h, 0.0])),
        ("spine", "hips", np.array([0.0, 1.10 * h, 0.0])),
        ("chest", "spine", np.array([0.0, 1.28 * h, 0.0])),
        ("neck", "chest", np.array([0.0, 1.46 * h, 0.0])),
        ("head", "neck", np.array([0.0, 1.56 * h, 0.0])),
    ]
    for side, sign in (("l", 1.0), ("r", -1.0)):
        mirror = np.array([sign, 1.0, 1.0])
        direction = _ARM_DIRECTION * mirror
        upper = shoulder * mirror
        table += [
            (f"upperarm_{side}", "chest", upper),
            (f"forearm_{side}", f"upperarm_{side}", upper + (_UPPER_ARM * h) * direction),
            (f"hand_{side}", f"forearm_{side}", upper + (_UPPER_ARM * h + _FOREARM * h) * direction),
        ]
    for side, sign in (("l", 1.0), ("r", -1.0)):
        x = 0.09 * sign * build.hip_width
        table += [
            (f"thigh_{side}", "hips", np.array([x, 0.92 * h, 0.0])),
            (f"shin_{side}", f"thigh_{side}", np.array([x, 0.50 * h, 0.0])),
            (f"foot_{side}", f"shin_{side}", np.array([x, 0.085 * h, 0.0])),
        ]
    return table


@lru_cache(maxsize=None)
def _joint_rest_positions(build: Build) -> np.ndarray:
    positions = np.array([position for _, _, position in _joint_table(build)], dtype=np.float64)
    positions.flags.writeable = False
    return positions


def joint_rest_positions(build: Build = STANDARD) -> np.ndarray:
    """(J, 3) float64 rest world positions of the joints of a build (read-only)."""
    return _joint_rest_positions(build)


JOINT_TABLE = _joint_table()
JOINT_NAMES = [name for name, _, _ in JOINT_TABLE]
JOINT_INDEX = {name: index for index, name in enumerate(JOINT_NAMES)}
JOINT_PARENTS = np.array([-1 if parent is None else JOINT_INDEX[parent] for _, parent, _ in JOINT_TABLE], dtype=np.int64)
JOINT_REST_POSITIONS = np.array([position for _, _, position in JOINT_TABLE], dtype=np.float64)
THIGH_LENGTH = 0.42  # hip to knee
SHIN_LENGTH = 0.415  # knee to ankle
ANKLE_HEIGHT = 0.085  # all three of the standard build: times Build.height for another


@dataclass(frozen=True)
class PartSpec:
    """One closed tube. controls: (K, 3) polyline, ends are poles; radii: (K, 2) (side, front) in metres,
    0 at both ends; reference: the 'front' direction of the cross-sections; stations: (control index,
    joint name) pairs, weights blend linearly between consecutive stations."""

    name: str
    controls: np.ndarray
    radii: np.ndarray
    reference: tuple[float, float, float]
    rings: int
    segments: int
    stations: tuple[tuple[float, str], ...]


def _part_specs(build: Build = STANDARD) -> list[PartSpec]:
    h, g = build.height, build.girth
    joints = joint_rest_positions(build)
    torso = [  # y, side radius, front radius, z offset
        (0.770, 0.000, 0.000, 0.000),
        (0.790, 0.090, 0.070, 0.000),
        (0.830, 0.145, 0.105, -0.005),
        (0.900, 0.170, 0.120, -0.010),
        (0.960, 0.175, 0.120, -0.010),
        (1.030, 0.155, 0.108, 0.000),
        (1.100, 0.140, 0.100, 0.000),
        (1.200, 0.150, 0.108, 0.005),
        (1.300, 0.165, 0.118, 0.010),
        (1.400, 0.172, 0.108, 0.000),
        (1.450, 0.148, 0.094, 0.000),
        (1.490, 0.080, 0.060, 0.000),
        (1.505, 0.000, 0.000, 0.000),
    ]
    head = [
        (1.420, 0.000, 0.000, 0.000),
        (1.440, 0.045, 0.045, 0.000),
        (1.530, 0.047, 0.050, 0.000),
        (1.560, 0.068, 0.078, 0.010),
        (1.600, 0.083, 0.097, 0.015),
        (1.645, 0.086, 0.100, 0.015),
        (1.690, 0.077, 0.091, 0.010),
        (1.725, 0.055, 0.065, 0.005),
        (1.748, 0.025, 0.030, 0.000),
        (1.755, 0.000, 0.000, 0.000),
    ]
    width = lambda y: np.interp(y, [_HIPS_TOP_Y, _CHEST_Y], [build.hip_width, build.shoulder_width])  # noqa: E731
    specs = [
        PartSpec(
            "torso",
            np.array([[0.0, y * h, z] for y, _, _, z in torso]),
            np.array([[a * width(y) * g, b * g] for y, a, b, _ in torso]),
            (0.0, 0.0, 1.0),
            rings=24,
            segments=28,
            stations=((0, "hips"), (4.3, "hips"), (6.4, "spine"), (7.4, "spine"), (8.2, "chest"), (10.5, "chest"), (12, "neck")),
        ),
        PartSpec(
            "head",
            np.array([[0.0, y * h, z] for y, _, _, z in head]),
            np.array([[a, b] for _, a, b, _ in head]),
            (0.0, 0.0, 1.0),
            rings=20,
            segments=24,
            stations=((0, "neck"), (2.0, "neck"), (2.7, "head"), (9, "head")),
        ),
    ]
    for side, sign in (("l", 1.0), ("r", -1.0)):
        mirror = np.array([sign, 1.0, 1.0])
        shoulder = joints[JOINT_INDEX[f"upperarm_{side}"]]
        elbow = joints[JOINT_INDEX[f"forearm_{side}"]]
        wrist = joints[JOINT_INDEX[f"hand_{side}"]]
        d = _ARM_DIRECTION * mirror * h  # offsets along the arm scale with the height
        arm = [
            (shoulder + np.array([-0.045, 0.01, 0.0]) * mirror, 0.0, 0.0),
            (shoulder + np.array([-0.03, 0.005, 0.0]) * mirror, 0.045, 0.048),
            (shoulder, 0.050, 0.050),
            (shoulder + 0.12 * d, 0.042, 0.045),
            (elbow, 0.034, 0.036),
            (elbow + 0.12 * d, 0.033, 0.035),
            (wrist - 0.01 * d, 0.024, 0.028),
            (wrist + 0.05 * d, 0.016, 0.042),
            (wrist + 0.12 * d, 0.013, 0.036),
            (wrist + _HAND * d, 0.0, 0.0),
        ]
        specs.append(
            PartSpec(
                f"arm_{side}",
                np.array([p for p, _, _ in arm]),
                np.array([[a * g, b * g] for _, a, b in arm]),
                (0.0, 0.0, 1.0),
                rings=20,
                segments=14,
                stations=((0, "chest"), (1.6, f"upperarm_{side}"), (3.6, f"upperarm_{side}"), (4.4, f"forearm_{side}"),
                          (5.7, f"forearm_{side}"), (6.4, f"hand_{side}"), (9, f"hand_{side}")),
            )
        )
    for side, sign in (("l", 1.0), ("r", -1.0)):
        x = 0.09 * sign * build.hip_width
        leg = [
            (1.000, 0.000, 0.000),
            (0.980, 0.070, 0.075),
            (0.920, 0.085, 0.088),
            (0.750, 0.075, 0.078),
            (0.580, 0.058, 0.060),
            (0.500, 0.050, 0.052),
            (0.400, 0.052, 0.056),
            (0.220, 0.040, 0.042),
            (0.100, 0.033, 0.035),
            (0.060, 0.030, 0.030),
            (0.045, 0.000, 0.000),
        ]
        specs.append(
            PartSpec(
                f"leg_{side}",
                np.array([[x, y * h, 0.0] for y, _, _ in leg]),
                np.array([[a * g, b * g] for _, a, b in leg]),
                (0.0, 0.0, 1.0),
                rings=24,
                segments=18,
                stations=((0, "hips"), (2.0, f"thigh_{side}"), (4.6, f"thigh_{side}"), (5.4, f"shin_{side}"),
                          (8.5, f"shin_{side}"), (10, f"foot_{side}")),
            )
        )
        foot = [
            ((x, 0.050, -0.060), 0.000, 0.000),
            ((x, 0.050, -0.045), 0.035, 0.035),
            ((x, 0.055, 0.000), 0.045, 0.050),
            ((x, 0.040, 0.080), 0.048, 0.035),
            ((x, 0.030, 0.150), 0.040, 0.025),
            ((x, 0.028, 0.180), 0.000, 0.000),
        ]
        specs.append(
            PartSpec(
                f"foot_{side}",
                np.array([(px, py * h, pz) for (px, py, pz), _, _ in foot]),
                np.array([[a, b] for _, a, b in foot]),
                (0.0, 1.0, 0.0),
                rings=10,
                segments=14,
                stations=((0, f"foot_{side}"), (5, f"foot_{side}")),
            )
        )
    return specs


PART_SPECS = _part_specs()


@lru_cache(maxsize=None)
def part_specs(build: Build = STANDARD) -> tuple[PartSpec, ...]:
    """The closed tubes of a build's body (PART_SPECS for the standard one)."""
    return tuple(_part_specs(build))


@dataclass(frozen=True)
class TubeMesh:
    """positions (V, 3) float64; uvs (V, 2); faces (T, 3) int64 (outward winding); axis_param (V,) in [0, 1]
    (arc-length fraction along the axis); around (V,) in [0, 1] (0 = back, 0.5 = front)."""

    positions: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray
    axis_param: np.ndarray
    around: np.ndarray


def _arc_lengths(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def tube_mesh(controls: np.ndarray, radii: np.ndarray, reference, rings: int, segments: int, uv_rect) -> TubeMesh:
    """Sweep an ellipse (radii (K, 2): side, front) along controls (K, 3); poles at both ends.

    rings: interior rings (evenly spaced in arc length); segments: vertices per ring (+1 duplicate
    at the seam so UVs wrap). The seam sits at the back (-reference side).
    """
    controls = np.asarray(controls, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    lengths = _arc_lengths(controls)
    total = lengths[-1]
    s = np.linspace(0.0, 1.0, rings + 2)[1:-1]  # interior rings; poles at s = 0 and 1
    centres = np.stack([np.interp(s * total, lengths, controls[:, k]) for k in range(3)], axis=1)
    ring_radii = np.stack([np.interp(s * total, lengths, radii[:, k]) for k in range(2)], axis=1)
    ahead = np.stack([np.interp(np.minimum(s + 0.01, 1.0) * total, lengths, controls[:, k]) for k in range(3)], axis=1)
    behind = np.stack([np.interp(np.maximum(s - 0.01, 0.0) * total, lengths, controls[:, k]) for k in range(3)], axis=1)
    tangent = ahead - behind
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    side = np.cross(tangent, np.asarray(reference, dtype=np.float64))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    front = np.cross(side, tangent)
    angle = 2 * np.pi * np.arange(segments + 1) / segments
    ring_positions = (
        centres[:, None, :]
        + ring_radii[:, 0, None, None] * np.sin(angle)[None, :, None] * side[:, None, :]
        - ring_radii[:, 1, None, None] * np.cos(angle)[None, :, None] * front[:, None, :]
    )
    u0, v0, u1, v1 = uv_rect
    pad_u, pad_v = UV_INSET * (u1 - u0) * 4, UV_INSET * (v1 - v0) * 4
    u_of = lambda t: u0 + pad_u + (u1 - u0 - 2 * pad_u) * t  # noqa: E731
    v_of = lambda t: v0 + pad_v + (v1 - v0 - 2 * pad_v) * t  # noqa: E731
    around = np.tile(np.arange(segments + 1) / segments, rings)
    axis_param = np.repeat(s, segments + 1)
    positions = np.concatenate([controls[:1], ring_positions.reshape(-1, 3), controls[-1:]])
    uvs = np.concatenate(
        [[[u_of(0.5), v_of(0.0)]], np.stack([u_of(around), v_of(axis_param)], axis=1), [[u_of(0.5), v_of(1.0)]]]
    )
    axis_param = np.concatenate([[0.0], axis_param, [1.0]])
    around = np.concatenate([[0.5], around, [0.5]])

    width = segments + 1
    ring_index = lambda r, j: 1 + r * width + j  # noqa: E731
    faces = []
    j = np.arange(segments)
    for r in range(rings - 1):
        a, b = ring_index(r, j), ring_index(r, j + 1)
        c, d = ring_index(r + 1, j), ring_index(r + 1, j + 1)
        faces += [np.stack([a, c, b], axis=1), np.stack([b, c, d], axis=1)]
    last_pole = len(positions) - 1
    faces.append(np.stack([np.zeros(segments, np.int64), ring_index(0, j), ring_index(0, j + 1)], axis=1))
    faces.append(np.stack([np.full(segments, last_pole), ring_index(rings - 1, j + 1), ring_index(rings - 1, j)], axis=1))
    faces = np.concatenate(faces).astype(np.int64)
    if signed_volume(positions, faces) < 0:
        faces = faces[:, ::-1].copy()
    return TubeMesh(positions, uvs, faces, axis_param, around)


def signed_volume(positions: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (positive when faces wind counter-clockwise seen from outside)."""
    p = np.asarray(positions, dtype=np.float64)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def _station_weights(spec: PartSpec, axis_param: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two-joint weights blending linearly between consecutive stations along the axis."""
    lengths = _arc_lengths(spec.controls)
    control_s = lengths / lengths[-1]
    station_s = np.interp([index for index, _ in spec.stations], np.arange(len(control_s)), control_s)
    station_joint = np.array([JOINT_INDEX[name] for _, name in spec.stations])
    k = np.clip(np.searchsorted(station_s, axis_param, side="right") - 1, 0, len(station_s) - 2)
    span = np.maximum(station_s[k + 1] - station_s[k], 1e-12)
    alpha = np.clip((axis_param - station_s[k]) / span, 0.0, 1.0)
    joints = np.zeros((len(axis_param), 4), dtype=np.uint16)
    weights = np.zeros((len(axis_param), 4), dtype=np.float32)
    joints[:, 0], joints[:, 1] = station_joint[k], station_joint[k + 1]
    weights[:, 0], weights[:, 1] = 1.0 - alpha, alpha
    same = joints[:, 0] == joints[:, 1]
    weights[same, 0], weights[same, 1], joints[same, 1] = 1.0, 0.0, 0
    return joints, weights


@dataclass(frozen=True)
class BodyMesh:
    """The merged body. part_ranges maps a part name to its (first, stop) vertex range."""

    positions: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (V, 3) float32
    uvs: np.ndarray  # (V, 2) float32
    faces: np.ndarray  # (T, 3) uint32
    joints: np.ndarray  # (V, 4) uint16
    weights: np.ndarray  # (V, 4) float32
    axis_param: np.ndarray  # (V,) float32
    around: np.ndarray  # (V,) float32
    part_ranges: dict[str, tuple[int, int]]
    part_faces: dict[str, tuple[int, int]]
    build: Build = STANDARD


def build_body(build: Build = STANDARD) -> BodyMesh:
    """The whole body mesh of a build in the rest pose (deterministic)."""
    arrays: dict[str, list[np.ndarray]] = {k: [] for k in ("positions", "uvs", "faces", "joints", "weights", "axis", "around")}
    part_ranges: dict[str, tuple[int, int]] = {}
    part_faces: dict[str, tuple[int, int]] = {}
    base = face_base = 0
    for spec in part_specs(build):
        tube = tube_mesh(spec.controls, spec.radii, spec.reference, spec.rings, spec.segments, BODY_UV_RECTS[spec.name])
        joints, weights = _station_weights(spec, tube.axis_param)
        arrays["positions"].append(tube.positions)
        arrays["uvs"].append(tube.uvs)
        arrays["faces"].append(tube.faces + base)
        arrays["joints"].append(joints)
        arrays["weights"].append(weights)
        arrays["axis"].append(tube.axis_param)
        arrays["around"].append(tube.around)
        part_ranges[spec.name] = (base, base + len(tube.positions))
        part_faces[spec.name] = (face_base, face_base + len(tube.faces))
        base += len(tube.positions)
        face_base += len(tube.faces)
    positions = np.concatenate(arrays["positions"])
    faces = np.concatenate(arrays["faces"])
    # Smooth across UV seams: compute normals on the welded surface (seam duplicates share a
    # position), then hand each copy the shared normal, so shading shows no seam.
    _, weld, inverse = np.unique(np.round(positions, 9), axis=0, return_index=True, return_inverse=True)
    normals = vertex_normals(positions[weld], inverse.reshape(-1)[faces]).astype(np.float32)[inverse.reshape(-1)]
    return BodyMesh(
        positions=positions.astype(np.float32),
        normals=normals,
        uvs=np.concatenate(arrays["uvs"]).astype(np.float32),
        faces=faces.astype(np.uint32),
        joints=np.concatenate(arrays["joints"]),
        weights=np.concatenate(arrays["weights"]),
        axis_param=np.concatenate(arrays["axis"]).astype(np.float32),
        around=np.concatenate(arrays["around"]).astype(np.float32),
        part_ranges=part_ranges,
        part_faces=part_faces,
        build=build,
    )


def rest_skeleton(build: Build = STANDARD) -> dict[str, np.ndarray]:
    """Local rest TRS and inverse bind matrices of the skeleton (rest rotations are identity)."""
    joint_count = len(JOINT_NAMES)
    rest = joint_rest_positions(build)
    translations = rest.copy()
    has_parent = JOINT_PARENTS >= 0
    translations[has_parent] -= rest[JOINT_PARENTS[has_parent]]
    inverse_bind = np.tile(np.eye(4), (joint_count, 1, 1))
    inverse_bind[:, :3, 3] = -rest
    return {
        "translations": translations,
        "rotations": np.tile([0.0, 0.0, 0.0, 1.0], (joint_count, 1)),
        "scales": np.ones((joint_count, 3)),
        "inverse_bind": inverse_bind.astype(np.float32),
    }


def build_character(body: BodyMesh, channels: list, duration: float, texture: np.ndarray | None) -> Character:
    """The sample humanoid as a Character (what write_character turns into character.glb)."""
    skeleton = rest_skeleton(body.build)
    return Character(
        positions=body.positions,
        normals=body.normals,
        uvs=body.uvs,
        faces=body.faces,
        joints=body.joints,
        weights=body.weights,
        joint_names=list(JOINT_NAMES),
        joint_parents=JOINT_PARENTS.copy(),
        joint_parent_transforms=np.tile(np.eye(4), (len(JOINT_NAMES), 1, 1)),
        inverse_bind_matrices=skeleton["inverse_bind"],
        rest_translations=skeleton["translations"],
        rest_rotations=skeleton["rotations"],
        rest_scales=skeleton["scales"],
        channels=channels,
        animation_duration=duration,
        texture=texture,
        name="crowdbake_sample_humanoid",
    )


def part_height(name: str, axis_param: np.ndarray) -> np.ndarray:
    """Rest-pose height y (metres) of the axis of part `name` at arc-length fractions axis_param (any shape)."""
    spec = next((spec for spec in PART_SPECS if spec.name == name), None)
    if spec is None:
        raise ValueError(f"unknown body part {name!r}; parts are {[s.name for s in PART_SPECS]}")
    lengths = _arc_lengths(spec.controls)
    return np.interp(np.asarray(axis_param) * lengths[-1], lengths, spec.controls[:, 1])


def rect_to_part(uv_rect: tuple[float, float, float, float], u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert tube_mesh's UV mapping: texture (u, v) inside uv_rect -> (around, axis_param), clipped to [0, 1]."""
    u0, v0, u1, v1 = uv_rect
    pad_u, pad_v = UV_INSET * (u1 - u0) * 4, UV_INSET * (v1 - v0) * 4
    around = (np.asarray(u) - u0 - pad_u) / (u1 - u0 - 2 * pad_u)
    axis_param = (np.asarray(v) - v0 - pad_v) / (v1 - v0 - 2 * pad_v)
    return np.clip(around, 0.0, 1.0), np.clip(axis_param, 0.0, 1.0)


def torso_skin_weights(heights: np.ndarray, build: Build = STANDARD) -> tuple[np.ndarray, np.ndarray]:
    """Skin weights of the torso surface at rest heights (N,) metres -> joints (N, 4), weights (N, 4).

    A garment pinned at the waist follows the body with these, so its waistband moves exactly like the
    torso under it.
    """
    spec = part_specs(build)[0]
    lengths = _arc_lengths(spec.controls)
    axis_param = np.interp(np.asarray(heights, dtype=np.float64), spec.controls[:, 1], lengths / lengths[-1])
    return _station_weights(spec, axis_param)
