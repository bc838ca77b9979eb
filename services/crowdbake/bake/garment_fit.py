"""Does the garment fit this character over the whole cache? Pure numpy (and scipy's k-d tree), no I/O.

crowdbake.bake.placement checks the cache's first frame: its up axis, its units, that it sits on the
character at all. A garment simulated on another character passes that check when the two are of a
size (CesiumMan's long skirt on RiggedFigure: both about 1.45 m, both walking in place), yet the
cloth does not follow this body: its legs swing where the other body's did not, so the skirt hangs
off them and bakes crumpled and off-centre. What gives it away is how much of the cloth is far from
the body over the cache: a garment simulated on this body and this animation stays near it.

The measure: the body is posed at each checked frame's time, its surface sampled (SURFACE_SAMPLES
points, area-weighted, so a body of a few large triangles counts as densely as a fine one), and each
cloth point's distance to the nearest sample taken. `far_fraction` is the share of cloth points
farther than FAR_FROM_BODY of the character's height, averaged over the checked frames.

Measured (services/benchmarks/bench_garment_fit.py), mean far_fraction over the cache:
    CesiumMan + long_skirt (its own simulation, loose ankle-length skirt)   0.07
    procedural sample, loose / tight garment                               0.02 / 0.00
    RobotExpressive + cape, Idle clip (its own simulation, other clips too) 0.01
    RiggedFigure + CesiumMan's long_skirt (the wrong character)            0.16
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A cloth point farther than this share of the character's height from its body surface hangs off it.
# At 0.15 a long skirt's hem on its own walker is rarely that far (7% of its points), on another
# walker often (16%); at 0.1 the two are 21% and 38%, a narrower ratio (table above).
FAR_FROM_BODY = 0.15
# Refuse above this mean share of far cloth points: between CesiumMan's own long skirt (0.07, the
# loosest matching garment we have) and the same skirt on RiggedFigure (0.16).
MAX_FAR_FRACTION = 0.12
# Body surface points per checked frame: the nearest one is within about 1 cm on a 1.8 m body.
SURFACE_SAMPLES = 20000
# Frames checked, spread evenly over the cache: the measure is a mean over the cycles the cache holds;
# 32 frames give the pairs of bench_garment_fit.py the figures of 100 within 0.01.
MAX_FRAMES_CHECKED = 32
# Fixed seed: the same inputs get the same verdict.
SAMPLE_SEED = 0


@dataclass(frozen=True)
class GarmentFit:
    """far_fraction: mean share of cloth points far from the body; worst_frame and worst_far_fraction:
    the checked frame with the largest share; height: the character's height (m) the distances are
    relative to; frames_checked: how many frames were measured."""

    far_fraction: float
    worst_frame: int
    worst_far_fraction: float
    height: float
    frames_checked: int

    @property
    def ok(self) -> bool:
        return self.far_fraction <= MAX_FAR_FRACTION


def checked_frames(frame_count: int) -> np.ndarray:
    """At most MAX_FRAMES_CHECKED frame indices (int64) spread evenly over 0..frame_count-1."""
    if frame_count < 1:
        raise ValueError(f"frame_count must be at least 1, got {frame_count}")
    return np.unique(np.linspace(0, frame_count - 1, min(frame_count, MAX_FRAMES_CHECKED)).round().astype(np.int64))


def surface_samples(positions: np.ndarray, faces: np.ndarray, count: int = SURFACE_SAMPLES,
                    seed: int = SAMPLE_SEED) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted points on a mesh, as (count, 3) vertex indices int64 and (count, 3) barycentric
    weights float64, so the same points follow the mesh in any pose: points = einsum(weights, pose[indices])."""
    positions = np.asarray(positions, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    corners = positions[faces]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    if len(faces) == 0 or area.sum() <= 0:
        raise ValueError("the body mesh has no area to sample")
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(faces), count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return faces[chosen], np.stack([1 - u - v, u, v], axis=1)


def measure_garment_fit(cloth_frames: np.ndarray, body_frames: np.ndarray, body_faces: np.ndarray,
                        frame_numbers: np.ndarray | None = None) -> GarmentFit:
    """cloth_frames (F, P, 3) and body_frames (F, V, 3), both Y-up metres, frame k of each at the same
    time; body_faces (T, 3) int; frame_numbers (F,) the cache frames they are (for worst_frame) -> GarmentFit."""
    from scipy.spatial import cKDTree

    cloth_frames = np.asarray(cloth_frames, np.float64)
    body_frames = np.asarray(body_frames, np.float64)
    if cloth_frames.ndim != 3 or cloth_frames.shape[-1] != 3 or body_frames.ndim != 3 or body_frames.shape[-1] != 3:
        raise ValueError(f"cloth_frames and body_frames must be (F, N, 3), got {cloth_frames.shape} and {body_frames.shape}")
    if len(cloth_frames) != len(body_frames) or len(cloth_frames) == 0:
        raise ValueError(f"cloth and body need the same number (> 0) of frames, got {len(cloth_frames)} and {len(body_frames)}")
    frame_numbers = np.arange(len(cloth_frames)) if frame_numbers is None else np.asarray(frame_numbers)
    height = float(np.ptp(body_frames[0][:, 1]))
    if height <= 0:
        raise ValueError("the body has no height")
    corners, weights = surface_samples(body_frames[0], body_faces)
    shares = np.empty(len(cloth_frames))
    for k, (cloth, body) in enumerate(zip(cloth_frames, body_frames)):
        surface = np.einsum("nk,nkc->nc", weights, body[corners])
        # Only "farther than the limit or not" counts: the search stops at the limit (inf beyond it), and
        # an unbalanced tree builds in a fraction of the time for the one query it serves.
        tree = cKDTree(np.vstack([surface, body]), balanced_tree=False, compact_nodes=False)
        distance, _ = tree.query(cloth, distance_upper_bound=FAR_FROM_BODY * height)
        shares[k] = float(np.isinf(distance).mean())
    worst = int(np.argmax(shares))
    return GarmentFit(float(shares.mean()), int(frame_numbers[worst]), float(shares[worst]), height, len(shares))
