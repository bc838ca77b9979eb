"""The two sample garments: a loose ankle-length skirt and a tight mid-thigh skirt.

A garment is a cylinder of `rows` rings by `columns` vertices hanging from a waistband. Its rest
shape is built around the collision body over the whole walk cycle, in the hips' rest frame: at
every height the ring clears the outermost capsule surface (legs included, in every pose of the
cycle) by `ease`; the loose skirt additionally flares out as a cone from the hips to a wide hem.
So the garment starts without penetrating the body in the frame-0 pose, and the tight one is as
tight as the stride allows.

The waistband row is pinned on the skin: WAISTBAND_GAP outside the torso's surface (and never inside
a capsule), so seen from above no gap opens between body and skirt. It follows the body with the same
skin weights as the torso at that height. The loose skirt's flare starts below the hips: above it the
cut follows the body like the tight one (a flare carried up to the waistband left it 5 cm off the waist all round). UVs unwrap the
cylinder into GARMENT_UV_RECT of the shared texture: u around (starting at the back, like the body's tubes), v down from the waistband. The seam column has two UVs per
position, so the OBJ keeps one position per vertex (what the PC2 cache indexes) and a reader splits
the seam.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from crowdbake.sample.cloth_sim import ClothParams
from crowdbake.sample.colliders import WAIST_HEIGHT, torso_radius
from crowdbake.sample.humanoid import GARMENT_UV_RECT, STANDARD, UV_INSET, Build

# Metres between the torso's surface and the pinned waistband: the band's own thickness on the skin.
WAISTBAND_GAP = 0.002
# Metres the pinned waistband keeps outside the collision capsules where they stand proud of the skin,
# so the body's turning under it (the spine twists against the hips) does not sink it into them.
WAISTBAND_CAPSULE_CLEARANCE = 0.002

# Both garments are the same cloth (ClothParams defaults); only cut and length differ. The paper
# (section 3) found tight clothing settles into a cycle within a few walk cycles and loose skirts
# need many or never do; that comes out of these two cuts without tuning the cloth per garment.


@dataclass(frozen=True)
class GarmentSpec:
    """Cut of a skirt. Heights in metres in the rest pose (y up); radii in metres."""

    name: str
    waist_y: float
    hem_y: float
    rows: int
    columns: int
    ease: float  # clearance over the body's outermost capsule surface
    flare_top_y: float = 0.0  # the cone starts here ...
    flare_top_radius: float = 0.0  # ... with this radius
    hem_radius: float = 0.0  # cone radius at the hem (0: no flare)
    pinned_rows: int = 1
    params: ClothParams = field(default_factory=ClothParams)


GARMENT_SPECS: dict[str, GarmentSpec] = {
    # Ankle-length, flaring from the hips to a 0.36 m hem radius: lots of free cloth the legs kick. The
    # cone starts at 0.14 m, inside the hips' cut at the sides and a little outside it at front and back,
    # so the cloth falls from the hips; a wider top (0.17 m) left a shelf standing out from the waistband
    # on the skin that never settled into a cycle.
    "loose": GarmentSpec(
        name="loose",
        waist_y=WAIST_HEIGHT,
        hem_y=0.26,
        rows=30,
        columns=72,
        ease=0.012,
        flare_top_y=0.98,
        flare_top_radius=0.14,
        hem_radius=0.36,
    ),
    # Mid-thigh, cut just around the hips and the thighs' range of motion: it rides on the body.
    "tight": GarmentSpec(
        name="tight",
        waist_y=WAIST_HEIGHT,
        hem_y=0.64,
        rows=15,
        columns=72,
        ease=0.010,
    ),
}
GARMENT_NAMES = tuple(GARMENT_SPECS)


def fitted_spec(spec: GarmentSpec, build: Build) -> GarmentSpec:
    """The cut of a garment for a build: heights scale with its height, the flare's radii with its hips
    (their width and girth). The rest (ease, rows, columns, cloth) is the garment's own."""
    if build == STANDARD:
        return spec
    h, hips = build.height, build.hip_width * build.girth
    return replace(spec, waist_y=spec.waist_y * h, hem_y=spec.hem_y * h, flare_top_y=spec.flare_top_y * h,
                   flare_top_radius=spec.flare_top_radius * hips, hem_radius=spec.hem_radius * hips)


@dataclass(frozen=True)
class Garment:
    """rest_positions (V, 3) float64, V = rows * columns, vertex r * columns + c; faces (T, 3) int64;
    uvs (U, 2) float32 with U = rows * (columns + 1) (glTF convention) and uv_faces (T, 3) indexing them;
    pinned (P,) int64 vertex indices of the waistband."""

    spec: GarmentSpec
    rest_positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    uv_faces: np.ndarray
    pinned: np.ndarray

    def vertex_uvs(self) -> np.ndarray:
        """One UV per position (V, 2): the seam column takes its u = start-of-rect UV."""
        rows, columns = self.spec.rows, self.spec.columns
        return self.uvs.reshape(rows, columns + 1, 2)[:, :columns].reshape(-1, 2)


def outer_radius(heights: np.ndarray, angles: np.ndarray, capsules: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Outermost distance from the vertical axis x = z = 0 at which rays hit any capsule.

    heights (R,) metres; angles (A,) radians around y, 0 pointing to -z (the back), pi/2 to +x;
    capsules (K, C, 2, 3) endpoints over K poses; radii (C,) -> (R, A) metres (0 where nothing is hit).
    Each capsule is cut by the horizontal plane at each height, and the cut is approximated by a
    circle (exact for vertical capsules, 1/cos(tilt) too small for tilted ones: ease covers it).
    """
    a, b = capsules[:, :, 0], capsules[:, :, 1]  # (K, C, 3)
    y = heights[:, None, None]  # (R, 1, 1)
    span = b[..., 1] - a[..., 1]
    safe = np.where(np.abs(span) < 1e-9, 1.0, span)
    t = np.clip((y - a[..., 1]) / safe, 0.0, 1.0)  # (R, K, C): segment point nearest the plane
    point = a[None] + t[..., None] * (b - a)[None]
    dy = y - point[..., 1]
    rho_squared = radii[None, None] ** 2 - dy**2
    centre = point[..., [0, 2]]  # (R, K, C, 2) in the x-z plane
    direction = np.stack([np.sin(angles), -np.cos(angles)], axis=1)  # (A, 2)
    projection = np.einsum("rkcj,aj->rkca", centre, direction)
    discriminant = projection**2 - np.sum(centre**2, axis=-1)[..., None] + rho_squared[..., None]
    far = np.where((discriminant >= 0) & (rho_squared[..., None] > 0), projection + np.sqrt(np.maximum(discriminant, 0.0)), 0.0)
    return np.maximum(far, 0.0).max(axis=(1, 2))


def grid_faces(rows: int, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of a closed cylinder grid and their UV-grid counterparts (the seam column duplicated).

    Quads alternate their diagonal in a checkerboard so the cloth has no preferred shear direction.
    Returns faces (T, 3) into rows * columns positions and uv_faces (T, 3) into rows * (columns + 1) UVs.
    """
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(columns), indexing="ij")
    r, c = r.ravel(), c.ravel()
    c_next = (c + 1) % columns
    p00, p01, p10, p11 = r * columns + c, r * columns + c_next, (r + 1) * columns + c, (r + 1) * columns + c_next
    width = columns + 1
    t00, t01, t10, t11 = r * width + c, r * width + c + 1, (r + 1) * width + c, (r + 1) * width + c + 1
    flip = (r + c) % 2 == 1
    # Winding: rows go down (-y), columns go round from the back towards +x; (p00, p01, p10) faces outward.
    first = np.where(flip[:, None], np.stack([p00, p11, p10], 1), np.stack([p00, p01, p10], 1))
    second = np.where(flip[:, None], np.stack([p00, p01, p11], 1), np.stack([p01, p11, p10], 1))
    first_uv = np.where(flip[:, None], np.stack([t00, t11, t10], 1), np.stack([t00, t01, t10], 1))
    second_uv = np.where(flip[:, None], np.stack([t00, t01, t11], 1), np.stack([t01, t11, t10], 1))
    return np.concatenate([first, second]).astype(np.int64), np.concatenate([first_uv, second_uv]).astype(np.int64)


def build_garment(spec: GarmentSpec, capsules_local: np.ndarray, radii: np.ndarray, thickness: float, build: Build = STANDARD) -> Garment:
    """The garment's rest mesh around the body (of `build`; spec as fitted_spec gives for it).

    capsules_local (K, C, 2, 3): the body's capsules over the cycle, expressed in the hips' rest
    frame (so the pose of the pelvis does not count, only the limbs relative to it); radii (C,);
    thickness: the simulator's collision margin, added to the capsule radii.
    """
    if spec.rows < 3 or spec.columns < 8 or spec.hem_y >= spec.waist_y:
        raise ValueError(f"garment {spec.name}: needs rows >= 3, columns >= 8 and hem below waist")
    heights = np.linspace(spec.waist_y, spec.hem_y, spec.rows)
    angles = 2.0 * np.pi * np.arange(spec.columns) / spec.columns
    radius = outer_radius(heights, angles, capsules_local, np.asarray(radii) + thickness) + spec.ease
    # The pinned waistband sits on the skin; the rows below hang clear of the capsules as cut above.
    for row in range(spec.pinned_rows):
        on_skin = torso_radius(heights[row], angles, build) + WAISTBAND_GAP
        clear = outer_radius(heights[row : row + 1], angles, capsules_local, np.asarray(radii))[0] + WAISTBAND_CAPSULE_CLEARANCE
        radius[row] = np.maximum(on_skin, clear)
    if spec.hem_radius > 0:
        # The cone flares below its top only: above it (the hips, the waistband) the cut follows the body.
        fraction = (spec.flare_top_y - heights) / (spec.flare_top_y - spec.hem_y)
        cone = np.where(fraction >= 0.0, spec.flare_top_radius + fraction * (spec.hem_radius - spec.flare_top_radius), 0.0)
        radius = np.maximum(radius, cone[:, None])
    # A ring must not be narrower than the one above it would allow the cloth to hang: keep rings
    # monotone below the widest point so the rest shape has no pleat folded inwards.
    widest = int(np.argmax(radius.mean(axis=1)))
    radius[widest:] = np.maximum.accumulate(radius[widest:], axis=0)
    positions = np.stack(
        [
            radius * np.sin(angles)[None],
            np.repeat(heights[:, None], spec.columns, axis=1),
            -radius * np.cos(angles)[None],
        ],
        axis=-1,
    ).reshape(-1, 3)
    faces, uv_faces = grid_faces(spec.rows, spec.columns)

    u0, v0, u1, v1 = GARMENT_UV_RECT
    inset_u, inset_v = UV_INSET * (u1 - u0), UV_INSET * (v1 - v0) * 4
    u = u0 + inset_u + (u1 - u0 - 2 * inset_u) * np.arange(spec.columns + 1) / spec.columns
    v = v0 + inset_v + (v1 - v0 - 2 * inset_v) * np.arange(spec.rows) / (spec.rows - 1)
    uvs = np.stack(np.meshgrid(u, v, indexing="xy"), axis=-1).reshape(-1, 2).astype(np.float32)
    pinned = np.arange(spec.pinned_rows * spec.columns, dtype=np.int64)
    return Garment(spec, positions, faces, uvs, uv_faces, pinned)
