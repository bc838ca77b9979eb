"""The light model every picture of a character is drawn with: the fidelity scores' mesh references and
impostor images, the numpy twin of crowdview's impostor shader, and the shaders that draw them in GL.

Lambert with an ambient term, one directional light fixed to the camera (above, to the left, in front) so
that every view is lit from the front, outfit colours by region code (SPEC.md), and no gamma.
"""
from __future__ import annotations

import numpy as np

from crowdbake.bake.impostor_views import OrthoView, sample_texture

AMBIENT = 0.3
DIFFUSE = 0.7
# Light direction in the camera's frame: towards the camera, up, and to the left (right, up, back weights).
LIGHT_IN_CAMERA = np.array([-0.4, 0.6, 0.7])


def camera_light(view: OrthoView) -> np.ndarray:
    """(3,) unit model-space direction towards the light for `view` (fixed to the camera)."""
    direction = LIGHT_IN_CAMERA[0] * view.right + LIGHT_IN_CAMERA[1] * view.up + LIGHT_IN_CAMERA[2] * view.back
    return direction / np.linalg.norm(direction)


def apply_outfit(texels: np.ndarray, outfit_row: np.ndarray) -> np.ndarray:
    """Outfit colours (SPEC.md): (N, 4) texels 0..255 (alpha = 17·region) -> (N, 3) RGB 0..1.

    Region 0 keeps the texture's colour; region r multiplies it by the outfit map's texel r.
    outfit_row: (16, 4) uint8, one row of the outfit map.
    """
    texels = np.asarray(texels, dtype=np.float64)
    regions = np.clip(np.rint(texels[:, 3] / 17.0).astype(np.int64), 0, 15)
    tint = np.asarray(outfit_row, dtype=np.float64)[regions, :3] / 255.0
    tint[regions == 0] = 1.0
    return texels[:, :3] / 255.0 * tint


def lambert(albedo: np.ndarray, normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """(N, 3) albedo 0..1 lit by a directional light: albedo · (AMBIENT + DIFFUSE · max(0, n·l))."""
    intensity = AMBIENT + DIFFUSE * np.clip(np.asarray(normals) @ np.asarray(light), 0.0, None)
    return np.clip(albedo * intensity[:, None], 0.0, 1.0)


def texels_at(uv: np.ndarray, material: np.ndarray, diffuse: list[np.ndarray]) -> np.ndarray:
    """(N, 4) float64 texels 0..255 of the diffuse textures at (N, 2) wrapped UVs, per (N,) material index."""
    texels = np.zeros((len(uv), 4), dtype=np.float64)
    for index, texture in enumerate(diffuse):
        selected = material == index
        if selected.any():
            texels[selected] = sample_texture(texture, uv[selected])
    return texels
