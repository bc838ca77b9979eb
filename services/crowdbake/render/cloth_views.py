"""Pictures of the cloth at chosen frames from a ring of viewpoints: the input of the edge metric (pass 2).

Dobbyn et al. 2006, section 3: "we generated images of the cloth at Fs and Fe from 5 different viewpoints
around the skirt". The cloth is drawn lit, with a light that travels with the camera, so its folds show as
shading. Lighting is two-sided: in every view each vertex normal is turned to face the camera, so a mesh
wound inwards (as simulator exports often are) shades exactly like one wound outwards, instead of flat
grey where Canny would find silhouettes and no folds; the face winding cannot change the winner. The body
is drawn in one flat colour: at Fs and Fe the body has the same pose, so its pixels and
outline are the same in both pictures and cancel in the comparison, while it still hides the cloth behind it.

All frames passed to one call share one framing (the bounding sphere of the cloth over those frames), so
a pixel is the same size in every picture of a candidate and across candidates.
"""
from __future__ import annotations

import logging
from typing import Callable

import cv2
import numpy as np

from crowdbake.geometry import vertex_normals
from crowdbake.render.offscreen import (
    Offscreen,
    bounding_sphere,
    flat_material,
    lit_material,
    orthographic_camera,
    ring_of_views,
    triangle_mesh,
    view_direction,
    view_pose,
)

import pyrender  # noqa: E402  (after offscreen, which chooses the GL platform)

logger = logging.getLogger(__name__)

DEFAULT_VIEW_COUNT = 5  # the paper's five viewpoints
DEFAULT_IMAGE_SIZE = 256  # pixels, square
# Slightly above the garment: folds on the top of a skirt and the hem both show, as in the paper's figure 1.
DEFAULT_ELEVATION_DEG = 15.0
CLOTH_COLOUR = (0.85, 0.85, 0.85)
BODY_COLOUR = (0.35, 0.35, 0.35)  # mid grey: its outline against the black background and the cloth is stable
LIGHT_INTENSITY = 3.0
AMBIENT = 0.08  # a little ambient keeps cloth seen edge-on from merging with the black background

# A render_views callable: cloth frames (N, V, 3) and body frames (N, Vb, 3) or None
# -> (N, views, H, W) uint8 grey pictures, view j of every frame taken by the same camera.
RenderViews = Callable[[np.ndarray, "np.ndarray | None"], np.ndarray]


def facing_normals(normals: np.ndarray, towards_viewer: np.ndarray) -> np.ndarray:
    """Unit normals (V, 3) flipped where they point away from the viewer: two-sided lighting for one view.

    towards_viewer: (3,) direction from the scene to an orthographic camera. A normal and its opposite give
    the same result, so reversing a mesh's winding (which negates its vertex normals) changes nothing.
    """
    normals = np.asarray(normals, dtype=np.float64)
    facing = normals @ np.asarray(towards_viewer, dtype=np.float64) < 0.0
    return np.where(facing[:, None], -normals, normals)


class ClothViewRenderer:
    """Renders cloth (+ body) frames from `views` azimuths around the garment; the pass-2 `render_views`.

    cloth_faces: (T, 3) int indices into the cloth's V points; body_faces: (Tb, 3) into the body's, or None.
    Calling it with cloth frames (N, V, 3) and body frames (N, Vb, 3) (or None) returns
    (N, views, size, size) uint8 grey images. The frames of one call share one framing.
    """

    def __init__(
        self,
        cloth_faces: np.ndarray,
        body_faces: np.ndarray | None = None,
        views: int = DEFAULT_VIEW_COUNT,
        size: int = DEFAULT_IMAGE_SIZE,
        elevation_deg: float = DEFAULT_ELEVATION_DEG,
    ):
        self.cloth_faces = np.asarray(cloth_faces, dtype=np.int64)
        if self.cloth_faces.ndim != 2 or self.cloth_faces.shape[1] != 3 or len(self.cloth_faces) == 0:
            raise ValueError(f"ClothViewRenderer: cloth_faces must be a non-empty (T, 3) array, got {self.cloth_faces.shape}")
        self.body_faces = None if body_faces is None else np.asarray(body_faces, dtype=np.int64)
        if self.body_faces is not None and (self.body_faces.ndim != 2 or self.body_faces.shape[1] != 3):
            raise ValueError(f"ClothViewRenderer: body_faces must be (Tb, 3), got {self.body_faces.shape}")
        self.views = ring_of_views(views, elevation_deg)
        self.size = int(size)

    def __call__(self, cloth_frames: np.ndarray, body_frames: np.ndarray | None = None) -> np.ndarray:
        cloth_frames = np.asarray(cloth_frames)
        if cloth_frames.ndim != 3 or cloth_frames.shape[2] != 3:
            raise ValueError(f"ClothViewRenderer: cloth frames must be (N, V, 3), got {cloth_frames.shape}")
        if len(cloth_frames) and self.cloth_faces.max() >= cloth_frames.shape[1]:
            raise ValueError(f"ClothViewRenderer: a cloth face index exceeds the {cloth_frames.shape[1]} cloth points")
        if body_frames is not None:
            body_frames = np.asarray(body_frames)
            if self.body_faces is None:
                raise ValueError("ClothViewRenderer: body frames given but the renderer has no body_faces")
            if body_frames.ndim != 3 or body_frames.shape[0] != cloth_frames.shape[0] or body_frames.shape[2] != 3:
                raise ValueError(
                    f"ClothViewRenderer: body frames {body_frames.shape} do not match cloth frames {cloth_frames.shape}"
                )
        count = cloth_frames.shape[0]
        images = np.empty((count, len(self.views), self.size, self.size), dtype=np.uint8)
        if count == 0:
            return images
        center, radius = bounding_sphere(cloth_frames)
        poses = [view_pose(center, radius, azimuth, elevation) for azimuth, elevation in self.views]
        camera = orthographic_camera(radius)
        cloth_material = lit_material(CLOTH_COLOUR)
        body_material = flat_material(BODY_COLOUR)
        with Offscreen(self.size, self.size) as offscreen:
            for i in range(count):
                scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=[AMBIENT] * 3)
                cloth = cloth_frames[i]
                normals = vertex_normals(cloth, self.cloth_faces)
                cloth_node = None
                if body_frames is not None:
                    # Flat colour: normals are not needed.
                    scene.add(triangle_mesh(body_frames[i], self.body_faces, None, body_material))
                camera_node = scene.add(camera, pose=poses[0])
                light_node = scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=LIGHT_INTENSITY), pose=poses[0])
                for j, pose in enumerate(poses):
                    if cloth_node is not None:
                        scene.remove_node(cloth_node)
                    towards_viewer = view_direction(*self.views[j])
                    cloth_node = scene.add(
                        triangle_mesh(cloth, self.cloth_faces, facing_normals(normals, towards_viewer), cloth_material)
                    )
                    scene.set_pose(camera_node, pose)
                    scene.set_pose(light_node, pose)  # a headlight: the light shines along the view
                    colour, _ = offscreen.render(scene)
                    images[i, j] = cv2.cvtColor(colour[..., :3], cv2.COLOR_RGB2GRAY)
        logger.debug("rendered %d frames x %d views at %d px", count, len(self.views), self.size)
        return images
