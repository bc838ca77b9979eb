"""Physical evidence of which clip drove a cloth: the cloth collided with that body, so under the right
clip it stays outside the body, and it moves with it. Pure numpy (and scipy's k-d tree), no I/O.

For one candidate clip, with the body posed by that clip at the cache's frames:

* penetration: the share of cloth vertices inside the body, averaged over the frames measured. Inside is
  crowdbake.bake.penetration's test (behind the nearest body vertex's tangent plane by more than its
  tolerance) and one more condition: the offset along that vertex's normal carries most of the distance
  to it (ALONG_NORMAL). A point far beyond the edge of an open or coarse mesh (the rim of a robot's
  bell-shaped torso) is "behind" its nearest vertex without being in the body.
* follow: how the cloth's motion follows the body's. For each cloth vertex, the correlation over the
  frame pairs (t, t + 1) between its displacement and its nearest body vertex's (nearest at t):
  sum(dc . db) / sqrt(sum |dc|^2 sum |db|^2), in -1..1, then the mean over the cloth. A cape pinned to
  the torso moves with the torso under the right clip; under another its nearest body point goes
  elsewhere, and the correlation falls to about 0 or below.

Measured, 16 frame pairs, 1000 cloth vertices (penetration, follow; services/tests/test_clip_evidence.py):
    long_skirt, CesiumMan's walk                   0.1%  0.31   the walk half a cycle on   1.1%  -0.07
    robot_clips cape, its Walking frames, Walking  1.3%  0.44   Running                    1.9%  -0.28
    robot_clips cape, its Running frames, Running  1.1%  0.55   Walking                    1.4%  -0.26
    robot_clips cape, its Idle frames, Idle        1.5%  0.66   Walking                    2.7%   0.16
    the sample's cloth, its walk                   0.0%  0.59   the body grown by 35%     22.4%   0.57

    evidence_pairs(frame_count) -> (P, 2) cache frames (t, t + 1) spread over the cache
    measure_clip_evidence(cloth, body, body_faces, body_normals, pairs) -> ClipEvidence
    conclusive({clip: ClipEvidence}) -> bool           the cloth clearly follows one of the clips
    rejections({clip: ClipEvidence}) -> {clip: why}  the clips the evidence clearly rules out
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crowdbake.bake.penetration import BodyFrames, PenetrationSettings

# Frame pairs measured, spread evenly over the cache: a mean over its cycles, at a cost that stays
# small with a dozen candidate clips (the robot's 12 that fit: about 2 s in all, most of it skinning).
EVIDENCE_PAIRS = 16
# Cloth vertices measured, evenly strided: the figures of 1000 and of every vertex of the caches above
# differ in the second decimal.
EVIDENCE_VERTICES = 1000
# A cloth point counts as inside only when the offset along the nearest body normal is at least this
# share of its distance to that vertex: the robot's cape over its Walking frames reads 19% "inside"
# Walking with the tangent-plane test alone (17% Running: no evidence either way), 1.3% with this.
ALONG_NORMAL = 0.7
# The evidence counts only when the cloth clearly follows some clip: a cache played across several clips
# (robot_clips' whole cache: Idle, Walking, Running) follows none of them over its length, best 0.17.
MIN_FOLLOW = 0.2
# The cloth does not follow a clip whose follow is this far below the best clip's: the right clip
# scores 0.3-0.7 on the caches above, a wrong one -0.3 to 0.16.
FOLLOW_MARGIN = 0.2
# The cloth is inside a clip's body when its share inside exceeds PENETRATION_FACTOR times the least
# of the clips it follows plus PENETRATION_MARGIN: a simulator leaves a few vertices inside (the skirt's
# legs poke through: 0.1%; the robot's cape 1.1-1.5%), a wrong clip puts more there (1.1-3%, 22% grown).
PENETRATION_FACTOR = 2.0
PENETRATION_MARGIN = 0.005


@dataclass(frozen=True)
class ClipEvidence:
    """penetration: mean share (0..1) of the cloth inside the body at the pairs' first frames; follow:
    mean correlation (-1..1) of the cloth's displacements with its nearest body vertex's; pairs: how many
    frame pairs were measured."""

    penetration: float
    follow: float
    pairs: int

    def text(self) -> str:
        return f"{100 * self.penetration:.1f}% inside, follow {self.follow:.2f}"


def evidence_pairs(frame_count: int, count: int = EVIDENCE_PAIRS) -> np.ndarray:
    """(P, 2) int64 cache frames (t, t + 1), P <= count, the t spread evenly over 0..frame_count-2."""
    if frame_count < 2:
        raise ValueError(f"the evidence needs at least 2 frames, got {frame_count}")
    starts = np.unique(np.linspace(0, frame_count - 2, min(count, frame_count - 1)).round().astype(np.int64))
    return np.stack([starts, starts + 1], axis=1)


def _vertex_normals(body: np.ndarray, faces: np.ndarray) -> np.ndarray:
    from crowdbake.geometry import vertex_normals

    return vertex_normals(body, np.asarray(faces, np.int64).reshape(-1, 3))


def measure_clip_evidence(cloth: np.ndarray, body: np.ndarray, body_faces: np.ndarray,
                          body_normals: np.ndarray | None = None, pairs: np.ndarray | None = None,
                          vertices: int = EVIDENCE_VERTICES) -> ClipEvidence:
    """The evidence for one clip.

    cloth (F, V, 3) and body (F, Vb, 3): Y-up metres, frame k of each at the same cache time (the body
    posed by the clip); body_faces (T, 3) int; body_normals (F, Vb, 3) unit outward normals (the skinned
    ones; derived from the faces when None); pairs (P, 2) int rows (a, b) into F: the frames whose
    displacements are compared (default every (k, k + 1)). Penetration is measured at each pair's first
    frame: pass a sample (evidence_pairs), not a whole cache. `vertices`: the cloth vertices measured at most."""
    cloth = np.asarray(cloth, np.float64)
    body = np.asarray(body, np.float64)
    if cloth.ndim != 3 or cloth.shape[2] != 3 or body.ndim != 3 or body.shape[2] != 3:
        raise ValueError(f"cloth and body must be (F, N, 3), got {cloth.shape} and {body.shape}")
    if len(cloth) != len(body) or len(cloth) < 2:
        raise ValueError(f"cloth and body need the same number (>= 2) of frames, got {len(cloth)} and {len(body)}")
    pairs = np.stack([np.arange(len(cloth) - 1), np.arange(1, len(cloth))], axis=1) if pairs is None else np.asarray(pairs, np.int64)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or len(pairs) == 0 or pairs.min() < 0 or pairs.max() >= len(cloth):
        raise ValueError(f"pairs must be (P, 2) frame indices below {len(cloth)}, got shape {pairs.shape}")
    normals = _vertex_normals(body, body_faces) if body_normals is None else np.asarray(body_normals, np.float64)
    cloth = cloth[:, np.unique(np.linspace(0, cloth.shape[1] - 1, min(vertices, cloth.shape[1])).round().astype(np.int64))]

    frames = BodyFrames(body, normals)
    settings = PenetrationSettings.for_body(body)
    a, b = pairs[:, 0], pairs[:, 1]
    inside = np.empty(len(pairs))
    near = np.empty((len(pairs), cloth.shape[1]), np.int64)
    for row, k in enumerate(a):
        offset, distance, near[row] = frames.signed_offsets(int(k), cloth[k])
        inside[row] = np.mean((offset < -settings.tolerance) & (distance < settings.max_depth)
                              & (-offset >= ALONG_NORMAL * distance))

    moved_cloth = cloth[b] - cloth[a]
    moved_body = np.take_along_axis(body[b], near[..., None], axis=1) - np.take_along_axis(body[a], near[..., None], axis=1)
    product = np.einsum("pvc,pvc->v", moved_cloth, moved_body)
    scale = np.sqrt(np.einsum("pvc,pvc->v", moved_cloth, moved_cloth) * np.einsum("pvc,pvc->v", moved_body, moved_body))
    # A vertex or body point that never moves says nothing either way: it counts as 0.
    follow = np.divide(product, scale, out=np.zeros_like(product), where=scale > 0)
    return ClipEvidence(float(inside.mean()), float(follow.mean()), len(pairs))


def conclusive(evidence: dict[int, ClipEvidence]) -> bool:
    """Whether the evidence can judge the clips: the cloth follows one of them by MIN_FOLLOW at least."""
    return bool(evidence) and max(e.follow for e in evidence.values()) >= MIN_FOLLOW


def rejections(evidence: dict[int, ClipEvidence]) -> dict[int, str]:
    """The clips the evidence rules out, each with why ("does not follow", "inside the body").

    A clip is judged against the best of the others: its follow against the highest (FOLLOW_MARGIN), its
    penetration against the least among the clips the cloth follows (PENETRATION_FACTOR, _MARGIN): a clip
    that moves the body away from the cloth has none inside and must not set the bar for the rest.
    Nothing is ruled out when the evidence is not conclusive."""
    if not conclusive(evidence):
        return {}
    best_follow = max(e.follow for e in evidence.values())
    why = {k: "does not follow" for k, e in evidence.items() if e.follow < best_follow - FOLLOW_MARGIN}
    followed = [e.penetration for k, e in evidence.items() if k not in why]
    bar = PENETRATION_FACTOR * min(followed) + PENETRATION_MARGIN
    for k, e in evidence.items():
        if e.penetration > bar:
            why[k] = "inside the body" if k not in why else "inside the body, does not follow"
    return why
