"""Vertex-animation textures (VAT): a mesh part's frames as 16-bit images an engine samples per vertex.

Layout (docs/export.md): one texel per vertex per block of rows. A block (a pose frame, or one of a skin's
per-vertex blocks) takes `rows_per_frame` rows of `width` texels: vertex `i` of block `f` is texel
`(x, y) = (i % width, f * rows_per_frame + i // width)`. `width` is the vertex count, wrapped at MAX_WIDTH
so the texture fits every WebGL2 device. Unused texels at the end of a block's last row are 0.

Two kinds, both R16G16B16A16_UNORM:

- `frames` (encode_vat): block f is pose frame f. RGB: the position, `q = round((p - bounds_min) /
  (bounds_max - bounds_min) * 65535)` per axis, decoded `p = bounds_min + q / 65535 * (bounds_max -
  bounds_min)`; A: the normal as an octahedral word (below). Each axis's codes lie on a grid of s = 2^k
  codes (position_steps: the coarsest whose half step, s * extent / 131070, is within
  POSITION_BOUND_M / sqrt(3), so a position is within POSITION_BOUND_M of its frame's as a distance; s = 8
  on a 2 m axis, 0.125 mm), so the low bits repeat and zstd finds them. Readers decode as before.
- `skin` (encode_skin), for a body the bundle stores as skinning (a CBSK): three blocks per vertex,
  SKIN_BLOCKS: 0 the rest position (RGB, as above, over the rest mesh's bounds) and rest normal (A);
  1 the four joint indices (each channel the index itself, read as q * 65535); 2 the four weights (unorm16
  codes summing to 65535, the CBSK's own). A second texture (encode_joints) holds per pose frame and joint
  the three rows of its 3 x 4 skinning matrix, row r of joint j at texel index i = 3 j + r of the frame's
  block; each channel c decodes as `joint_min[c] + q / 65535 * (joint_max[c] - joint_min[c])` (RGB the
  3 x 3 block's columns, A the translation). A shader skins the rest vertex as crowdview does
  (runtime/src/shaders/mesh.vert.glsl): p = sum_k w_k M_jk (rest, 1), n = normalize(sum_k w_k L_jk rest_n).

Octahedral word (Meyer et al., "On floating-point normal vectors", EGSR 2010, section 3.3; Cigolle et al.,
JCGT 2014): the unit normal's two octahedral coordinates e in [-1, 1] as 8-bit codes u, v =
round((e + 1) / 2 * 255), word = u + 256 v; decode e = code / 255 * 2 - 1, z = 1 - |e.x| - |e.y|, where
z < 0 fold (x, y) = (1 - |e.y|, 1 - |e.x|) * sign, normalise. Within 0.95 degrees (OCTAHEDRAL_MAX_ERROR_DEG);
normals only shade, and the word rides in the alpha the position leaves free, so a frame is one fetch and
8 bytes where a separate RGBA8 normal texture took 12.

Bounds are over every frame, so one pair serves every animation. An axis with zero extent (a flat mesh)
stores 0 and decodes to bounds_min exactly.

Each vertex's texel in block 0 is given to the mesh as its second texture coordinate (TEXCOORD_1), at the
texel's centre, so an engine that reorders or splits vertices on import keeps the link.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from crowdbake.formats.pose_codec import decode_octahedral, encode_octahedral
from crowdbake.formats.skinned_cache import WEIGHT_CODE_SUM

# WebGL2 guarantees 2048-texel textures (MAX_TEXTURE_SIZE >= 2048); every desktop GPU does 8192+.
MAX_WIDTH = 2048
UNORM16_MAX = 65535
OCTAHEDRAL_CODE_MAX = 255  # 8 bits per octahedral coordinate, two in the 16-bit alpha
# The largest angle between a unit normal and its decoded octahedral word: measured over a dense sphere by
# services/tests/test_export_vat.py.
OCTAHEDRAL_MAX_ERROR_DEG = 0.95
# The largest distance of a `frames` VAT position from the pose frame's own (position_steps): a quarter of a
# millimetre, half the bundle's own cloth rounding bound (SPEC.md, CBPC) and far under a pixel.
POSITION_BOUND_M = 2.5e-4
# A skin texture's blocks per vertex: rest position and normal, joints, weights.
SKIN_BLOCKS = 3
SKIN_REST, SKIN_JOINTS, SKIN_WEIGHTS = range(SKIN_BLOCKS)
# A joint's 3 x 4 matrix takes three texels, one per row.
JOINT_ROWS = 3


@dataclass(frozen=True)
class VatLayout:
    """Where each vertex of each block (a frame, or a skin's block) lives in the texture."""

    vertex_count: int
    frame_count: int
    width: int
    rows_per_frame: int

    @property
    def height(self) -> int:
        return self.frame_count * self.rows_per_frame


def vat_layout(vertex_count: int, frame_count: int, max_width: int = MAX_WIDTH) -> VatLayout:
    """The texture layout for `vertex_count` vertices over `frame_count` blocks (both > 0)."""
    if vertex_count <= 0 or frame_count <= 0 or max_width <= 0:
        raise ValueError(f"vertex_count, frame_count and max_width must be positive, got {vertex_count}, {frame_count}, {max_width}")
    width = min(vertex_count, max_width)
    return VatLayout(vertex_count, frame_count, width, -(-vertex_count // width))


def vat_texcoords(layout: VatLayout, vertices: np.ndarray | None = None) -> np.ndarray:
    """(V, 2) float32: each vertex's texel centre in block 0, as (u, v) in [0, 1] over the whole texture.
    vertices: (V,) indices into the layout's vertices (another LOD's mesh reading these texels), else all."""
    index = np.arange(layout.vertex_count) if vertices is None else np.asarray(vertices, dtype=np.int64)
    x = index % layout.width
    y = index // layout.width
    return np.stack([(x + 0.5) / layout.width, (y + 0.5) / layout.height], axis=1).astype(np.float32)


def _place(values: np.ndarray, layout: VatLayout) -> np.ndarray:
    """(F, V, 4) uint16 -> (H, W, 4) image in the layout, unused texels 0."""
    frames, vertices, _ = values.shape
    padded = np.zeros((frames, layout.rows_per_frame * layout.width, 4), dtype=values.dtype)
    padded[:, :vertices] = values
    return padded.reshape(layout.height, layout.width, 4)


def _unplace(image: np.ndarray, layout: VatLayout) -> np.ndarray:
    """(H, W, 4) image -> (F, V, 4) values (inverse of _place)."""
    per_frame = image.reshape(layout.frame_count, layout.rows_per_frame * layout.width, 4)
    return per_frame[:, : layout.vertex_count]


def octahedral_words(normals: np.ndarray) -> np.ndarray:
    """(..., 3) unit normals -> (...) uint16 octahedral words: u + 256 v, 8 bits each (module docstring)."""
    codes = encode_octahedral(normals, OCTAHEDRAL_CODE_MAX)
    return (codes[..., 0] | (codes[..., 1] << 8)).astype(np.uint16)


def decode_octahedral_words(words: np.ndarray) -> np.ndarray:
    """(...) uint16 octahedral words -> (..., 3) float64 unit normals (the shaders decode alike)."""
    words = np.asarray(words).astype(np.int64)
    return decode_octahedral(np.stack([words & 0xFF, words >> 8], axis=-1), OCTAHEDRAL_CODE_MAX).astype(np.float64)


def _position_codes(positions: np.ndarray, bound_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(..., V, 3) metres -> (codes (..., V, 3) float64 in 0..65535, bounds_min (3,), bounds_max (3,), steps (3,)):
    each axis's codes rounded once onto position_steps' grid for bound_m (0: every code, steps 1)."""
    low = positions.reshape(-1, 3).min(axis=0)
    high = positions.reshape(-1, 3).max(axis=0)
    extent = high - low
    scale = np.divide(UNORM16_MAX, extent, out=np.zeros(3), where=extent > 0)
    steps = position_steps(extent, bound_m) if bound_m > 0 else np.ones(3, dtype=np.int64)
    # A code past the last multiple of its step (near 65535) stays the top code: still within half a step.
    return np.minimum(np.rint((positions - low) * scale / steps) * steps, UNORM16_MAX), low, high, steps


def position_steps(extent: np.ndarray, bound_m: float = POSITION_BOUND_M) -> np.ndarray:
    """(3,) axis extents (metres) -> (3,) int64 grid steps in 16-bit codes, each a power of two: the largest
    whose half step (s · extent / 131070) is within bound_m / sqrt(3), or 1."""
    per_axis = bound_m / np.sqrt(3.0)
    half_code = np.asarray(extent, dtype=np.float64) / (2 * UNORM16_MAX)
    ratio = np.divide(per_axis, half_code, out=np.full(3, 1.0), where=half_code > 0)
    exponent = np.clip(np.floor(np.log2(np.maximum(ratio, 1.0))), 0, 15)
    return (2 ** exponent).astype(np.int64)


@dataclass(frozen=True)
class VertexAnimation:
    """A pose cache as one `frames` VAT image (H, W, 4) uint16 (positions in RGB, octahedral normals in A)
    and the bounds that decode positions (metres)."""

    layout: VatLayout
    texels: np.ndarray
    bounds_min: np.ndarray  # (3,) float64
    bounds_max: np.ndarray
    steps: np.ndarray = field(default_factory=lambda: np.ones(3, dtype=np.int64))  # (3,) codes per grid step (position_steps)

    @property
    def max_position_error(self) -> np.ndarray:
        """(3,) metres: the largest decode error per axis, half a grid step."""
        return (self.bounds_max - self.bounds_min) * self.steps / (2 * UNORM16_MAX)


def encode_vat(positions: np.ndarray, normals: np.ndarray, max_width: int = MAX_WIDTH, bound_m: float = POSITION_BOUND_M) -> VertexAnimation:
    """positions, normals: (F, V, 3) float, metres and unit vectors -> VertexAnimation (module docstring), the
    positions on position_steps' grid for bound_m (0: the plain 16 bits)."""
    positions = np.asarray(positions, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or normals.shape != positions.shape:
        raise ValueError(f"positions and normals must be (F, V, 3) alike, got {positions.shape} and {normals.shape}")
    layout = vat_layout(positions.shape[1], positions.shape[0], max_width)
    codes, low, high, steps = _position_codes(positions, bound_m)
    texels = np.concatenate([codes, octahedral_words(normals)[..., None]], axis=2).astype(np.uint16)
    return VertexAnimation(layout, _place(texels, layout), low, high, steps)


def decode_vat(animation: VertexAnimation) -> tuple[np.ndarray, np.ndarray]:
    """VertexAnimation -> (positions, normals), each (F, V, 3) float64; normals unit."""
    values = _unplace(animation.texels, animation.layout)
    positions = animation.bounds_min + values[..., :3].astype(np.float64) / UNORM16_MAX * (animation.bounds_max - animation.bounds_min)
    return positions, decode_octahedral_words(values[..., 3])


@dataclass(frozen=True)
class SkinTexture:
    """A skinned body's `skin` VAT image (H, W, 4) uint16, SKIN_BLOCKS blocks a vertex (module docstring),
    and the bounds that decode its rest positions (metres)."""

    layout: VatLayout
    texels: np.ndarray
    bounds_min: np.ndarray  # (3,) float64
    bounds_max: np.ndarray


def encode_skin(rest_positions: np.ndarray, rest_normals: np.ndarray, joints: np.ndarray, weight_codes: np.ndarray,
                max_width: int = MAX_WIDTH) -> SkinTexture:
    """rest_positions, rest_normals (V, 3) float; joints (V, 4) int; weight_codes (V, 4) unorm16 codes summing to
    65535 -> SkinTexture. A joint whose weight is 0 is written as 0 (any joint would do; 0 reads the least)."""
    rest_positions = np.asarray(rest_positions, dtype=np.float64)
    vertex_count = rest_positions.shape[0] if rest_positions.ndim == 2 else -1
    shapes = [np.shape(rest_positions), np.shape(rest_normals), np.shape(joints), np.shape(weight_codes)]
    if shapes != [(vertex_count, 3), (vertex_count, 3), (vertex_count, 4), (vertex_count, 4)]:
        raise ValueError(f"rest positions and normals (V, 3), joints and weights (V, 4) expected, got {shapes}")
    joints = np.asarray(joints, dtype=np.int64)
    weight_codes = np.asarray(weight_codes, dtype=np.int64)
    if joints.min(initial=0) < 0 or joints.max(initial=0) > UNORM16_MAX or (weight_codes.sum(axis=1) != WEIGHT_CODE_SUM).any():
        raise ValueError(f"joints must be 0..{UNORM16_MAX} and each vertex's weight codes sum to {WEIGHT_CODE_SUM}")
    layout = vat_layout(vertex_count, SKIN_BLOCKS, max_width)
    codes, low, high, _ = _position_codes(rest_positions)
    rest = np.concatenate([codes, octahedral_words(rest_normals)[:, None]], axis=1)
    blocks = np.stack([rest, np.where(weight_codes > 0, joints, 0), weight_codes]).astype(np.uint16)
    return SkinTexture(layout, _place(blocks, layout), low, high)


def decode_skin(texture: SkinTexture) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SkinTexture -> (rest positions (V, 3) float64, rest normals (V, 3) unit, joints (V, 4) int64, weights (V, 4) float64)."""
    blocks = _unplace(texture.texels, texture.layout)
    rest = blocks[SKIN_REST]
    positions = texture.bounds_min + rest[:, :3].astype(np.float64) / UNORM16_MAX * (texture.bounds_max - texture.bounds_min)
    return (positions, decode_octahedral_words(rest[:, 3]), blocks[SKIN_JOINTS].astype(np.int64),
            blocks[SKIN_WEIGHTS].astype(np.float64) / WEIGHT_CODE_SUM)


@dataclass(frozen=True)
class JointTexture:
    """Every pose frame's joint matrices as a `joints` image (H, W, 4) uint16 (module docstring): the layout's
    vertices are the matrix rows (3 a joint), its blocks the pose frames; minimum, maximum (4,) decode the
    channels (RGB the 3 x 3 block's columns, A the translation)."""

    layout: VatLayout
    texels: np.ndarray
    joint_count: int
    minimum: np.ndarray  # (4,) float64
    maximum: np.ndarray


def encode_joints(matrices: np.ndarray, used: np.ndarray | None = None, max_width: int = MAX_WIDTH) -> JointTexture:
    """matrices (F, J, 3, 4) float skinning matrices per pose frame and joint -> JointTexture. used: (J,) bool,
    the joints some vertex weighs; the others are written as the identity, which no shader reads and which
    keeps them from stretching the channels' ranges."""
    matrices = np.asarray(matrices, dtype=np.float64)
    if matrices.ndim != 4 or matrices.shape[2:] != (3, 4) or 0 in matrices.shape[:2]:
        raise ValueError(f"matrices must be (F, J, 3, 4) with F, J > 0, got {matrices.shape}")
    frame_count, joint_count = matrices.shape[:2]
    if used is not None:
        matrices = np.where(np.asarray(used, dtype=bool)[None, :, None, None], matrices, np.eye(3, 4))
    rows = matrices.reshape(frame_count, joint_count * JOINT_ROWS, 4)
    low, high = rows.reshape(-1, 4).min(axis=0), rows.reshape(-1, 4).max(axis=0)
    extent = high - low
    scale = np.divide(UNORM16_MAX, extent, out=np.zeros(4), where=extent > 0)
    layout = vat_layout(joint_count * JOINT_ROWS, frame_count, max_width)
    return JointTexture(layout, _place(np.rint((rows - low) * scale).astype(np.uint16), layout), joint_count, low, high)


def decode_joints(texture: JointTexture) -> np.ndarray:
    """JointTexture -> (F, J, 3, 4) float64 matrices, as the shaders decode them."""
    rows = texture.minimum + _unplace(texture.texels, texture.layout).astype(np.float64) / UNORM16_MAX * (texture.maximum - texture.minimum)
    return rows.reshape(texture.layout.frame_count, texture.joint_count, JOINT_ROWS, 4)


def play_skin(skin: SkinTexture, joints: JointTexture, frames: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The numpy twin of the shaders' skinning (for tests and the export's error figure): (K,) pose frames
    (every one when None) -> positions (K, V, 3) metres and unit normals (K, V, 3), from the two textures'
    decoded texels."""
    rest, rest_normals, joint_of, weights = decode_skin(skin)
    matrices = decode_joints(joints)
    frames = np.arange(matrices.shape[0]) if frames is None else np.asarray(frames, dtype=np.int64)
    positions, normals = [], []
    for frame in frames:
        blended = np.einsum("vk,vkij->vij", weights, matrices[frame][joint_of])  # (V, 3, 4)
        positions.append(np.einsum("vij,vj->vi", blended[..., :3], rest) + blended[..., 3])
        turned = np.einsum("vij,vj->vi", blended[..., :3], rest_normals)
        normals.append(turned / np.maximum(np.linalg.norm(turned, axis=-1, keepdims=True), 1e-12))
    return np.asarray(positions), np.asarray(normals)


# A coarser LOD's vertex reads the finer LOD's texels where it is that vertex: within this distance of it in
# every frame and SHARED_NORMAL_TOLERANCE_DEG of its normal. The bundle rounds each LOD's frames to 16 bits
# within its own bounds (a CBPC's per-frame bounds): the robot's cape at LOD 1 lies 0.064 mm from its LOD 0
# vertices, a tenth of the VAT's own rounding on a body that size, far under a pixel.
SHARED_POSITION_TOLERANCE_M = 1e-4
SHARED_NORMAL_TOLERANCE_DEG = 1.0


def shared_vertices(fine: np.ndarray, fine_normals: np.ndarray, coarse: np.ndarray, coarse_normals: np.ndarray,
                    tolerance_m: float = SHARED_POSITION_TOLERANCE_M, tolerance_deg: float = SHARED_NORMAL_TOLERANCE_DEG) -> np.ndarray | None:
    """fine (F, V, 3), coarse (F, W, 3) positions with their unit normals alike -> (W,) int64: for each coarse
    vertex the fine vertex it is (within the tolerances in every frame; of several, the nearest), or None
    when some coarse vertex is none of them (a simplifier that moved it): then the coarse LOD keeps texels
    of its own."""
    from scipy.spatial import cKDTree

    fine, coarse = np.asarray(fine, dtype=np.float64), np.asarray(coarse, dtype=np.float64)
    if fine.ndim != 3 or coarse.ndim != 3 or fine.shape[0] != coarse.shape[0] or fine.shape[2] != 3 or coarse.shape[2] != 3:
        raise ValueError(f"fine and coarse must be (F, V, 3) over the same frames, got {fine.shape} and {coarse.shape}")
    cosine = np.cos(np.radians(tolerance_deg))
    tree = cKDTree(fine[0])
    chosen = np.empty(coarse.shape[1], dtype=np.int64)
    for vertex, candidates in enumerate(tree.query_ball_point(coarse[0], tolerance_m)):
        if not candidates:
            return None
        candidates = np.asarray(candidates)
        distance = np.linalg.norm(fine[:, candidates] - coarse[:, vertex, None], axis=-1).max(axis=0)
        turned = (np.asarray(fine_normals)[:, candidates] * np.asarray(coarse_normals)[:, vertex, None]).sum(-1).min(axis=0)
        fits = (distance <= tolerance_m) & (turned >= cosine)
        if not fits.any():
            return None
        chosen[vertex] = candidates[fits][np.argmin(distance[fits])]
    return chosen


def shared_skin_vertices(fine_rest: np.ndarray, fine_normals: np.ndarray, fine_joints: np.ndarray, fine_weights: np.ndarray,
                         coarse_rest: np.ndarray, coarse_normals: np.ndarray, coarse_joints: np.ndarray, coarse_weights: np.ndarray,
                         tolerance_deg: float = SHARED_NORMAL_TOLERANCE_DEG) -> np.ndarray | None:
    """As shared_vertices for two skins (rest positions and unit normals (V, 3), joints and weight codes (V, 4)):
    a coarse vertex is a fine one with the same rest position (float32 rounding), weights and weighted
    joints, and a rest normal within tolerance_deg; None where some coarse vertex is none."""
    from scipy.spatial import cKDTree

    fine_joints = np.where(np.asarray(fine_weights) > 0, fine_joints, 0)
    coarse_joints = np.where(np.asarray(coarse_weights) > 0, coarse_joints, 0)
    scale = max(float(np.abs(fine_rest).max(initial=0.0)), 1e-9)
    tree = cKDTree(np.asarray(fine_rest, dtype=np.float64))
    cosine = np.cos(np.radians(tolerance_deg))
    chosen = np.empty(len(coarse_rest), dtype=np.int64)
    for vertex, candidates in enumerate(tree.query_ball_point(np.asarray(coarse_rest, dtype=np.float64), 4 * np.finfo(np.float32).eps * scale)):
        fits = [c for c in candidates if (fine_joints[c] == coarse_joints[vertex]).all() and (fine_weights[c] == coarse_weights[vertex]).all()
                and float(np.dot(fine_normals[c], coarse_normals[vertex])) >= cosine]
        if not fits:
            return None
        chosen[vertex] = fits[0]
    return chosen
