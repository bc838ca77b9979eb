"""Vertex-animation textures (VAT): a pose cache's positions and normals per frame as 16-bit images.

Layout (docs/export.md): one texel per vertex per frame. A frame takes `rows_per_frame` rows of
`width` texels: vertex `i` of frame `f` is texel `(x, y) = (i % width, f * rows_per_frame + i // width)`.
`width` is the vertex count, wrapped at MAX_WIDTH so the texture fits every WebGL2 device.
Unused texels at the end of a frame's last row are 0.

Encoding (unsigned normalised RGBA, A = the format's maximum on used texels):
  position: 16 bits, `q = round((p - bounds_min) / (bounds_max - bounds_min) * 65535)` per axis; decode
            `p = bounds_min + q / 65535 * (bounds_max - bounds_min)`. Error <= extent / 131070 per axis.
  normal:   8 bits, `q = round((n + 1) / 2 * 255)`; decode `n = q / 255 * 2 - 1`, then normalise.
            Error <= 1 / 255 per component before normalising (under 0.5 degree): normals only shade,
            and 8 bits take half the bytes of 16 and a third of them once compressed.
Bounds are over every frame, so one pair serves the whole cycle. An axis with zero extent (a flat
mesh) stores 0 and decodes to bounds_min exactly.

Each vertex's texel at frame 0 is given to the mesh as its second texture coordinate (TEXCOORD_1),
at the texel's centre, so an engine that reorders or splits vertices on import keeps the link.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# WebGL2 guarantees 2048-texel textures (MAX_TEXTURE_SIZE >= 2048); every desktop GPU does 8192+.
MAX_WIDTH = 2048
UNORM16_MAX = 65535
UNORM8_MAX = 255


@dataclass(frozen=True)
class VatLayout:
    """Where each vertex of each frame lives in the texture."""

    vertex_count: int
    frame_count: int
    width: int
    rows_per_frame: int

    @property
    def height(self) -> int:
        return self.frame_count * self.rows_per_frame


def vat_layout(vertex_count: int, frame_count: int, max_width: int = MAX_WIDTH) -> VatLayout:
    """The texture layout for `vertex_count` vertices over `frame_count` frames (both > 0)."""
    if vertex_count <= 0 or frame_count <= 0 or max_width <= 0:
        raise ValueError(f"vertex_count, frame_count and max_width must be positive, got {vertex_count}, {frame_count}, {max_width}")
    width = min(vertex_count, max_width)
    return VatLayout(vertex_count, frame_count, width, -(-vertex_count // width))


def vat_texcoords(layout: VatLayout) -> np.ndarray:
    """(V, 2) float32: each vertex's texel centre at frame 0, as (u, v) in [0, 1] over the whole texture."""
    index = np.arange(layout.vertex_count)
    x = index % layout.width
    y = index // layout.width
    return np.stack([(x + 0.5) / layout.width, (y + 0.5) / layout.height], axis=1).astype(np.float32)


def _place(values: np.ndarray, layout: VatLayout) -> np.ndarray:
    """(F, V, 4) uint16 or uint8 -> (H, W, 4) image in the layout, unused texels 0."""
    frames, vertices, _ = values.shape
    padded = np.zeros((frames, layout.rows_per_frame * layout.width, 4), dtype=values.dtype)
    padded[:, :vertices] = values
    return padded.reshape(layout.height, layout.width, 4)


def _unplace(image: np.ndarray, layout: VatLayout) -> np.ndarray:
    """(H, W, 4) image -> (F, V, 4) values (inverse of _place)."""
    per_frame = image.reshape(layout.frame_count, layout.rows_per_frame * layout.width, 4)
    return per_frame[:, : layout.vertex_count]


@dataclass(frozen=True)
class VertexAnimation:
    """A pose cache as two VAT images (H, W, 4), positions uint16 and normals uint8, and the bounds that
    decode positions (metres)."""

    layout: VatLayout
    positions: np.ndarray
    normals: np.ndarray
    bounds_min: np.ndarray  # (3,) float64
    bounds_max: np.ndarray

    @property
    def max_position_error(self) -> np.ndarray:
        """(3,) metres: the largest decode error per axis, half a quantisation step."""
        return (self.bounds_max - self.bounds_min) / (2 * UNORM16_MAX)


def encode_vat(positions: np.ndarray, normals: np.ndarray, max_width: int = MAX_WIDTH) -> VertexAnimation:
    """positions, normals: (F, V, 3) float, metres and unit vectors -> VertexAnimation (encoding above)."""
    positions = np.asarray(positions, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or normals.shape != positions.shape:
        raise ValueError(f"positions and normals must be (F, V, 3) alike, got {positions.shape} and {normals.shape}")
    layout = vat_layout(positions.shape[1], positions.shape[0], max_width)
    low = positions.reshape(-1, 3).min(axis=0)
    high = positions.reshape(-1, 3).max(axis=0)
    extent = high - low
    scale = np.divide(UNORM16_MAX, extent, out=np.zeros(3), where=extent > 0)
    quantised = np.rint((positions - low) * scale)
    quantised_normals = np.rint((np.clip(normals, -1.0, 1.0) + 1.0) * 0.5 * UNORM8_MAX)
    position_texels = np.concatenate([quantised, np.full(positions.shape[:2] + (1,), UNORM16_MAX)], axis=2).astype(np.uint16)
    normal_texels = np.concatenate([quantised_normals, np.full(positions.shape[:2] + (1,), UNORM8_MAX)], axis=2).astype(np.uint8)
    return VertexAnimation(layout, _place(position_texels, layout), _place(normal_texels, layout), low, high)


def decode_vat(animation: VertexAnimation) -> tuple[np.ndarray, np.ndarray]:
    """VertexAnimation -> (positions, normals), each (F, V, 3) float64; normals renormalised."""
    layout = animation.layout
    q_positions = _unplace(animation.positions, layout)[..., :3].astype(np.float64)
    q_normals = _unplace(animation.normals, layout)[..., :3].astype(np.float64)
    positions = animation.bounds_min + q_positions / UNORM16_MAX * (animation.bounds_max - animation.bounds_min)
    normals = q_normals / UNORM8_MAX * 2.0 - 1.0
    lengths = np.linalg.norm(normals, axis=-1, keepdims=True)
    return positions, normals / np.maximum(lengths, 1e-12)
