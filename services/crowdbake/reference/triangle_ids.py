"""Triangle-id renders through pyrender: the visibility buffer the exact float64 maps are resolved from
(crowdbake.reference.coverage, impostor_maps, mesh_reference), the oracle crowdbake.render.map_shader
is tested against.

Every triangle is drawn in one flat colour that encodes its index + 1 in 24 bits (unwelded vertices, so no
colour is interpolated between triangles), unlit (RenderFlags.FLAT), opaque, double-sided, through the
orthographic camera of crowdbake.bake.impostor_views.OrthoView, with its depth.

Under OSMesa pyrender draws straight into the context's buffer (no multisampling). Under EGL it draws
into a 4x multisampled framebuffer and resolves it, which can mix two ids on a silhouette; the inside and
depth tests of crowdbake.reference.coverage.resolve_coverage catch those texels and repair them from
their neighbours.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from crowdbake.render import offscreen  # (also chooses the GL platform before pyrender loads)
from crowdbake.bake.impostor_views import CAMERA_DISTANCE_RADII, OrthoView
from crowdbake.reference.coverage import Coverage, resolve_coverage

if TYPE_CHECKING:
    import pyrender  # imported where drawn (see crowdbake.render.offscreen), after the platform choice

# 24 bits of triangle id: RGB8, id + 1 so that 0 is the background.
MAX_TRIANGLES = (1 << 24) - 1


def triangle_id_colours(triangle_count: int) -> np.ndarray:
    """(T, 3) uint8 colours encoding triangle index + 1 in 24 bits, little end in red."""
    if not 0 < triangle_count <= MAX_TRIANGLES:
        raise ValueError(f"triangle_id_colours: 1 .. {MAX_TRIANGLES} triangles, got {triangle_count}")
    code = np.arange(1, triangle_count + 1, dtype=np.uint32)
    return np.stack([code & 255, (code >> 8) & 255, (code >> 16) & 255], axis=-1).astype(np.uint8)


def decode_triangle_ids(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3+) uint8 id image -> (H, W) int64 triangle index, -1 for the background."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] < 3 or rgb.dtype != np.uint8:
        raise ValueError(f"decode_triangle_ids: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    code = rgb[..., 0].astype(np.int64) | (rgb[..., 1].astype(np.int64) << 8) | (rgb[..., 2].astype(np.int64) << 16)
    return code - 1


def camera_pose(view: OrthoView) -> np.ndarray:
    """(4, 4) float64 camera-to-world matrix of `view` (camera looks down its -Z), as pyrender wants it."""
    pose = np.eye(4)
    eye = view.center + CAMERA_DISTANCE_RADII * view.radius * view.back
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = view.right, view.up, view.back, eye
    return pose


def clip_range(view: OrthoView) -> tuple[float, float]:
    """(znear, zfar) in metres from the eye of `view` that hold the whole bounding sphere with margin."""
    return (CAMERA_DISTANCE_RADII - 1.5) * view.radius, (CAMERA_DISTANCE_RADII + 1.5) * view.radius


def _id_mesh(positions: np.ndarray, faces: np.ndarray) -> pyrender.Mesh:
    """A pyrender mesh whose triangle k is drawn in the flat colour of id k + 1 (unwelded vertices)."""
    import pyrender

    faces = np.asarray(faces, dtype=np.int64)
    corners = np.ascontiguousarray(np.asarray(positions, dtype=np.float32)[faces].reshape(-1, 3))
    colours = np.ones((len(corners), 4), dtype=np.float32)
    # k / 255 is written back to an 8-bit buffer as exactly k (the GL conversion rounds to nearest).
    colours[:, :3] = np.repeat(triangle_id_colours(len(faces)), 3, axis=0) / np.float32(255.0)
    material = pyrender.MetallicRoughnessMaterial(
        # Floats, not ints: pyrender reads an integer list as 0..255 and would make the mesh transparent.
        baseColorFactor=[1.0, 1.0, 1.0, 1.0],
        metallicFactor=0.0,
        roughnessFactor=1.0,
        doubleSided=True,  # garments are open: their inside shows from above and below
    )
    primitive = pyrender.Primitive(positions=corners, color_0=colours, mode=pyrender.constants.GLTF.TRIANGLES, material=material)
    return pyrender.Mesh(primitives=[primitive])


def eye_depth(pyrender_depth: np.ndarray, znear: float, zfar: float) -> np.ndarray:
    """Eye-space depth (metres along the view axis) from pyrender's depth image of an orthographic camera.

    pyrender linearises depth with the perspective formula 2nf / (f + n - z (f - n)) whatever the camera;
    undo it to get NDC z back, then apply the orthographic mapping n + (z + 1) / 2 · (f - n). 0 stays 0.
    """
    depth = np.asarray(pyrender_depth, dtype=np.float64)
    drawn = depth > 0
    ndc = np.zeros_like(depth)
    ndc[drawn] = (zfar + znear - 2.0 * znear * zfar / depth[drawn]) / (zfar - znear)
    return np.where(drawn, znear + (ndc + 1.0) * 0.5 * (zfar - znear), 0.0)


@dataclass(frozen=True)
class TriangleIdImage:
    """One rendered view: triangle ids (H, W) int64 (-1 = background) and eye depth (H, W) float64."""

    ids: np.ndarray
    depth: np.ndarray


class TriangleIdRenderer:
    """Renders triangle-id images of square size² views; one GL context, reused for many views and meshes.

        with TriangleIdRenderer(128) as renderer:
            renderer.set_mesh(positions, faces)
            image = renderer.render(view)
    """

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"TriangleIdRenderer: size must be positive, got {size}")
        import pyrender

        self.size = int(size)
        self._offscreen = offscreen.Offscreen(self.size, self.size)
        self._open = False
        self._scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.0, 0.0, 0.0])
        self._mesh_node: pyrender.Node | None = None
        self._camera_node: pyrender.Node | None = None

    def __enter__(self) -> "TriangleIdRenderer":
        self._offscreen.__enter__()
        self._open = True
        return self

    def __exit__(self, *exc_info) -> None:
        self._offscreen.close()
        self._open = False

    def set_mesh(self, positions: np.ndarray, faces: np.ndarray) -> None:
        """Replace the mesh: positions (V, 3) model space, faces (T, 3) int (all parts concatenated)."""
        if self._mesh_node is not None:
            self._scene.remove_node(self._mesh_node)
        self._mesh_node = self._scene.add(_id_mesh(positions, faces))

    def render(self, view: OrthoView) -> TriangleIdImage:
        """The id and depth images of `view` (its size must be this renderer's)."""
        if not self._open:
            raise RuntimeError("TriangleIdRenderer.render called outside its `with` block")
        if self._mesh_node is None:
            raise RuntimeError("TriangleIdRenderer.render called before set_mesh")
        if view.size != self.size:
            raise ValueError(f"TriangleIdRenderer: view is {view.size}², renderer {self.size}²")
        import pyrender

        znear, zfar = clip_range(view)
        camera = pyrender.OrthographicCamera(xmag=view.radius, ymag=view.radius, znear=znear, zfar=zfar)
        if self._camera_node is not None:
            self._scene.remove_node(self._camera_node)
        self._camera_node = self._scene.add(camera, pose=camera_pose(view))
        colour, depth = self._offscreen.render(self._scene, flags=pyrender.RenderFlags.FLAT)
        return TriangleIdImage(decode_triangle_ids(colour), eye_depth(depth, znear, zfar))

    def coverage(self, view: OrthoView, positions: np.ndarray, faces: np.ndarray) -> Coverage:
        """Render `view` of the current mesh (which must be positions/faces) and resolve exact coverage."""
        image = self.render(view)
        return resolve_coverage(view, image.ids, positions, faces, image.depth)
