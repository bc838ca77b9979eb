"""The export's engine shaders (services/crowdbake/export/shaders) compile: each GLSL file inside a
GLSL 3.30 core and a GLSL ES 3.00 program, each HLSL file inside a shader model 5 entry point, with
Khronos' glslangValidator (Debian's glslang-tools, scripts/apt-packages.txt)."""
from __future__ import annotations

import re
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
# Engine setups (docs/export.md): Unity's Custom Function file (its plain-HLSL core; the UnityTexture2D
# wrapper needs Unity's includes) and Unreal's Custom node code, wrapped in the function Unreal makes of it.
ENGINE_HLSL = {
    "unity_vat_custom_function.hlsl": "{source}\nTexture2D<float4> V; Texture2D<float4> J;\nfloat4 main(float2 uv : TEXCOORD1) : SV_Position "
    "{{ float3 p, n, q, m; CrowdbakeVatSample(uv, 1.5, V, J, float3(0, 0, 0), float3(1, 1, 1), 1, 1, 2, float4(-1, -1, -1, -2), float4(1, 1, 1, 2), "
    "float4(24, 24, 1, 0), 24, p, n); CrowdbakeToObject(p, n, float3(0, 1, 0), 0.9, q, m); return float4(q + m, 1); }}",
    "unreal_vat_custom_node.hlsl": "Texture2D<float4> VatMap; Texture2D<float4> JointMap;\n"
    "float3 CustomExpression0(float2 VatUV, float Frame, float3 BoundsMin, float3 BoundsMax, float RowsPerFrame, float Skinned, float JointRowsPerFrame, "
    "float4 JointMin, float4 JointMax, float4 Range, float RangeAfter, float3 NodeTranslation, float NodeScale, float3 LocalPosition, inout float3 Normal) "
    "{{\n{source}\n}}\nfloat4 main(float2 uv : TEXCOORD1) : SV_Position "
    "{{ float3 n = 0; float3 o = CustomExpression0(uv, 1.5, 0, 1, 1, 1, 2, -1, 1, float4(24, 24, 1, 0), 24, 0, 1, 0, n); return float4(o + n, 1); }}",
}
GODOT = SHADERS / "crowdbake_vat.gdshader"

HLSL = {
    "vat.hlsl": ("vert", "float4 main(float2 uv : TEXCOORD1) : SV_Position { float3 p, n; CbVatSample(uv, 1.5, p, n); return float4(p + n, 1); }"),
    "impostor_uv.hlsl": ("frag", "float4 main(float2 uv : TEXCOORD0) : SV_Target { float3 c; if (!CbImpostorColour(uv, int2(0, 0), 0, 0, 0, 0, c)) discard; return float4(c, 1); }"),
}


def compile_shader(tmp_path: Path, name: str, stage: str, source: str, *flags: str) -> subprocess.CompletedProcess:
    path = tmp_path / f"{name}.{stage}"
    path.write_text(source)
    # -V writes SPIR-V: into tmp_path, not the working folder (its default).
    output = ["-o", str(tmp_path / f"{name}.spv")] if "-V" in flags else []
    return subprocess.run([GLSLANG, *flags, *output, str(path)], capture_output=True, text=True, timeout=60)


@pytest.fixture(autouse=True)
def needs_glslang():
    if GLSLANG is None:
        pytest.skip("glslangValidator is not installed (apt-get install glslang-tools; scripts/setup.sh does)")


@pytest.mark.parametrize("defines", ["", "#define CB_VAT_INTEGER\n"])
@pytest.mark.parametrize("version", ["330 core", "300 es"])
@pytest.mark.parametrize("name", sorted(GLSL))
def test_glsl_compiles(tmp_path, name, version, defines):
    """Each file in both GLSL versions; vat.glsl also with its VATs bound as RGBA16UI (CB_VAT_INTEGER, WebGL2's way)."""
    stage, call = GLSL[name]
    precision = "precision highp float;\nprecision highp int;\nprecision highp sampler2DArray;\n" if version.endswith("es") else ""
    out = "out vec4 o_colour;\n" if stage == "frag" else ""
    source = f"#version {version}\n{defines}{precision}{out}{(SHADERS / name).read_text()}\nvoid main() {{ {call} }}\n"
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


@pytest.mark.parametrize("name", sorted(ENGINE_HLSL))
def test_engine_hlsl_compiles(tmp_path, name):
    source = ENGINE_HLSL[name].format(source=(SHADERS / name).read_text())
    result = compile_shader(tmp_path, name.replace(".", "_"), "vert", source, "-D", "-e", "main", "-V")
    assert result.returncode == 0, result.stdout + result.stderr


def test_godot_shader_reads_what_the_export_writes():
    """No Godot 4 binary installs here (Debian packages Godot 3, whose shading language differs), so the
    .gdshader is checked two ways: a uniform for every value of the export's `vat` block and `node` it needs,
    each naming the export.json key it is set from; and its code compiled as GLSL 3.30 by glslangValidator
    once Godot's own syntax is translated (uniform hints dropped, its built-ins declared), which catches
    type and call mistakes, Godot's language being GLSL's in these respects."""
    source = GODOT.read_text()
    assert "shader_type spatial;" in source and "void vertex()" in source
    uniforms = set(re.findall(r"^uniform \w+ (\w+)", source, re.M))
    assert {"vat_texture", "vat_joints", "bounds_min", "bounds_max", "rows_per_frame", "skinned", "joint_rows_per_frame", "joint_min", "joint_max",
            "frames_per_second", "range_first", "range_frames", "range_loop", "range_before", "range_after", "node_translation", "node_scale"} <= uniforms
    for key in ("vat.texture", "vat.joints", "vat.bounds_min", "vat.bounds_max", "vat.rows_per_frame", "vat.kind", "vat.joints.rows_per_frame",
                "vat.joints.min", "vat.joints.max", "vat.frames_per_second", "parts[].node.translation",
                "animations[].vat.first_frame", "animations[].vat.frames", "animations[].vat.loop", "animations[].vat.before_frame",
                "animations[].vat.after_frame"):
        assert key in source, key


def godot_as_glsl(source: str) -> str:
    """A .gdshader's code as a GLSL 3.30 vertex shader: shader_type / render_mode lines and uniform hints
    removed, Godot's built-ins (vertex and fragment ones alike) declared as globals."""
    body = re.sub(r"^(shader_type|render_mode) [^;]*;", "", source, flags=re.M)
    body = re.sub(r"^(uniform [^:;=]+?)\s*:[^;=]*", r"\1", body, flags=re.M)  # `: filter_nearest, ...`
    builtins = "vec3 VERTEX; vec3 NORMAL; vec2 UV; vec2 UV2; float TIME; vec3 ALBEDO; float ROUGHNESS;\n"
    return f"#version 330 core\n{builtins}{body}\nvoid main() {{ vertex(); fragment(); gl_Position = vec4(VERTEX + ALBEDO, ROUGHNESS); }}\n"


def test_godot_shader_code_compiles_as_glsl(tmp_path):
    result = compile_shader(tmp_path, "godot_vat", "vert", godot_as_glsl(GODOT.read_text()))
    assert result.returncode == 0, result.stdout + result.stderr
    # The translation is not a rubber stamp: a type mistake Godot would refuse is refused here too.
    broken = GODOT.read_text().replace("int j0 = min(int(floor(x)),", "int j0 = min(floor(x),")
    assert compile_shader(tmp_path, "godot_broken", "vert", godot_as_glsl(broken)).returncode != 0
