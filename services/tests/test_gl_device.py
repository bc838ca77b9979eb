"""Which EGL device the bake draws on (crowdbake.render.gl_device), as crowdview chooses: EGL_DEVICE_ID
when set, else a hardware device before Mesa's software one; and the GL context its reports record.

The choice is tested on made-up device lists (a GPU server lists Mesa's software device beside the GPU's);
the context on this machine's own OSMesa and, in a process of its own, its EGL."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from crowdbake.render.gl_device import EglDevice, choose_egl_device, describe, is_software_renderer
from egl_fixtures import platform_env

SOFTWARE = EglDevice(0, "Mesa software", "EGL_MESA_device_software EGL_EXT_device_drm_render_node")
GPU = EglDevice(1, "/dev/dri/card1, CUDA device 0", "EGL_NV_device_cuda EGL_EXT_device_drm")
SECOND_GPU = EglDevice(2, "/dev/dri/card2, CUDA device 1", "EGL_NV_device_cuda EGL_EXT_device_drm")


def test_a_gpu_listed_after_mesas_software_device_is_chosen():
    assert choose_egl_device([SOFTWARE, GPU, SECOND_GPU], None) == 1


def test_egl_device_id_is_honoured_even_when_it_names_the_software_device():
    assert choose_egl_device([SOFTWARE, GPU, SECOND_GPU], "2") == 2
    assert choose_egl_device([SOFTWARE, GPU], "0") == 0


def test_without_a_gpu_the_software_device_draws_and_without_devices_egl_chooses():
    assert choose_egl_device([SOFTWARE], None) == 0
    assert choose_egl_device([], None) is None


@pytest.mark.parametrize("requested, problem", [("2", ": no such device"), ("-1", ": no such device"), ("cuda:0", " is not a device index")])
def test_an_egl_device_id_that_names_no_device_is_refused_with_the_list(requested, problem):
    with pytest.raises(ValueError) as refused:
        choose_egl_device([SOFTWARE, GPU], requested)
    assert str(refused.value) == f"EGL_DEVICE_ID={requested!r}{problem} (2 EGL devices: 0 Mesa software; 1 /dev/dri/card1, CUDA device 0)"


def test_software_rasterisers_are_told_from_gpus_by_gl_renderer():
    assert is_software_renderer("llvmpipe (LLVM 15.0.6, 256 bits)") and is_software_renderer("Gallium 0.4 on softpipe")
    assert not is_software_renderer("NVIDIA H100 80GB HBM3/PCIe/SSE2")


def test_the_offscreen_context_records_its_platform_and_gl_strings():
    """This process's platform (OSMesa unless the suite runs under EGL): under OSMesa, no device and a
    software rasteriser (Mesa's OSMesa is always one)."""
    from crowdbake.render.offscreen import Offscreen

    with Offscreen(8, 8) as offscreen:
        gl = offscreen.gl.to_json()
    assert gl["platform"] == os.environ["PYOPENGL_PLATFORM"]
    assert gl["vendor"] and gl["version"] and gl["renderer"] != "unknown"
    if gl["platform"] == "osmesa":
        assert gl["device"] is None and gl["software_rasteriser"] and "Mesa" in gl["version"]
        assert describe(gl).endswith(", osmesa, a software rasteriser")


EGL_TRIANGLE = """
import json, os
import numpy as np
import pyrender
from crowdbake.render import gl_device, offscreen

scene = pyrender.Scene(bg_color=[0, 0, 0, 1])
scene.add(offscreen.triangle_mesh(np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]), None,
                                  offscreen.lit_material([1, 0, 0])))
scene.add(offscreen.orthographic_camera(1.5), pose=offscreen.view_pose([0, 0, 0], 1.5, 0, 0))
with offscreen.Offscreen(32, 32) as renderer:
    colour, _ = renderer.render(scene, flags=pyrender.RenderFlags.FLAT)
    gl = renderer.gl.to_json()
listed = [d.index for d in gl_device.query_egl_devices()]
print(json.dumps({"gl": gl, "red_pixels": int((colour[..., 0] > 200).sum()), "EGL_DEVICE_ID": os.environ.get("EGL_DEVICE_ID"),
                  "listed": listed}))
"""


def test_under_egl_a_render_works_on_the_chosen_device_and_records_it(egl_or_skip):
    done = subprocess.run([sys.executable, "-c", EGL_TRIANGLE], env=platform_env("egl", EGL_DEVICE_ID=""), capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    gl = result["gl"]
    assert result["red_pixels"] > 150  # the triangle covers a fifth of the 32² view (area 2 of 3.15²)
    assert gl["platform"] == "egl" and gl["device"] is not None
    # EGL_DEVICE_ID was unset: the bake chose, and told pyrender through it.
    assert result["EGL_DEVICE_ID"] == str(gl["device"]["index"]) and gl["device"]["count"] == len(result["listed"])
    if gl["device"]["software"]:  # Mesa's EGL alone (this machine): llvmpipe, and no GPU was passed over
        assert gl["device"]["name"] == "Mesa software" and gl["software_rasteriser"]


def test_under_egl_an_egl_device_id_beyond_the_list_stops_naming_the_devices(egl_or_skip):
    done = subprocess.run([sys.executable, "-c", EGL_TRIANGLE], env=platform_env("egl", EGL_DEVICE_ID="99"), capture_output=True,
                          text=True, timeout=120)
    assert done.returncode != 0
    assert "ValueError: EGL_DEVICE_ID='99': no such device (" in done.stderr
