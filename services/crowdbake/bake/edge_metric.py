"""Pass 2 of the cycle search: the paper's edge metric (Dobbyn et al. 2006, section 3).

The cloth at the candidate's start frame Fs and end frame Fe is pictured from several viewpoints (see
crowdbake.render.cloth_views); each picture becomes a Canny edge image (Canny 1986), and the two edge sets
of a view are compared by their mean distance both ways (a chamfer distance read from a distance transform,
the "edge distance estimator" of the paper, after Bhat et al. 2003: folds and silhouettes are what the eye
follows). The per-view distances are summed; the candidate with the smallest sum wins.

Pure: images in, numbers and edge images out. Distances are in pixels.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

# Canny hysteresis thresholds on 8-bit intensity. The renders are a lit matte cloth on black next to a
# flat-coloured body; fold shading changes by tens of grey levels over a few pixels, so 40/100 keeps the
# folds and silhouettes while ignoring the slow shading gradients across a smooth panel.
DEFAULT_CANNY_LOW = 40
DEFAULT_CANNY_HIGH = 100
# Edge pixels further than this from any edge of the other image count as this far (pixels). Without a
# cap, one fold that exists in only one image would dominate the mean; with it, the metric reads as
# "how much of the edge structure is out of place" (Bhat et al. use a truncated distance for the same reason).
DEFAULT_TRUNCATION_PX = 10.0


@dataclass(frozen=True)
class EdgeComparison:
    """The edge distance of one candidate, with what it was computed from.

    total: sum over views of the symmetric mean edge distance (pixels).
    per_view: (views,) float64 symmetric mean distance per view (pixels).
    edges_start, edges_end: (views, H, W) bool Canny edge images at Fs and Fe.
    """

    total: float
    per_view: np.ndarray
    edges_start: np.ndarray
    edges_end: np.ndarray


def _as_grey(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(np.ascontiguousarray(image[..., :3], dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    if image.ndim != 2:
        raise ValueError(f"{name}: expected an (H, W) grey or (H, W, 3|4) colour image, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"{name}: expected uint8 pixels, got {image.dtype}")
    return np.ascontiguousarray(image)


def edge_image(image: np.ndarray, low: float = DEFAULT_CANNY_LOW, high: float = DEFAULT_CANNY_HIGH) -> np.ndarray:
    """Canny edges of an (H, W) uint8 grey (or (H, W, 3|4) RGB) image: (H, W) bool, True on edges."""
    grey = _as_grey(image, "edge_image")
    if not 0 <= low <= high:
        raise ValueError(f"edge_image: need 0 <= low <= high, got low={low}, high={high}")
    return cv2.Canny(grey, float(low), float(high), L2gradient=True) > 0


def distance_to_edges(edges: np.ndarray) -> np.ndarray:
    """(H, W) float32 Euclidean distance (pixels) from every pixel to the nearest True pixel of `edges`.

    Where `edges` has no True pixel at all the result is +inf everywhere.
    """
    edges = np.asarray(edges, dtype=bool)
    if edges.ndim != 2:
        raise ValueError(f"distance_to_edges: expected (H, W) edges, got shape {edges.shape}")
    if not edges.any():
        return np.full(edges.shape, np.inf, dtype=np.float32)
    # distanceTransform measures the distance to the nearest zero pixel, so edges become the zeros.
    background = np.where(edges, 0, 255).astype(np.uint8)
    return cv2.distanceTransform(background, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def directed_chamfer(edges_from: np.ndarray, distance_to: np.ndarray, truncation_px: float) -> float:
    """Mean over the True pixels of `edges_from` of min(distance_to, truncation_px) (pixels).

    An image without edges has nothing out of place: 0.
    """
    values = distance_to[np.asarray(edges_from, dtype=bool)]
    if values.size == 0:
        return 0.0
    return float(np.minimum(values, truncation_px).mean(dtype=np.float64))


def chamfer_distance(
    edges_a: np.ndarray, edges_b: np.ndarray, truncation_px: float = DEFAULT_TRUNCATION_PX
) -> float:
    """Symmetric truncated chamfer distance between two (H, W) bool edge images, in pixels.

    The average of the mean distance from A's edges to B's and from B's edges to A's, each pixel's distance
    capped at `truncation_px`. 0 for identical edge sets; `truncation_px` when one image has edges and the
    other has none (every edge is out of place); 0 when neither has edges.
    """
    edges_a = np.asarray(edges_a, dtype=bool)
    edges_b = np.asarray(edges_b, dtype=bool)
    if edges_a.shape != edges_b.shape or edges_a.ndim != 2:
        raise ValueError(f"chamfer_distance: need two (H, W) images of one shape, got {edges_a.shape} and {edges_b.shape}")
    if not truncation_px > 0:
        raise ValueError(f"chamfer_distance: truncation_px must be positive, got {truncation_px}")
    a_to_b = directed_chamfer(edges_a, distance_to_edges(edges_b), truncation_px)
    b_to_a = directed_chamfer(edges_b, distance_to_edges(edges_a), truncation_px)
    return 0.5 * (a_to_b + b_to_a)


def compare_views(
    images_start: Sequence[np.ndarray] | np.ndarray,
    images_end: Sequence[np.ndarray] | np.ndarray,
    canny_low: float = DEFAULT_CANNY_LOW,
    canny_high: float = DEFAULT_CANNY_HIGH,
    truncation_px: float = DEFAULT_TRUNCATION_PX,
) -> EdgeComparison:
    """The paper's pass-2 metric for one candidate: edge distance between Fs and Fe summed over the views.

    images_start, images_end: (views, H, W) uint8 grey pictures (or sequences of (H, W) / (H, W, 3) images)
    of the cloth at Fs and at Fe, view i of both taken by the same camera.
    """
    if len(images_start) != len(images_end) or len(images_start) == 0:
        raise ValueError(
            f"compare_views: need the same non-zero number of views at Fs and Fe, got {len(images_start)} and {len(images_end)}"
        )
    edges_start = np.stack([edge_image(image, canny_low, canny_high) for image in images_start])
    edges_end = np.stack([edge_image(image, canny_low, canny_high) for image in images_end])
    if edges_start.shape != edges_end.shape:
        raise ValueError(f"compare_views: Fs and Fe images differ in size: {edges_start.shape} vs {edges_end.shape}")
    per_view = np.array(
        [chamfer_distance(a, b, truncation_px) for a, b in zip(edges_start, edges_end)], dtype=np.float64
    )
    return EdgeComparison(float(per_view.sum()), per_view, edges_start, edges_end)
