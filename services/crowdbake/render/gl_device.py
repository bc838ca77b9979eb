"""Which GL context the bake draws with, and what it is.

Under PYOPENGL_PLATFORM=egl pyrender draws on the EGL device numbered EGL_DEVICE_ID (pyrender's own
variable; it takes device 0 when unset). glvnd lists every vendor library's devices, and on a GPU server
with Mesa installed Mesa's software device (llvmpipe, marked EGL_MESA_device_software) may come first.
So the bake chooses as crowdview does (runtime/src/gl_context.cpp, --gl-device auto): EGL_DEVICE_ID when
set, else the first device that is not Mesa's software one, else the software one; and it sets
EGL_DEVICE_ID to that choice for pyrender (and the processes this one starts).

The GL strings of the context that drew the impostor maps go into the bake's reports (fidelity.json,
texture_memory.json, the summary): figures measured on llvmpipe and on a GPU are not comparable.
"""
from __future__ import annotations

import ctypes
import logging
import os
import threading
from dataclasses import dataclass
from typing import Any, Sequence

logger = logging.getLogger(__name__)

DEVICE_VARIABLE = "EGL_DEVICE_ID"  # read by pyrender.offscreen.OffscreenRenderer._create
SOFTWARE_DEVICE_EXTENSION = "EGL_MESA_device_software"
# GL_RENDERER names of software rasterisers, as crowdview's is_software_renderer has them.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast")
# EGL enums pyrender's binding lacks (EGL_EXT_device_query, EGL_EXT_device_drm, EGL_NV_device_cuda).
_EGL_EXTENSIONS = 0x3055
_EGL_DRM_DEVICE_FILE_EXT = 0x3233
_EGL_CUDA_DEVICE_NV = 0x323A


@dataclass(frozen=True)
class EglDevice:
    """One device as eglQueryDevicesEXT lists it: its index in that list, a name ("/dev/dri/card0, CUDA
    device 0", "Mesa software", "unnamed") and its own extensions."""

    index: int
    name: str
    extensions: str

    @property
    def software(self) -> bool:
        return SOFTWARE_DEVICE_EXTENSION in self.extensions.split()


def device_list_text(devices: Sequence[EglDevice]) -> str:
    """ "2 EGL devices: 0 /dev/dri/card0, CUDA device 0; 1 Mesa software", for errors."""
    entries = "; ".join(f"{d.index} {d.name}" for d in devices)
    return f"{len(devices)} EGL device{'' if len(devices) == 1 else 's'}" + (f": {entries}" if devices else "")


def choose_egl_device(devices: Sequence[EglDevice], requested: str | None) -> int | None:
    """The index pyrender should draw on: `requested` (EGL_DEVICE_ID's text) when given, else the first
    hardware device, else the first device. None where EGL lists no device and none was requested (pyrender
    then uses EGL's default display). ValueError, naming the devices, for a request that is no listed index."""
    if requested is not None:
        try:
            index = int(requested)
        except ValueError:
            raise ValueError(f"{DEVICE_VARIABLE}={requested!r} is not a device index ({device_list_text(devices)})") from None
        if not 0 <= index < len(devices):
            raise ValueError(f"{DEVICE_VARIABLE}={requested!r}: no such device ({device_list_text(devices)})")
        return index
    hardware = [d.index for d in devices if not d.software]
    if hardware:
        return hardware[0]
    return devices[0].index if devices else None


def is_software_renderer(gl_renderer: str) -> bool:
    lower = gl_renderer.lower()
    return any(name in lower for name in SOFTWARE_RENDERERS)


@dataclass(frozen=True)
class GlContextInfo:
    """What a context is: the platform (PYOPENGL_PLATFORM), the EGL device (None under OSMesa) and the
    GL strings. to_json is what the reports record."""

    platform: str
    vendor: str
    renderer: str
    version: str
    device: EglDevice | None = None
    device_count: int = 0

    @property
    def software_rasteriser(self) -> bool:
        return is_software_renderer(self.renderer)

    def to_json(self) -> dict[str, Any]:
        device = None if self.device is None else {
            "index": self.device.index, "count": self.device_count, "name": self.device.name, "software": self.device.software}
        return {"platform": self.platform, "device": device, "vendor": self.vendor, "renderer": self.renderer,
                "version": self.version, "software_rasteriser": self.software_rasteriser}


def describe(gl: dict[str, Any]) -> str:
    """One line from GlContextInfo.to_json: "llvmpipe (LLVM 15.0.6, 256 bits), OpenGL 4.5 (Core Profile)
    Mesa 22.3.6, Mesa/X.org, egl device 0 of 1 (Mesa software), a software rasteriser"."""
    device = gl.get("device")
    where = gl["platform"] + ("" if device is None else f" device {device['index']} of {device['count']} ({device['name']})")
    return (f"{gl['renderer']}, OpenGL {gl['version']}, {gl['vendor']}, {where}"
            + (", a software rasteriser" if gl.get("software_rasteriser") else ""))


def current_context(device: EglDevice | None = None, device_count: int = 0) -> GlContextInfo:
    """The GL strings of the context current on this thread, on this process's platform."""
    from OpenGL.GL import GL_RENDERER, GL_VENDOR, GL_VERSION, glGetString

    def text(name: int) -> str:
        value = glGetString(name)
        return value.decode("utf-8", "replace") if value else "unknown"

    return GlContextInfo(os.environ.get("PYOPENGL_PLATFORM", ""), text(GL_VENDOR), text(GL_RENDERER), text(GL_VERSION), device,
                         device_count)


def query_egl_devices() -> list[EglDevice]:
    """Every EGL device, named as crowdview names them; [] where EGL cannot list devices."""
    import OpenGL.EGL as egl
    from pyrender.platforms import egl as pyrender_egl

    if pyrender_egl._eglQueryDevicesEXT is None or pyrender_egl._eglQueryDeviceStringEXT is None:
        return []
    query_string = pyrender_egl._eglQueryDeviceStringEXT
    query_attribute = pyrender_egl._get_egl_func("eglQueryDeviceAttribEXT", egl.EGLBoolean, pyrender_egl._EGLDeviceEXT,
                                                  egl.EGLint, ctypes.POINTER(ctypes.c_ssize_t))
    devices = []
    for index, device in enumerate(pyrender_egl.query_devices()):
        handle = device._display  # pyrender keeps the EGLDeviceEXT under this name
        extensions = (query_string(handle, _EGL_EXTENSIONS) or b"").decode("ascii", "replace")
        devices.append(EglDevice(index, _device_name(handle, extensions, query_string, query_attribute), extensions))
    return devices


def _device_name(handle, extensions: str, query_string, query_attribute) -> str:
    """The device's DRM node and CUDA index where its driver names them (crowdview's device_name)."""
    names = extensions.split()
    if SOFTWARE_DEVICE_EXTENSION in names:
        return "Mesa software"
    parts = []
    if "EGL_EXT_device_drm" in names and (drm := query_string(handle, _EGL_DRM_DEVICE_FILE_EXT)):
        parts.append(drm.decode("ascii", "replace"))
    cuda = ctypes.c_ssize_t(0)
    if "EGL_NV_device_cuda" in names and query_attribute is not None and query_attribute(handle, _EGL_CUDA_DEVICE_NV, ctypes.byref(cuda)):
        parts.append(f"CUDA device {cuda.value}")
    return ", ".join(parts) or "unnamed"


_CHOICE_LOCK = threading.Lock()
_CHOICE: tuple[EglDevice | None, int] | None = None


def egl_device_for_pyrender() -> tuple[EglDevice | None, int]:
    """Under EGL, before pyrender makes a context: the device it will draw on and how many EGL lists,
    chosen once per process (choose_egl_device) and set as EGL_DEVICE_ID when that was unset. (None, 0)
    where EGL lists no device."""
    global _CHOICE
    with _CHOICE_LOCK:
        if _CHOICE is None:
            devices = query_egl_devices()
            requested = os.environ.get(DEVICE_VARIABLE)
            index = choose_egl_device(devices, requested)
            if index is not None and requested is None:
                os.environ[DEVICE_VARIABLE] = str(index)
            _CHOICE = (None if index is None else devices[index], len(devices))
            logger.info("EGL: drawing on %s of %s", "the default display" if index is None else f"device {index}",
                        device_list_text(devices))
        return _CHOICE
