"""The bake's GL context, one per view size, and the shaders drawn in it (BakeRenderer).

- the map shader (crowdbake.render.map_shader): every view of a task's normal, UV, detail and surface
  maps drawn, already encoded, in one pass (shader_maps), and the fidelity references shaded per sample
  and box-filtered (shader_references);
- crowdview's own impostor shader (crowdbake.render.runtime_shader): the pictures the pack stage scores
  (runtime_impostors).

The context is pyrender's (crowdbake.render.offscreen.Offscreen: OSMesa by default, EGL selectable); the
map shader's framebuffer is never multisampled. The exact float64 maps the shader is tested against are
drawn from triangle-id renders by a test oracle, crowdbake.reference.triangle_ids.
"""
from __future__ import annotations

import atexit
import logging
import os
import threading

import numpy as np

from crowdbake.render import offscreen  # (also chooses the GL platform before pyrender loads)
from crowdbake.bake.impostor_views import OrthoView
from crowdbake.render import map_shader
from crowdbake.render.map_shader import MapShader, ShaderMaps
from crowdbake.render.runtime_shader import RuntimeAtlas, RuntimeImpostorShader, RuntimePicture, map_texels

logger = logging.getLogger(__name__)


class BakeRenderer:
    """The bake's shaders in one GL context of size² (module docstring), reused for many views and meshes.

        with BakeRenderer(128) as renderer:
            maps = renderer.shader_maps(views, positions, normals, uvs, next_positions, faces, material, diffuse)
    """

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"BakeRenderer: size must be positive, got {size}")
        self.size = int(size)
        # The GL context is offscreen.Offscreen's: one place creates and deletes pyrender contexts.
        self._offscreen = offscreen.Offscreen(self.size, self.size)
        self._open = False
        self._shaders: dict[tuple[int, str], MapShader] = {}  # by (view size, pass)
        self._runtime_shader: RuntimeImpostorShader | None = None

    def __enter__(self) -> "BakeRenderer":
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
        context (views of one size, any size; arguments as map_shader.MapShader.draw)."""
        if not self._open:
            raise RuntimeError("BakeRenderer.shader_maps called outside its `with` block")
        with self._offscreen.current():
            shader = self._shader(views[0].size if views else self.size, map_shader.MAPS)
            return map_shader.draw_maps(shader, views, positions, normals, uvs, next_positions, faces, triangle_material, diffuse)

    def shader_references(self, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray,
                          faces: np.ndarray, triangle_material: np.ndarray, diffuse: list[np.ndarray], outfit_row: np.ndarray,
                          supersample: int, with_coverage: bool = False) -> np.ndarray:
        """The fidelity stage's mesh references of `views` (size S · supersample), (V, S, S, 3) float32
        ((V, S, S, 4) with_coverage): crowdbake.render.map_shader.draw_references in this renderer's context."""
        if not self._open:
            raise RuntimeError("BakeRenderer.shader_references called outside its `with` block")
        with self._offscreen.current():
            shader = self._shader(views[0].size if views else self.size, map_shader.REFERENCE)
            return map_shader.draw_references(shader, views, positions, normals, uvs, faces, triangle_material, diffuse, outfit_row,
                                              supersample, with_coverage)

    def shader_footprints(self, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, faces: np.ndarray,
                          triangle_material: np.ndarray, material_count: int, supersample: int) -> np.ndarray:
        """Each texel's footprint in `views` (size S · supersample), (V, S, S, 4) float32: the mean shading
        normal over its samples and, in alpha, the share of them the mesh covers (the alpha
        shader_references(..., with_coverage=True) gives; map_shader.draw_footprints)."""
        if not self._open:
            raise RuntimeError("BakeRenderer.shader_footprints called outside its `with` block")
        with self._offscreen.current():
            shader = self._shader(views[0].size if views else self.size, map_shader.FOOTPRINT)
            return map_shader.draw_footprints(shader, views, positions, normals, faces, triangle_material, material_count, supersample)

    def runtime_impostors(self, atlas: RuntimeAtlas, pictures: list[RuntimePicture]) -> np.ndarray:
        """crowdview's impostor shader's pictures of `atlas` (crowdbake.render.runtime_shader), drawn in this
        renderer's context: (N, S, S, 3) float32."""
        if not self._open:
            raise RuntimeError("BakeRenderer.runtime_impostors called outside its `with` block")
        maps = map_texels(atlas, pictures)  # the CPU's decoding, outside the render's seconds
        with self._offscreen.current():
            if self._runtime_shader is None:
                self._runtime_shader = RuntimeImpostorShader()
            return self._runtime_shader.draw(atlas, pictures, maps)


_SHARED: dict[tuple[int, int], BakeRenderer] = {}


def shared_renderer(size: int) -> BakeRenderer:
    """An open BakeRenderer of `size`² kept for the life of this process (and thread).

    Creating a GL context, compiling pyrender's shaders and tearing it all down again (pyrender runs the
    garbage collector on delete) costs about a quarter of a second under OSMesa: more than rendering a
    whole ring of views. Impostor tasks running one after another in a worker reuse one context instead.
    Closed at exit.
    """
    key = (threading.get_ident(), int(size))
    renderer = _SHARED.get(key)
    if renderer is None:
        renderer = BakeRenderer(size).__enter__()
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
