"""Offscreen rendering with pyrender: cameras that look at a box, flat and lit materials, one reusable renderer.

Shared by every bake step that needs pictures (the cycle search's edge images, the impostor views).

Conventions (those of glTF and pyrender): right-handed, +Y up, a camera looks down its own -Z axis,
poses are camera-to-world (4, 4) float64 matrices. Azimuth 0 puts the camera on the +Z side of the target
(in front of a glTF character, which faces +Z); azimuth grows counter-clockwise seen from above, so 90
degrees is the +X side. Elevation is positive above the target.

The GL platform is chosen by PYOPENGL_PLATFORM, read when OpenGL is first imported: we default it to
"osmesa" (software, runs on any worker) and leave any value the caller set alone, so "egl" selects a GPU
(the device: crowdbake.render.gl_device). Each Offscreen knows its context's GL strings (`gl`), which the
bake's reports record.
pyrender (with trimesh and most of scipy behind it: seconds of start-up) is imported by the functions that
draw, not by this module, so that processes that never render (the API, pack-only workers, `--help`)
do not pay for it.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, Sequence

import numpy as np

from crowdbake.render import gl_device
from crowdbake.render.gl_device import GlContextInfo

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

if TYPE_CHECKING:
    import pyrender

logger = logging.getLogger(__name__)

# Ortho cameras sit this many bounding radii from the target: far enough that znear never clips the box.
CAMERA_DISTANCE_RADII = 3.0
# Margin added around the bounding sphere in the image, as a fraction of the radius, so silhouettes
# never touch the border (Canny would otherwise see the image edge as part of the outline).
FRAME_MARGIN = 0.05
# Below this length an up vector is treated as parallel to the viewing direction.
_PARALLEL_TOLERANCE = 1e-9


@dataclass
class RenderTimings:
    """Seconds spent inside the GL renderer: `seconds` in render calls (draw and read-back) over `renders`
    calls, `setup_seconds` creating and deleting contexts (shader compilation included)."""

    seconds: float = 0.0
    renders: int = 0
    setup_seconds: float = 0.0

    def minus(self, earlier: "RenderTimings") -> "RenderTimings":
        return RenderTimings(self.seconds - earlier.seconds, self.renders - earlier.renders, self.setup_seconds - earlier.setup_seconds)


# Every GL call of the bake goes through Offscreen (cycle views, impostor views, fidelity references), which
# adds its seconds here: a process-wide total a runner reads before and after a stage (render_timings, or
# the timed_renders context manager). A lock, because a worker may render from several threads.
_TOTALS = RenderTimings()
_TOTALS_LOCK = threading.Lock()


def _add_time(seconds: float = 0.0, renders: int = 0, setup_seconds: float = 0.0) -> None:
    with _TOTALS_LOCK:
        _TOTALS.seconds += seconds
        _TOTALS.renders += renders
        _TOTALS.setup_seconds += setup_seconds


def render_timings() -> RenderTimings:
    """A copy of this process's running totals of time inside the renderer."""
    with _TOTALS_LOCK:
        return RenderTimings(_TOTALS.seconds, _TOTALS.renders, _TOTALS.setup_seconds)


@contextmanager
def timed_renders() -> Iterator[RenderTimings]:
    """Measure the renderer's time inside a `with` block (this process, every thread):

        with timed_renders() as gl:
            stage_impostor_views(work, task)
        timings["render_s"] = gl.seconds

    The yielded RenderTimings is filled in when the block ends.
    """
    before = render_timings()
    result = RenderTimings()
    try:
        yield result
    finally:
        delta = render_timings().minus(before)
        result.seconds, result.renders, result.setup_seconds = delta.seconds, delta.renders, delta.setup_seconds


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose (4, 4) float64 for a camera at `eye` looking at `target`.

    eye, target, up: (3,) in world units. When `up` is parallel to the viewing direction (looking straight
    down or up) the world Z axis is used as up instead, so the pose is always a proper rotation.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    forward = target - eye
    distance = np.linalg.norm(forward)
    if distance < _PARALLEL_TOLERANCE:
        raise ValueError("look_at: eye and target coincide")
    back = -forward / distance  # the camera's +Z points away from what it looks at
    right = np.cross(up, back)
    if np.linalg.norm(right) < _PARALLEL_TOLERANCE:
        right = np.cross(np.array([0.0, 0.0, 1.0]), back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    pose = np.eye(4)
    pose[:3, 0] = right
    pose[:3, 1] = true_up
    pose[:3, 2] = back
    pose[:3, 3] = eye
    return pose


def view_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit (3,) vector from the target towards the camera for the given azimuth/elevation (degrees)."""
    azimuth = np.radians(azimuth_deg)
    elevation = np.radians(elevation_deg)
    return np.array(
        [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
    )


def view_pose(
    center: Sequence[float], radius: float, azimuth_deg: float, elevation_deg: float
) -> np.ndarray:
    """Camera-to-world pose (4, 4) looking at `center` from `CAMERA_DISTANCE_RADII * radius` away.

    center: (3,) world units; radius: bounding radius of what is looked at (world units, > 0).
    """
    if not radius > 0:
        raise ValueError(f"view_pose: radius must be positive, got {radius}")
    center = np.asarray(center, dtype=np.float64).reshape(3)
    eye = center + CAMERA_DISTANCE_RADII * radius * view_direction(azimuth_deg, elevation_deg)
    return look_at(eye, center)


def ring_of_views(count: int, elevation_deg: float = 0.0, start_azimuth_deg: float = 0.0) -> list[tuple[float, float]]:
    """`count` (azimuth, elevation) pairs in degrees, evenly spaced around the vertical axis."""
    if count < 1:
        raise ValueError(f"ring_of_views: count must be at least 1, got {count}")
    return [(start_azimuth_deg + 360.0 * i / count, elevation_deg) for i in range(count)]


def bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Center (3,) and radius of a sphere around (..., 3) points: the box center and half its diagonal.

    Not the minimal sphere, but stable (it depends only on the extremes) and cheap.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0 or not np.all(np.isfinite(points)):
        raise ValueError("bounding_sphere: points must be a non-empty array of finite values")
    low, high = points.min(axis=0), points.max(axis=0)
    center = 0.5 * (low + high)
    radius = 0.5 * float(np.linalg.norm(high - low))
    return center, max(radius, _PARALLEL_TOLERANCE)


def orthographic_camera(radius: float, aspect: float = 1.0) -> pyrender.OrthographicCamera:
    """Orthographic camera that frames a sphere of `radius` (plus FRAME_MARGIN) seen from a `view_pose`.

    aspect: width / height of the image. Orthographic, so a pixel is the same world size everywhere in the
    view, which makes edge distances in pixels comparable across the image and between frames.
    """
    import pyrender

    half_height = radius * (1.0 + FRAME_MARGIN)
    half_width = half_height * aspect
    if aspect < 1.0:  # keep the whole sphere inside the narrower dimension
        half_width, half_height = half_height, half_height / aspect
    return pyrender.OrthographicCamera(
        xmag=half_width,
        ymag=half_height,
        znear=max(radius * (CAMERA_DISTANCE_RADII - 1.5), 1e-4),
        zfar=radius * (CAMERA_DISTANCE_RADII + 1.5),
    )


def flat_material(rgb: Sequence[float], double_sided: bool = True) -> pyrender.MetallicRoughnessMaterial:
    """A material drawn in one constant colour whatever the lights: emissive, with a black metallic base.

    A black metal has neither a diffuse term nor a specular one (F0 is the base colour), so the shaded
    colour is exactly the emissive `rgb` (each in [0, 1]).
    """
    import pyrender

    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[0.0, 0.0, 0.0, 1.0],
        metallicFactor=1.0,
        roughnessFactor=1.0,
        emissiveFactor=list(rgb)[:3],
        doubleSided=double_sided,
    )


def lit_material(rgb: Sequence[float], double_sided: bool = True) -> pyrender.MetallicRoughnessMaterial:
    """A matte (rough dielectric) material whose shading shows the surface's shape: folds, creases."""
    import pyrender

    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[*list(rgb)[:3], 1.0],
        metallicFactor=0.0,
        roughnessFactor=1.0,
        doubleSided=double_sided,
    )


def triangle_mesh(
    positions: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None,
    material: pyrender.Material,
) -> pyrender.Mesh:
    """A pyrender mesh from (V, 3) positions, (T, 3) integer faces and optional (V, 3) vertex normals."""
    import pyrender

    positions = np.ascontiguousarray(positions, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    primitive = pyrender.Primitive(
        positions=positions,
        normals=None if normals is None else np.ascontiguousarray(normals, dtype=np.float32),
        indices=faces,
        material=material,
        mode=pyrender.constants.GLTF.TRIANGLES,
    )
    return pyrender.Mesh(primitives=[primitive])


def single_sample_framebuffer(offscreen: "pyrender.OffscreenRenderer") -> None:
    """Make pyrender draw into a single-sample framebuffer where it draws into one of its own (EGL), as it
    draws into OSMesa's buffer: the bake's pictures must be the same on every platform.

    pyrender allocates its offscreen framebuffer with 4 samples (RenderFlags.OFFSCREEN, used where the
    platform supports framebuffers) and resolves it on read-back, so a triangle-id render mixes ids on the
    silhouette and the edge images blur: under EGL 0.5 % of an id render's texels differed from OSMesa's.
    Its sample count has no public setting: the framebuffer is made here as pyrender would make it, and its
    "multisample" renderbuffers re-specified with one sample (the read-back's blit then copies)."""
    renderer = offscreen._renderer
    if not offscreen._platform.supports_framebuffers():
        return  # OSMesa: pyrender draws into the context's own single-sample buffer
    from OpenGL.GL import GL_DEPTH_COMPONENT24, GL_RENDERBUFFER, GL_RGBA, glBindRenderbuffer, glRenderbufferStorage

    offscreen._platform.make_current()
    renderer._configure_main_framebuffer()
    for buffer, pixel_format in ((renderer._main_cb_ms, GL_RGBA), (renderer._main_db_ms, GL_DEPTH_COMPONENT24)):
        glBindRenderbuffer(GL_RENDERBUFFER, buffer)
        glRenderbufferStorage(GL_RENDERBUFFER, pixel_format, renderer.viewport_width, renderer.viewport_height)
    glBindRenderbuffer(GL_RENDERBUFFER, 0)


def one_context_program_cache():
    """A pyrender shader program cache that compiles each program once per Offscreen.

    pyrender keys its programs by the current GL context's handle object as well as by shader files and
    defines; PyOpenGL's OSMesa binding returns a new handle object on every call, so under OSMesa every
    render compiled its shaders again (about 2 ms a program, two or more programs a render) and kept every
    copy until the renderer closed. An Offscreen owns exactly one context, so files and defines suffice."""
    from pyrender.shader_program import ShaderProgramCache

    class OneContextProgramCache(ShaderProgramCache):
        def __init__(self) -> None:
            super().__init__()
            self._by_source: dict[tuple, object] = {}

        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
            key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
            program = self._by_source.get(key)
            if program is None:
                program = self._by_source[key] = super().get_program(vertex_shader, fragment_shader, geometry_shader, defines)
            return program

        def clear(self) -> None:
            super().clear()
            self._by_source = {}

    return OneContextProgramCache()


class Offscreen:
    """One offscreen GL renderer of a fixed size, reused across renders and released on exit.

    Use as a context manager:

        with Offscreen(256, 256) as offscreen:
            colour, depth = offscreen.render(scene)

    Creating a GL context is the slow part (tens of milliseconds under OSMesa), so render many
    scenes with one Offscreen rather than one Offscreen per picture.
    """

    def __init__(self, width: int, height: int):
        if width < 1 or height < 1:
            raise ValueError(f"Offscreen: size must be positive, got {width}x{height}")
        self.width = int(width)
        self.height = int(height)
        self._renderer: pyrender.OffscreenRenderer | None = None
        self.gl: GlContextInfo | None = None  # what the context is, once entered

    def __enter__(self) -> "Offscreen":
        import pyrender

        started = time.perf_counter()
        device, device_count = gl_device.egl_device_for_pyrender() if os.environ["PYOPENGL_PLATFORM"] == "egl" else (None, 0)
        self._renderer = pyrender.OffscreenRenderer(self.width, self.height)
        self._renderer._renderer._program_cache = one_context_program_cache()  # no public hook: see that function
        single_sample_framebuffer(self._renderer)
        self._renderer._platform.make_current()
        self.gl = gl_device.current_context(device, device_count)
        _add_time(setup_seconds=time.perf_counter() - started)
        logger.debug("offscreen renderer %dx%d: %s", self.width, self.height, gl_device.describe(self.gl.to_json()))
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        if self._renderer is not None:
            started = time.perf_counter()
            self._renderer.delete()
            self._renderer = None
            _add_time(setup_seconds=time.perf_counter() - started)

    @contextmanager
    def current(self, setup: bool = False) -> Iterator[None]:
        """Make this renderer's GL context current for GL calls of one's own (crowdbake.render.map_shader)
        inside the block, whose seconds count as one render (setup: as set-up time instead, for freeing
        GL objects). pyrender sets the state it needs at every render, so what the block leaves bound
        does not reach pyrender's draws."""
        if self._renderer is None:
            raise RuntimeError("Offscreen.current used outside its `with` block")
        started = time.perf_counter()
        self._renderer._platform.make_current()
        try:
            yield
        finally:
            self._renderer._platform.make_uncurrent()
            elapsed = time.perf_counter() - started
            if setup:
                _add_time(setup_seconds=elapsed)
            else:
                _add_time(seconds=elapsed, renders=1)

    def render(self, scene: "pyrender.Scene", flags: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Render `scene` through its main camera: colour (H, W, 3 or 4) uint8 and depth (H, W) float32.

        flags: pyrender.RenderFlags (0 = NONE). Depth is in world units along the view axis, 0 where
        nothing was drawn.
        """
        if self._renderer is None:
            raise RuntimeError("Offscreen.render called outside its `with` block")
        started = time.perf_counter()
        colour, depth = self._renderer.render(scene, flags=flags)
        _add_time(seconds=time.perf_counter() - started, renders=1)
        return colour, depth
