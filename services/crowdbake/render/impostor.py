"""The impostor bake's GL, with pyrender's context (OSMesa by default, EGL selectable).

Two kinds of drawing share one context per view size (VisibilityRenderer):

- the map shader (crowdbake.render.map_shader): every view of a task's normal, UV, detail and surface
  maps drawn, already encoded, in one pass (shader_maps), and the fidelity references shaded per sample
  and box-filtered (shader_references). This is what the bake draws with.
- a visibility buffer through pyrender: every triangle drawn in one flat colour that encodes its index
  + 1 in 24 bits (unwelded vertices, so no colour is interpolated between triangles), unlit
  (RenderFlags.FLAT), opaque, double-sided, through the orthographic camera of
  crowdbake.bake.impostor_views.OrthoView, with its depth (render, coverage). crowdbake.bake.reference.impostor_maps
  turns that into the exact float64 maps and crowdbake.bake.fidelity into the exact references that
  the shader is tested against.

Under OSMesa pyrender draws straight into the context's buffer (no multisampling). Under EGL it draws
into a 4x multisampled framebuffer and resolves it, which can mix two ids on a silhouette; the inside and
depth tests of resolve_coverage catch those texels and repair them from their neighbours. The map
shader's framebuffer is never multisampled.
"""
from __future__ import annotations

import atexit
import logging
import os
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from crowdbake.render import offscreen  # (also chooses the GL platform before pyrender loads)
from crowdbake.bake import impostor_views
from crowdbake.bake.impostor_views import Coverage, OrthoView
from crowdbake.render import map_shader
from crowdbake.render.map_shader import MapShader, ShaderMaps
from crowdbake.render.runtime_shader import RuntimeAtlas, RuntimeImpostorShader, RuntimePicture, map_texels

if TYPE_CHECKING:
    import pyrender  # imported where drawn (see crowdbake.render.offscreen), after the platform choice

logger = logging.getLogger(__name__)


def _id_mesh(positions: np.ndarray, faces: np.ndarray) -> pyrender.Mesh:
    """A pyrender mesh whose triangle k is drawn in the flat colour of id k + 1 (unwelded vertices)."""
    import pyrender

    faces = np.asarray(faces, dtype=np.int64)
    corners = np.ascontiguousarray(np.asarray(positions, dtype=np.float32)[faces].reshape(-1, 3))
    colours = np.ones((len(corners), 4), dtype=np.float32)
    # k / 255 is written back to an 8-bit buffer as exactly k (the GL conversion rounds to nearest).
    colours[:, :3] = np.repeat(impostor_views.triangle_id_colours(len(faces)), 3, axis=0) / np.float32(255.0)
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
class VisibilityImage:
    """One rendered view: triangle ids (H, W) int64 (-1 = background) and eye depth (H, W) float64."""

    ids: np.ndarray
    depth: np.ndarray


class VisibilityRenderer:
    """Renders triangle-id images of square size² views; one GL context, reused for many views and meshes.

        with VisibilityRenderer(128) as renderer:
            renderer.set_mesh(positions, faces)
            image = renderer.render(view)
    """

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"VisibilityRenderer: size must be positive, got {size}")
        import pyrender

        self.size = int(size)
        # The GL context is offscreen.Offscreen's: one place creates and deletes pyrender contexts.
        self._offscreen = offscreen.Offscreen(self.size, self.size)
        self._open = False
        self._scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.0, 0.0, 0.0])
        self._mesh_node: pyrender.Node | None = None
        self._camera_node: pyrender.Node | None = None
        self._triangle_count = 0
        self._shaders: dict[tuple[int, str], MapShader] = {}  # by (view size, pass)
        self._runtime_shader: RuntimeImpostorShader | None = None

    def __enter__(self) -> "VisibilityRenderer":
        self._offscreen.__enter__()
        self._open = True
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        shaders = [*self._shaders.values(), *filter(None, [self._runtime_shader])]
        if shaders and self._open:
            with self._offscreen.current(setup=True):
                for shader in shaders:
                    shader.delete()
        self._shaders, self._runtime_shader = {}, None
        self._offscreen.close()
        self._open = False

    @property
    def gl(self) -> offscreen.GlContextInfo:
        """What this renderer's context is (crowdbake.render.gl_device), for the reports."""
        if self._offscreen.gl is None:
            raise RuntimeError("VisibilityRenderer.gl read outside its `with` block")
        return self._offscreen.gl

    def _shader(self, size: int, shader_pass) -> MapShader:
        """This context's MapShader of `shader_pass` for views of `size`² (the context must be current)."""
        key = (int(size), shader_pass.name)
        if key not in self._shaders:
            self._shaders[key] = MapShader(size, shader_pass)
        return self._shaders[key]

    def shader_maps(self, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray,
                    next_positions: np.ndarray, faces: np.ndarray, triangle_material: np.ndarray,
                    diffuse: list[np.ndarray]) -> ShaderMaps:
        """The impostor maps of every view of a mesh, drawn by crowdbake.render.map_shader in this renderer's
        context (views of one size, any size; arguments as map_shader.MapShader.draw). Independent of
        set_mesh: the mesh is given here."""
        if not self._open:
            raise RuntimeError("VisibilityRenderer.shader_maps called outside its `with` block")
        with self._offscreen.current():
            shader = self._shader(views[0].size if views else self.size, map_shader.MAPS)
            return map_shader.draw_maps(shader, views, positions, normals, uvs, next_positions, faces, triangle_material, diffuse)

    def shader_references(self, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray,
                          faces: np.ndarray, triangle_material: np.ndarray, diffuse: list[np.ndarray], outfit_row: np.ndarray,
                          supersample: int, with_coverage: bool = False) -> np.ndarray:
        """The fidelity stage's mesh references of `views` (size S · supersample), (V, S, S, 3) float32
        ((V, S, S, 4) with_coverage): crowdbake.render.map_shader.draw_references in this renderer's context."""
        if not self._open:
            raise RuntimeError("VisibilityRenderer.shader_references called outside its `with` block")
        with self._offscreen.current():
            shader = self._shader(views[0].size if views else self.size, map_shader.REFERENCE)
            return map_shader.draw_references(shader, views, positions, normals, uvs, faces, triangle_material, diffuse, outfit_row,
                                              supersample, with_coverage)

    def runtime_impostors(self, atlas: RuntimeAtlas, pictures: list[RuntimePicture]) -> np.ndarray:
        """crowdview's impostor shader's pictures of `atlas` (crowdbake.render.runtime_shader), drawn in this
        renderer's context: (N, S, S, 3) float32."""
        if not self._open:
            raise RuntimeError("VisibilityRenderer.runtime_impostors called outside its `with` block")
        maps = map_texels(atlas, pictures)  # the CPU's decoding, outside the render's seconds
        with self._offscreen.current():
            if self._runtime_shader is None:
                self._runtime_shader = RuntimeImpostorShader()
            return self._runtime_shader.draw(atlas, pictures, maps)

    def set_mesh(self, positions: np.ndarray, faces: np.ndarray) -> None:
        """Replace the mesh: positions (V, 3) model space, faces (T, 3) int (all parts concatenated)."""
        if self._mesh_node is not None:
            self._scene.remove_node(self._mesh_node)
        self._mesh_node = self._scene.add(_id_mesh(positions, faces))
        self._triangle_count = len(faces)

    def render(self, view: OrthoView) -> VisibilityImage:
        """The id and depth images of `view` (its size must be this renderer's)."""
        if not self._open:
            raise RuntimeError("VisibilityRenderer.render called outside its `with` block")
        if self._mesh_node is None:
            raise RuntimeError("VisibilityRenderer.render called before set_mesh")
        if view.size != self.size:
            raise ValueError(f"VisibilityRenderer: view is {view.size}², renderer {self.size}²")
        import pyrender

        znear, zfar = view.clip_range
        camera = pyrender.OrthographicCamera(xmag=view.radius, ymag=view.radius, znear=znear, zfar=zfar)
        if self._camera_node is not None:
            self._scene.remove_node(self._camera_node)
        self._camera_node = self._scene.add(camera, pose=view.camera_pose())
        colour, depth = self._offscreen.render(self._scene, flags=pyrender.RenderFlags.FLAT)
        return VisibilityImage(impostor_views.decode_triangle_ids(colour), eye_depth(depth, znear, zfar))

    def coverage(self, view: OrthoView, positions: np.ndarray, faces: np.ndarray) -> Coverage:
        """Render `view` of the current mesh (which must be positions/faces) and resolve exact coverage."""
        image = self.render(view)
        return impostor_views.resolve_coverage(view, image.ids, positions, faces, image.depth)


_SHARED: dict[tuple[int, int], VisibilityRenderer] = {}


def shared_renderer(size: int) -> VisibilityRenderer:
    """An open VisibilityRenderer of `size`² kept for the life of this process (and thread).

    Creating a GL context, compiling pyrender's shaders and tearing it all down again (pyrender runs the
    garbage collector on delete) costs about a quarter of a second under OSMesa: more than rendering a
    whole ring of views. Impostor tasks running one after another in a worker reuse one context instead.
    Closed at exit.
    """
    key = (threading.get_ident(), int(size))
    renderer = _SHARED.get(key)
    if renderer is None:
        renderer = VisibilityRenderer(size).__enter__()
        _SHARED[key] = renderer
    return renderer


def _forget_shared() -> None:
    """In a forked child: drop the parent's renderers unclosed. Their GL contexts belong to the parent (the
    child has none of OSMesa's rasteriser threads); the child creates its own on first use."""
    _SHARED.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_shared)


@atexit.register
def _close_shared() -> None:
    while _SHARED:
        _, renderer = _SHARED.popitem()
        try:
            renderer.close()
        except Exception:  # noqa: BLE001 - the GL library may already be gone at interpreter exit
            logger.debug("closing a shared renderer at exit failed", exc_info=True)
