"""Parallax- and motion-corrected impostor samples: each baked (view, frame) tile reprojected to the camera's
direction and the cycle frame before crowdview's blend (crowdbake.reference.impostor_blend) mixes them.

A baked tile holds, per texel, the surface point its orthographic view saw. With that point's depth along
the view axis (and, optionally, its motion to a neighbouring baked frame), the texel's surface point is known
in 3D; a camera a few degrees away, or a frame part way to the next baked one, sees it elsewhere. The
runtime can only gather, so the reprojection is inverted per screen pixel by a fixed-point iteration
(as parallax occlusion mapping does): start where the pixel's ray crosses the plane through the bounds
centre, read the tile's depth (and motion) there, move the surface point to the frame, project it to the
camera, and shift the tile coordinate by the screen miss, mapped back into the tile's axes. Depth and
motion are dilated into the background (the nearest inside texel's), so every step reads a value, and
read bilinearly. The iteration converges to the surface nearest its start, which at a depth jump (an arm
before the torso) need not be the one the camera sees; with the tile's coverage known, it starts where the
pixel's ray, marched from the camera's side, first passes behind a covered texel's surface (first_hit). The
UV map, material and coverage are then read at the final texel, nearest, as crowdview reads them, and the
normal and colour also at the four texels round the point (`taps`: crowdview's filtered_normal and
filtered_albedo). Pure numpy; positions in model-space metres, coordinates in texels.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from crowdbake.bake import surface_maps
from crowdbake.reference.impostor_blend import DecodedTile, FrameWeights
from crowdbake.bake.impostor_views import OrthoView

# Fixed-point steps: at halfway between 32 azimuths (5.6°) or 20° rings (10°) each step shrinks the miss by
# about the camera angle's sine times the surface slope, so a few steps converge except at depth jumps.
DEFAULT_ITERATIONS = 4
# The march before them (runtime/src/config.h CV_MARCH_STEPS, CV_MARCH_REFINE): one step for each tile texel
# the ray's points cross in the source tile, at most MARCH_STEPS, then MARCH_REFINE halvings.
MARCH_STEPS = 48
MARCH_REFINE = 4


def _texel_scale(view: OrthoView) -> float:
    return view.size / (2.0 * view.radius)


def surface_points(view: OrthoView, xy: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(..., 3) model-space points of a view at texel coordinates (..., 2) (x right, y down, 0..size) and
    depth (...) in metres along view.back from the bounds centre (positive towards the camera)."""
    scale = _texel_scale(view)
    x = xy[..., 0] / scale - view.radius
    y = view.radius - xy[..., 1] / scale
    return view.center + x[..., None] * view.right + y[..., None] * view.up + depth[..., None] * view.back


def to_texels(view: OrthoView, points: np.ndarray) -> np.ndarray:
    """(..., 2) texel coordinates of (..., 3) model-space points in `view` (crowdbake.bake.impostor_views.project)."""
    offset = points - view.center
    scale = _texel_scale(view)
    return np.stack([(offset @ view.right + view.radius) * scale, (view.radius - offset @ view.up) * scale], axis=-1)


def bilinear_planes(planes: np.ndarray, size_x: int, x: np.ndarray, y: np.ndarray) -> list[np.ndarray]:
    """A field held as (C, H·W) planes (row-major texels) read bilinearly at texel coordinates x, y (any
    shape, alike), clamped to the edge: C arrays shaped like x. One plane at a time, four `take`s of
    contiguous float rows: about twice as fast as gathering (H·W, C) rows."""
    size_y = planes.shape[1] // size_x
    x = np.clip(x - 0.5, 0.0, size_x - 1.0)
    y = np.clip(y - 0.5, 0.0, size_y - 1.0)
    x0 = np.minimum(x.astype(np.intp), size_x - 2)  # x >= 0, so truncation is floor
    y0 = np.minimum(y.astype(np.intp), size_y - 2)
    fx, fy = x - x0, y - y0
    corner = y0 * size_x + x0
    out = []
    for plane in planes:
        top_left, top_right = plane.take(corner), plane.take(corner + 1)
        bottom_left, bottom_right = plane.take(corner + size_x), plane.take(corner + size_x + 1)
        top = top_left + (top_right - top_left) * fx
        bottom = bottom_left + (bottom_right - bottom_left) * fx
        out.append(top + (bottom - top) * fy)
    return out


def field_planes(field: np.ndarray) -> np.ndarray:
    """(S, S, C) or (S, S) field -> (C, S·S) contiguous planes for bilinear_planes."""
    field = np.asarray(field, np.float64)
    if field.ndim == 2:
        return field.reshape(1, -1)
    return np.ascontiguousarray(np.moveaxis(field, -1, 0)).reshape(field.shape[-1], -1)


def bilinear(field: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(S, S, C) or (S, S) field read bilinearly at (..., 2) texel coordinates, clamped to the edge."""
    read = bilinear_planes(field_planes(field), field.shape[1], xy[..., 0], xy[..., 1])
    return np.stack(read, axis=-1) if np.ndim(field) == 3 else read[0]


def reproject(source: OrthoView, depth: np.ndarray, target: OrthoView, motion: np.ndarray | None = None,
              fraction: float = 0.0, iterations: int = DEFAULT_ITERATIONS, coverage: np.ndarray | None = None,
              crop: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where each target pixel finds its surface point in the source tile.

    source, target: views of one size S; depth: (S, S) metres along source.back from the centre, dilated
    into the background; motion: optional (S, S, 3) metres each texel's surface point moves to the other
    baked frame, dilated likewise, applied times `fraction`; coverage: optional (S, S) 0..1, the character's
    share of each texel: with it the fixed-point steps start at the ray's first hit (first_hit), within
    `crop` (x, y, width, height tile texels; None: the whole tile). Returns (S, S, 2) source texel
    coordinates and (S, S) the remaining screen miss in target texels.
    """
    field = depth if motion is None or not fraction else np.concatenate(
        [depth[..., None], fraction * (motion @ np.stack([source.right, source.up, source.back]).T)], axis=-1)
    march = None if coverage is None else (field_planes(np.stack([depth, coverage], axis=-1)), crop or (0, 0, depth.shape[1], depth.shape[0]))
    return reproject_planes(source, field_planes(field), depth.shape[1], target, iterations, march)


def tile_points(view: OrthoView, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tile texel coordinates (x, y), each (...), of model-space offsets (..., 3) from the bounds centre."""
    scale = _texel_scale(view)
    return (offsets @ view.right + view.radius) * scale, (view.radius - offsets @ view.up) * scale


def march_span(source: OrthoView, target: OrthoView, on_plane: np.ndarray, crop: tuple[int, int, int, int],
               reach: float) -> tuple[np.ndarray, np.ndarray]:
    """(lowest, highest), each (...): the depths along target.back, within +-reach metres, between which the
    ray through each on_plane point (..., 3 offsets from the bounds centre) projects into the source's crop
    (x, y, width, height tile texels; a slab per tile axis). lowest > highest where it never does. As
    impostor_warp.glsl march_span: only steps in this span can pass behind the source's surface."""
    scale = _texel_scale(source)
    along = scale * np.array([target.back @ source.right, -(target.back @ source.up)])  # texels a metre of depth
    at_plane = tile_points(source, on_plane)
    lowest, highest = np.full(on_plane.shape[:-1], -reach), np.full(on_plane.shape[:-1], reach)
    for axis in range(2):
        start, end = crop[axis], crop[axis] + crop[axis + 2]
        if abs(along[axis]) < 1e-6:  # the ray keeps this coordinate: all of it or none inside
            inside = (at_plane[axis] >= start) & (at_plane[axis] < end)
            lowest, highest = np.where(inside, lowest, reach), np.where(inside, highest, -reach)
            continue
        a, b = (start - at_plane[axis]) / along[axis], (end - at_plane[axis]) / along[axis]
        lowest, highest = np.maximum(lowest, np.minimum(a, b)), np.minimum(highest, np.maximum(a, b))
    return lowest, highest


def first_hit(source: OrthoView, target: OrthoView, on_plane: np.ndarray, planes: np.ndarray, width: int,
              crop: tuple[int, int, int, int], start: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Where each target pixel's ray first passes behind the surface of a covered source texel (as
    impostor_warp.glsl first_hit): marched from the camera's side of the bounds (depth +radius along
    target.back) to the far side, one step for each source texel the ray's points cross (the tile size
    times the sine of the angle between the views; 1 to MARCH_STEPS), then MARCH_REFINE halvings; the last
    point in front of the surface is returned, `start` (x, y) where the ray never passes behind one. Steps
    whose points project outside `crop` are skipped (march_span): they cannot pass behind a covered texel.
    on_plane: (S, S, 3) each pixel's point on the plane through the bounds centre facing the target camera,
    as an offset from the centre; planes: the source's depth (metres along source.back) and coverage (0..1)
    as (2, S·S) planes."""
    size, radius = target.size, target.radius
    low = np.array(crop[:2], dtype=np.float64)
    high = low + np.array(crop[2:], dtype=np.float64)

    def behind(depth: np.ndarray) -> np.ndarray:
        points = on_plane + depth[..., None] * target.back
        x, y = tile_points(source, points)
        inside = (x >= low[0]) & (y >= low[1]) & (x < high[0]) & (y < high[1])
        surface, share = bilinear_planes(planes, width, np.clip(x, low[0] + 0.5, high[0] - 0.5), np.clip(y, low[1] + 0.5, high[1] - 0.5))
        return inside & (share > 0.5) & (points @ source.back <= surface)

    crossed = size * float(np.linalg.norm(np.cross(source.back, target.back)))  # texels the ray's points span
    if crossed < 0.01:  # the source's own view: every depth lands on the start
        return start
    reach = surface_maps.DEPTH_RANGE * radius  # the span of the surface map's depth codes
    steps = int(np.clip(np.ceil(crossed), 1, MARCH_STEPS))
    spacing = 2.0 * reach / steps
    # The steps keep their places; those outside the crop's span are skipped (march_span), the first kept
    # step's predecessor standing as the last point in front.
    lowest, highest = march_span(source, target, on_plane, crop, reach)
    first = np.maximum(1, np.floor((reach - highest) / spacing).astype(np.int64))
    last = np.minimum(steps, np.ceil((reach - lowest) / spacing).astype(np.int64))
    found = np.zeros((size, size), dtype=bool)
    front, back = reach - (first - 1) * spacing, np.full((size, size), reach)
    for n in range(1, steps + 1):
        depth = reach - n * spacing
        hit = ~found & (first <= n) & (n <= last) & behind(np.full((size, size), depth))
        front[hit], back[hit] = depth + spacing, depth
        found |= hit
    for _ in range(MARCH_REFINE):
        middle = 0.5 * (front + back)
        passed = behind(middle)
        back, front = np.where(passed, middle, back), np.where(passed, front, middle)
    x, y = tile_points(source, on_plane + front[..., None] * target.back)
    return np.where(found, x, start[0]), np.where(found, y, start[1])


def reproject_planes(source: OrthoView, planes: np.ndarray, width: int, target: OrthoView,
                     iterations: int = DEFAULT_ITERATIONS,
                     march: tuple[np.ndarray, tuple[int, int, int, int]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """reproject with the source's fields as (C, S·S) planes (field_planes): depth, then optionally the
    motion times the fraction along the source's right, up and (optionally) back; march: the depth and
    coverage planes and the crop for first_hit (None: start on the centre plane). Returns the same.

    The views' axes are constant, so the surface point is kept as its coordinates along the source's
    right, up and back, and the screen miss of a step is an affine function of the texel coordinate and
    the reads: its constant and coefficients are taken once (the sums of surface_points then to_texels,
    fewer operations per pixel).
    """
    size = target.size
    scale = _texel_scale(target)
    radius = target.radius
    rows, columns = np.mgrid[0:size, 0:size]
    pixel_x, pixel_y = columns + 0.5, rows + 0.5
    source_axes = np.stack([source.right, source.up, source.back])
    on_right, on_up = source_axes @ target.right, source_axes @ target.up  # (3,) each
    # Start where the pixel's ray crosses the plane through the centre facing the camera.
    plane_right, plane_up = pixel_x / scale - radius, radius - pixel_y / scale
    start = plane_right[..., None] * target.right + plane_up[..., None] * target.up
    x = (start @ source.right + radius) * scale
    y = (radius - start @ source.up) * scale
    if march is not None:
        x, y = first_hit(source, target, start, march[0], width, march[1], (x, y))
    # A point at source texel (x, y) plus (right, up, back) metres lands at target texel
    #   (on_right · (x/s - r + right, r - y/s + up, back) + r) · s  across, and
    #   (r - on_up · (...)) · s  down; the miss is the pixel minus that.
    miss_x0 = pixel_x - scale * radius * (1.0 - on_right[0] + on_right[1])
    miss_y0 = pixel_y - scale * radius * (1.0 + on_up[0] - on_up[1])
    along = [scale * on_right, scale * on_up]  # per metre along the source's right, up, back
    # A screen miss (dx right, dy down, target texels) as a move in the source's texels.
    sx_dx, sx_dy = target.right @ source.right, -(target.up @ source.right)
    sy_dx, sy_dy = -(target.right @ source.up), target.up @ source.up
    for _ in range(iterations + 1):
        read = bilinear_planes(planes, width, x, y)
        dx = miss_x0 - on_right[0] * x + on_right[1] * y - along[0][2] * read[0]
        dy = miss_y0 + on_up[0] * x - on_up[1] * y + along[1][2] * read[0]
        for axis, moved in enumerate(read[1:]):  # right, up, back
            dx -= along[0][axis] * moved
            dy += along[1][axis] * moved
        x, y = x + sx_dx * dx + sx_dy * dy, y + sy_dx * dx + sy_dy * dy
    return np.stack([x, y], axis=-1), np.hypot(dx, dy)


def gather(tile: DecodedTile, xy: np.ndarray, valid: np.ndarray | None = None) -> DecodedTile:
    """The tile read at (S, S, 2) texel coordinates, nearest texel; outside the tile or not `valid`: uncovered."""
    size_y, size_x = tile.covered.shape
    x = np.floor(xy[..., 0]).astype(np.intp)
    y = np.floor(xy[..., 1]).astype(np.intp)
    inside = (x >= 0) & (x < size_x) & (y >= 0) & (y < size_y)
    texel = np.clip(y, 0, size_y - 1) * size_x + np.clip(x, 0, size_x - 1)  # flat indices: one `take` a map
    covered = tile.covered.reshape(-1).take(texel) & inside
    if valid is not None:
        covered &= valid
    uv = np.where(covered[..., None], tile.uv.reshape(-1, 2).take(texel, axis=0), 0.0)
    return DecodedTile(uv, tile.material.reshape(-1).take(texel), covered, tile.normal.reshape(-1, 3).take(texel, axis=0))


def motion_fraction(layer: int, frames: FrameWeights) -> float:
    """How far a sample of atlas layer `layer` moves along its layer's motion (one baked step of velocity):
    the earlier of the two blended frames forward by the frame weight, the later one back by the rest
    (shaders/impostor_warp.glsl: +w for frame sample 0, -(1 - w) for sample 1); 0 when both are one."""
    if frames.layers[0] == frames.layers[1]:
        return 0.0
    return frames.weight if layer == frames.layers[0] else -(1.0 - frames.weight)


def bilinear_taps(tile: DecodedTile, xy: np.ndarray, crop: tuple[int, int, int, int]) -> tuple[tuple[np.ndarray, DecodedTile], ...]:
    """The four texels round each (S, S, 2) texel coordinate (top left, top right, bottom left, bottom
    right, clamped to `crop`), each gathered (gather) with its (S, S) bilinear weight: what crowdview's
    filtered_normal and filtered_albedo read (impostor_warp.glsl bilinear_taps)."""
    q = xy - 0.5
    corner = np.floor(q)
    fx, fy = q[..., 0] - corner[..., 0], q[..., 1] - corner[..., 1]
    x0, y0, width, height = crop
    taps = []
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        x = np.clip(corner[..., 0] + dx, x0, x0 + width - 1)
        y = np.clip(corner[..., 1] + dy, y0, y0 + height - 1)
        weight = (fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy)
        taps.append((weight, gather(tile, np.stack([x + 0.5, y + 0.5], axis=-1))))
    return tuple(taps)


def warp_tile(tile: DecodedTile, source: OrthoView, surface: tuple[np.ndarray, np.ndarray], target: OrthoView,
              fraction: float, iterations: int = DEFAULT_ITERATIONS, coverage: np.ndarray | None = None,
              crop: tuple[int, int, int, int] | None = None) -> DecodedTile:
    """A (view, frame) sample as crowdview draws it with reprojection: `tile` gathered where each pixel of
    the `target` view finds its surface point, with the four texels round it (`taps`). surface: the tile's
    (depth (S, S), motion (S, S, 2)) metres, decoded from the bundle's surface map
    (crowdbake.bake.surface_maps.decode_surface); coverage: its (S, S) alpha, 0..1 (None: all 1, as a bc1
    surface map reads), read bilinearly at the same points as the sample's share and marched through
    (first_hit); crop: the stored part of the tile (x, y, width, height; None: all of it). At the sample's
    own view and frame the reprojection is the identity, and the tile is returned as it is."""
    same_view = source.azimuth_deg == target.azimuth_deg and source.elevation_deg == target.elevation_deg
    if same_view and fraction == 0.0:
        return tile if coverage is None else replace(tile, share=np.asarray(coverage, np.float64))
    depth, motion = surface
    if fraction:  # the surface map's motion is along the source's right and up already
        planes = np.stack([depth.ravel(), fraction * motion[..., 0].ravel(), fraction * motion[..., 1].ravel()])
    else:
        planes = depth.reshape(1, -1)
    crop = crop or (0, 0, depth.shape[1], depth.shape[0])
    share = np.ones_like(depth) if coverage is None else np.asarray(coverage, np.float64)
    xy, miss = reproject_planes(source, planes, depth.shape[1], target, iterations, (field_planes(np.stack([depth, share], axis=-1)), crop))
    gathered = replace(gather(tile, xy), miss=miss, taps=bilinear_taps(tile, xy, crop))
    return gathered if coverage is None else replace(gathered, share=bilinear(coverage, xy))
