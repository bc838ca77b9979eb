"""The sample humanoid's collision proxies: capsules fitted inside the body mesh (a ring of small ones at
the waist, so a pinned waistband can sit on the skin) and their positions as the skeleton moves.

The cloth simulator (crowdbake.sample.cloth_sim) collides against these, not the mesh: capsules are cheap
to test and smooth, and fitted a little inside the surface so cloth resting on them looks as if it rests on
the body.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.sample.humanoid import JOINT_INDEX, JOINT_NAMES, STANDARD, BodyMesh, Build, joint_rest_positions, part_specs


@dataclass(frozen=True)
class Capsules:
    """names (C,); joints (C,) int: the joint each capsule rides on; endpoints (C, 2, 3) rest-pose
    world positions; radii (C,) metres, fitted so the capsule encloses the body vertices it covers."""

    names: tuple[str, ...]
    joints: np.ndarray
    endpoints: np.ndarray
    radii: np.ndarray
    build: Build = STANDARD  # whose skeleton the rest endpoints are attached to


# Where a skirt's waistband sits: between the hips (widest at y = 0.96) and the narrowest waist (1.10).
# Heights here are the standard build's; another build's are these times Build.height.
WAIST_HEIGHT = 1.06
# The waist belt: capsules tangent to the torso from inside, spanning the torso's control rings at 1.03
# and 1.10 (its profile is linear between them, so a capsule tangent at both ends stays tangent in
# between). 12 keep the scallops between neighbours to ~2 mm on the 0.30 x 0.21 m waist; the pad moves
# them out by half that, so the belt stays within ~2 mm of the mesh at WAIST_HEIGHT, inside or out.
_BELT_COUNT = 12
_BELT_SPAN = (1.03, 1.10)
_BELT_PAD = 0.001


@dataclass(frozen=True)
class _CapsuleSpec:
    """One capsule: the joint it rides on, its rest endpoints (2, 3), and either a fixed radius or the body
    parts and height range (y_low, y_high) of the vertices its fitted radius must enclose."""

    name: str
    joint: str
    endpoints: np.ndarray
    parts: tuple[str, ...] = ()
    covers: tuple[float, float] = (0.0, 0.0)
    radius: float | None = None


def torso_section(height: float, build: Build = STANDARD) -> tuple[float, float, float]:
    """The torso's elliptical cross-section at a rest height (metres): (side radius, front radius, z of its centre)."""
    spec = part_specs(build)[0]
    heights = spec.controls[:, 1]  # the torso's axis rises monotonically, nearly straight up
    return (float(np.interp(height, heights, spec.radii[:, 0])), float(np.interp(height, heights, spec.radii[:, 1])),
            float(np.interp(height, heights, spec.controls[:, 2])))


def torso_radius(height: float, angles: np.ndarray, build: Build = STANDARD) -> np.ndarray:
    """Distance from the vertical axis x = z = 0 to the torso's surface along horizontal rays at `height`.

    angles (A,) radians around y, 0 pointing to -z (the back), pi/2 to +x (garments.outer_radius's
    convention) -> (A,) metres, on the smooth ellipse the mesh's rings sample (the faceted mesh lies at
    most ~1 mm inside it).
    """
    a, b, centre_z = torso_section(height, build)
    dx, dz = np.sin(angles), -np.cos(angles)
    # (t dx / a)^2 + ((t dz - centre_z) / b)^2 = 1, the far root.
    qa = (dx / a) ** 2 + (dz / b) ** 2
    qb = -2.0 * dz * centre_z / b**2
    qc = (centre_z / b) ** 2 - 1.0
    return (-qb + np.sqrt(qb * qb - 4.0 * qa * qc)) / (2.0 * qa)


def _waist_belt(build: Build = STANDARD) -> list[_CapsuleSpec]:
    """Capsules inscribed in the torso at WAIST_HEIGHT, each tangent where it touches at every height of the span.

    The largest circle inside an ellipse that touches it at a point is centred where the point's normal
    meets the major axis (the ellipse's medial axis); its radius is kept, and at each end of the span the
    capsule's end sits that radius inside the same (parametric) point of that height's section.
    """
    specs = []
    a, b, _ = torso_section(WAIST_HEIGHT * build.height, build)
    for k in range(_BELT_COUNT):
        phi = 2.0 * np.pi * k / _BELT_COUNT  # parametric angle: x = a cos(phi), z = b sin(phi)
        normal = np.array([np.cos(phi) / a, np.sin(phi) / b])
        normal /= np.linalg.norm(normal)
        # At the sides the normal runs along the major axis: the circle is the curvature circle there.
        radius = b * np.sin(phi) / normal[1] if abs(normal[1]) > 1e-9 else b * b / a
        ends = []
        for height in (y * build.height for y in _BELT_SPAN):
            a_y, b_y, centre_z = torso_section(height, build)
            normal_y = np.array([np.cos(phi) / a_y, np.sin(phi) / b_y])
            normal_y /= np.linalg.norm(normal_y)
            centre = np.array([a_y * np.cos(phi), b_y * np.sin(phi)]) - radius * normal_y
            ends.append([centre[0], height, centre[1] + centre_z])
        specs.append(_CapsuleSpec(f"waist_{k:02d}", "hips", np.array(ends), radius=float(radius) + _BELT_PAD))
    return specs


def _pelvis_spread(build: Build) -> float:
    """(a^2 - b^2) / (2 a) of the hips' section (a, b) at their widest (y = 0.96 in the standard build)."""
    a, b, _ = torso_section(0.96 * build.height, build)
    return (a * a - b * b) / (2.0 * a)


def _pelvis_reach(build: Build) -> float:
    """a - d: how far a pelvis capsule reaches out to the hips' side (a) from its axis (d = _pelvis_spread)."""
    return torso_section(0.96 * build.height, build)[0] - _pelvis_spread(build)


def _capsule_specs(build: Build = STANDARD) -> list[_CapsuleSpec]:
    """Every collision capsule of the body."""
    specs = []
    h, joints = build.height, joint_rest_positions(build)
    at = np.array([1.0, h, 1.0])  # rest heights below are the standard build's
    # Pairs of vertical capsules a distance 2d apart fit an elliptical cross-section (a, b) best when
    # d = (a^2 - b^2) / (2 a): hips (0.175, 0.12) -> d = 0.046. They end low enough (their caps reach
    # ~1.08) that at WAIST_HEIGHT they stay inside the belt. Another build's hips (a, b) move them apart by d's
    # ratio, and down by as much as their radius (a - d) grows, so their caps stay as far under the waist.
    spread = _pelvis_spread(build) / _pelvis_spread(STANDARD)
    drop = _pelvis_reach(build) - _pelvis_reach(STANDARD) * h
    for side, sign in (("l", 1.0), ("r", -1.0)):
        ends = np.array([[0.046 * sign * spread, 0.84, -0.008], [0.046 * sign * spread, 0.94, -0.008]]) * at - [0.0, drop, 0.0]
        specs.append(_CapsuleSpec(f"pelvis_{side}", "hips", ends, ("torso",), (0.76 * h, 1.02 * h)))
    specs += _waist_belt(build)
    for side, sign in (("l", 1.0), ("r", -1.0)):
        x = 0.09 * sign * build.hip_width
        leg, foot = (f"leg_{side}",), (f"foot_{side}",)
        specs += [
            _CapsuleSpec(f"thigh_upper_{side}", f"thigh_{side}", np.array([[x, 0.90, 0.0], [x, 0.72, 0.0]]) * at, leg, (0.70 * h, 0.93 * h)),
            _CapsuleSpec(f"thigh_lower_{side}", f"thigh_{side}", np.array([[x, 0.72, 0.0], [x, 0.52, 0.0]]) * at, leg, (0.50 * h, 0.74 * h)),
            _CapsuleSpec(f"shin_upper_{side}", f"shin_{side}", np.array([[x, 0.50, 0.0], [x, 0.30, 0.0]]) * at, leg, (0.28 * h, 0.52 * h)),
            _CapsuleSpec(f"shin_lower_{side}", f"shin_{side}", np.array([[x, 0.30, 0.0], [x, 0.08, 0.0]]) * at, leg, (0.04 * h, 0.32 * h)),
            _CapsuleSpec(f"foot_{side}", f"foot_{side}", np.array([[x, 0.045, -0.03], [x, 0.035, 0.13]]) * at, foot, (-1.0, 1.0)),
        ]
    for side in ("l", "r"):
        elbow = joints[JOINT_INDEX[f"forearm_{side}"]]
        wrist = joints[JOINT_INDEX[f"hand_{side}"]]
        direction = (wrist - elbow) / np.linalg.norm(wrist - elbow)
        ends = np.array([elbow, wrist + 0.11 * h * direction])
        specs.append(_CapsuleSpec(f"forearm_{side}", f"forearm_{side}", ends, (f"arm_{side}",), (0.0, elbow[1] + 0.01)))
    return specs


def fit_capsules(body: BodyMesh) -> Capsules:
    """Collision capsules: the waist belt's radii as designed, the others' enclosing the covered rest-pose vertices.

    Joint-blended vertices are covered by both neighbouring capsules' ranges; a fitted radius is the
    largest distance from the capsule's segment to a vertex it covers (the vertex's nearest capsule among
    those covering the same part, so paired capsules like the two pelvis ones share the work).
    """
    specs = _capsule_specs(body.build)
    positions = body.positions.astype(np.float64)
    radii = np.zeros(len(specs))
    for index, spec in enumerate(specs):
        if spec.radius is not None:
            radii[index] = spec.radius
            continue
        selected = np.zeros(len(positions), dtype=bool)
        for part in spec.parts:
            first, stop = body.part_ranges[part]
            selected[first:stop] = True
        low, high = spec.covers
        selected &= (positions[:, 1] >= low) & (positions[:, 1] <= high)
        # Among capsules covering the same parts and heights, a vertex belongs to its nearest one.
        peers = [k for k, other in enumerate(specs) if other.radius is None and other.parts == spec.parts and other.covers == spec.covers]
        distances = np.stack([segment_distance(positions[selected], *specs[k].endpoints) for k in peers])
        mine = distances.argmin(axis=0) == peers.index(index)
        radii[index] = float(distances[peers.index(index)][mine].max()) if mine.any() else 0.0
    return Capsules(
        names=tuple(spec.name for spec in specs),
        joints=np.array([JOINT_INDEX[spec.joint] for spec in specs], dtype=np.int64),
        endpoints=np.stack([spec.endpoints for spec in specs]),
        radii=radii,
        build=body.build,
    )


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points (N, 3) to the segment a-b -> (N,)."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def capsule_track(capsules: Capsules, world_matrices: np.ndarray) -> np.ndarray:
    """Capsule endpoints over time: world_matrices (F, J, 4, 4) joint world transforms -> (F, C, 2, 3).

    Each capsule moves rigidly with its joint: p(t) = world(t) @ world_rest^-1 @ p_rest.
    """
    rest_world = np.tile(np.eye(4), (len(JOINT_NAMES), 1, 1))
    rest_world[:, :3, 3] = joint_rest_positions(capsules.build)
    relative = world_matrices[:, capsules.joints] @ np.linalg.inv(rest_world[capsules.joints])  # (F, C, 4, 4)
    homogeneous = np.concatenate([capsules.endpoints, np.ones(capsules.endpoints.shape[:2] + (1,))], axis=-1)  # (C, 2, 4)
    moved = np.einsum("fcij,ckj->fcki", relative, homogeneous)
    return moved[..., :3]
