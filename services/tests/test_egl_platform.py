"""The bake under EGL (what a worker with a GPU uses) makes the same bytes as under OSMesa.

Regression: pyrender draws offscreen into a 4-sample framebuffer where the platform supports framebuffers
(EGL), and resolves it on read-back, so a triangle-id render mixed ids on the silhouette: under Mesa's
EGL the shader's maps and the exact maps disagreed on 0.5 % of texels (test_map_shader failed) and the
cycle search's edge images blurred. crowdbake.render.offscreen.single_sample_framebuffer fixes the
sample count. The platform is read when OpenGL is first imported, so each side runs in a process of its own.
The two bundles differ only where they record which platform drew them.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from egl_fixtures import TESTS, platform_env
from repo_paths import REPO_ROOT

pytestmark = pytest.mark.slow
# The bundle files that record the GL context that drew them (crowdbake.render.gl_device), and so name the platform.
RENDERER_RECORDS = ("fidelity.json", "texture_memory.json")
BAKE = """
import sys
from pathlib import Path
from baked_service import PARAMS
from crowdbake.params import BakeParams
from crowdbake.stages.runner import run_bake
from crowdbake.stages.validate import BakeInputs
sample, out = Path(sys.argv[1]), Path(sys.argv[2])
inputs = BakeInputs(sample / "character.glb", sample / "cloth.pc2", sample / "cloth.obj", sample / "textures", None,
                    "platform", "1.0.0", BakeParams.from_dict(PARAMS), created="2006-09-04T12:00:00Z")
print(run_bake(inputs, out, workers=0).bundle)
"""


def _files(folder: Path) -> dict[str, bytes]:
    return {path.relative_to(folder).as_posix(): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


def _without_renderer(files: dict[str, bytes]) -> tuple[dict[str, object], list[dict]]:
    """A bundle's files with the GL context records taken out (and the manifest's entries of the files that
    hold them), and those records: fidelity.json's and texture_memory.json's `gl_renderers`, fidelity.json's
    runtime `gl_renderer`."""
    kept: dict[str, object] = {}
    records = []
    for name, data in files.items():
        if name.endswith(RENDERER_RECORDS):
            document = json.loads(data)
            records += document.pop("gl_renderers")
            if "runtime" in document:
                records.append(document["runtime"].pop("gl_renderer"))
            kept[name] = document
        elif name.endswith("manifest.json"):
            manifest = json.loads(data)
            manifest["files"] = [entry for entry in manifest["files"] if entry["path"] not in RENDERER_RECORDS]
            kept[name] = manifest
        else:
            kept[name] = data
    return kept, records


def test_the_shader_maps_are_the_exact_maps_under_egl(egl_or_skip):
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(TESTS / "test_map_shader.py")],
                          env=platform_env("egl"), capture_output=True, text=True, timeout=600, cwd=REPO_ROOT / "services")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]


def test_a_bake_under_egl_is_the_bake_under_osmesa_to_the_byte(egl_or_skip, small_sample, tmp_path):
    bundles = {}
    for platform in ("osmesa", "egl"):
        # A bundles folder each, below a folder each: the two bundles are other bytes of one NAME/VERSION,
        # which sibling bundles folders (sharing their exports folder) refuse.
        done = subprocess.run([sys.executable, "-c", BAKE, str(small_sample), str(tmp_path / platform / "bundles")], env=platform_env(platform),
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-3000:]
        bundles[platform] = _files(tmp_path / platform / "bundles")
    assert bundles["egl"] and bundles["egl"].keys() == bundles["osmesa"].keys()
    egl, egl_records = _without_renderer(bundles["egl"])
    osmesa, osmesa_records = _without_renderer(bundles["osmesa"])
    assert [name for name in egl if egl[name] != osmesa[name]] == []
    assert {record["platform"] for record in egl_records} == {"egl"} and all(record["device"] for record in egl_records)
    assert {record["platform"] for record in osmesa_records} == {"osmesa"} and not any(record["device"] for record in osmesa_records)
