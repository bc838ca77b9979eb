"""The export's engine shaders (services/crowdbake/export/shaders) compile: each GLSL file inside a
GLSL 3.30 core and a GLSL ES 3.00 program, each HLSL file inside a shader model 5 entry point, with
Khronos' glslangValidator (Debian's glslang-tools, scripts/apt-packages.txt)."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

SHADERS = Path(__file__).resolve().parents[1] / "crowdbake" / "export" / "shaders"
GLSLANG = shutil.which("glslangValidator")

# file: (stage, the call a program would make)
GLSL = {
    "vat.glsl": ("vert", "vec3 p, n; cb_vat_sample(vec2(0.5), 1.5, p, n); gl_Position = vec4(p + n, 1.0);"),
    "impostor_uv.glsl": ("frag", "vec3 c; if (!cb_impostor_colour(vec2(0.5), ivec2(0), 0, 0.0, 0, 0, c)) discard; o_colour = vec4(c, 1.0);"),
}
HLSL = {
    "vat.hlsl": ("vert", "float4 main(float2 uv : TEXCOORD1) : SV_Position { float3 p, n; CbVatSample(uv, 1.5, p, n); return float4(p + n, 1); }"),
    "impostor_uv.hlsl": ("frag", "float4 main(float2 uv : TEXCOORD0) : SV_Target { float3 c; if (!CbImpostorColour(uv, int2(0, 0), 0, 0, 0, 0, c)) discard; return float4(c, 1); }"),
}


def compile_shader(tmp_path: Path, name: str, stage: str, source: str, *flags: str) -> subprocess.CompletedProcess:
    path = tmp_path / f"{name}.{stage}"
    path.write_text(source)
    return subprocess.run([GLSLANG, *flags, str(path)], capture_output=True, text=True, timeout=60)


@pytest.fixture(autouse=True)
def needs_glslang():
    if GLSLANG is None:
        pytest.skip("glslangValidator is not installed (apt-get install glslang-tools; scripts/setup.sh does)")


@pytest.mark.parametrize("version", ["330 core", "300 es"])
@pytest.mark.parametrize("name", sorted(GLSL))
def test_glsl_compiles(tmp_path, name, version):
    stage, call = GLSL[name]
    precision = "precision highp float;\nprecision highp int;\nprecision highp sampler2DArray;\n" if version.endswith("es") else ""
    out = "out vec4 o_colour;\n" if stage == "frag" else ""
    source = f"#version {version}\n{precision}{out}{(SHADERS / name).read_text()}\nvoid main() {{ {call} }}\n"
    result = compile_shader(tmp_path, name.replace(".", "_"), stage, source)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("name", sorted(HLSL))
def test_hlsl_compiles(tmp_path, name):
    stage, entry = HLSL[name]
    source = f"{(SHADERS / name).read_text()}\n{entry}\n"
    result = compile_shader(tmp_path, name.replace(".", "_"), stage, source, "-D", "-e", "main", "-V")
    assert result.returncode == 0, result.stdout + result.stderr


def test_a_broken_shader_is_refused(tmp_path):
    """The check can fail: a call with the wrong arguments does not compile."""
    source = f"#version 330 core\n{(SHADERS / 'vat.glsl').read_text()}\nvoid main() {{ cb_vat_sample(1.0); }}\n"
    assert compile_shader(tmp_path, "broken", "vert", source).returncode != 0
