"""The export's reference VAT shader (services/crowdbake/export/shaders/vat.glsl) run, not only compiled: a
vertex program around cb_vat_sample, in the bake's GL context (OSMesa), writes each vertex's position and
normal out by transform feedback, for vertex frames and for a skin, at whole and fractional frames of a
clip and of a transition. They must be what crowdbake.export.vat decodes (its numpy twin) blended as the
glTF animation blends keys (crowdbake.export.animations.vat_shader_twin), both with the textures bound
as normalised RGBA16 and as RGBA16UI (CB_VAT_INTEGER, WebGL2's way)."""
from __future__ import annotations

import ctypes

import numpy as np
import pytest

from crowdbake.export.animations import vat_shader_twin
from crowdbake.export.vat import decode_vat, encode_joints, encode_skin, encode_vat, play_skin, vat_texcoords
from test_export_vat import angles_deg, two_bone_body

pytest.importorskip("pyrender")
from crowdbake.render import offscreen  # noqa: E402

SHADER = offscreen.__file__.rsplit("/render/", 1)[0] + "/export/shaders/vat.glsl"
# float32 arithmetic in the shader against float64 in numpy.
POSITION_TOLERANCE = 2e-5
NORMAL_DEGREES = 0.05

# A clip of 4 frames from pose frame 1, and a transition of 2 frames (pose frames 4, 5) from 0 to 2.
CLIP = {"first_frame": 1, "frames": 4, "loop": 1, "before_frame": 4, "after_frame": 1}
TRANSITION = {"first_frame": 4, "frames": 2, "loop": 0, "before_frame": 0, "after_frame": 2}
FRAMES = [0.0, 1.0, 2.5, 3.75, 5.2, -0.4]


def program_source(integer: bool) -> str:
    return ("#version 330 core\n" + ("#define CB_VAT_INTEGER\n" if integer else "") + open(SHADER).read() +
            "\nlayout(location = 0) in vec2 vat_uv;\nuniform float frame;\nout vec3 played_position;\nout vec3 played_normal;\n"
            "void main() { cb_vat_sample(vat_uv, frame, played_position, played_normal); gl_Position = vec4(0.0); }\n")


def run_shader(textures: dict[str, np.ndarray], uniforms: dict, texcoords: np.ndarray, frames: list[float], integer: bool) -> tuple[np.ndarray, np.ndarray]:
    """Positions and normals (len(frames), V, 3) the program writes for each vertex (texcoords (V, 2)) at each frame."""
    from OpenGL import GL
    from OpenGL.GL import shaders

    with offscreen.Offscreen(8, 8) as context, context.current():
        vertex = shaders.compileShader(program_source(integer), GL.GL_VERTEX_SHADER)
        program = GL.glCreateProgram()
        GL.glAttachShader(program, vertex)
        names = (ctypes.POINTER(ctypes.c_char) * 2)(*[ctypes.create_string_buffer(name) for name in (b"played_position", b"played_normal")])
        GL.glTransformFeedbackVaryings(program, 2, names, GL.GL_INTERLEAVED_ATTRIBS)
        GL.glLinkProgram(program)
        assert GL.glGetProgramiv(program, GL.GL_LINK_STATUS), GL.glGetProgramInfoLog(program)
        GL.glUseProgram(program)
        handles = []
        for unit, (name, texels) in enumerate(textures.items()):
            handle = int(GL.glGenTextures(1))
            handles.append(handle)
            GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
            GL.glBindTexture(GL.GL_TEXTURE_2D, handle)
            GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
            if integer:
                GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA16UI, texels.shape[1], texels.shape[0], 0, GL.GL_RGBA_INTEGER, GL.GL_UNSIGNED_SHORT, texels)
            else:
                GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA16, texels.shape[1], texels.shape[0], 0, GL.GL_RGBA, GL.GL_UNSIGNED_SHORT, texels)
            for parameter in (GL.GL_TEXTURE_MIN_FILTER, GL.GL_TEXTURE_MAG_FILTER):
                GL.glTexParameteri(GL.GL_TEXTURE_2D, parameter, GL.GL_NEAREST)
            GL.glUniform1i(GL.glGetUniformLocation(program, name), unit)
        for name, value in uniforms.items():
            location = GL.glGetUniformLocation(program, name)
            if isinstance(value, int):
                GL.glUniform1i(location, value)
            elif len(value) == 3:
                GL.glUniform3f(location, *value)
            else:
                GL.glUniform4f(location, *value)
        vao = GL.glGenVertexArrays(1)
        GL.glBindVertexArray(vao)
        coords = np.ascontiguousarray(texcoords, dtype=np.float32)
        source = GL.glGenBuffers(1)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, source)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, coords.nbytes, coords, GL.GL_STATIC_DRAW)
        GL.glEnableVertexAttribArray(0)
        GL.glVertexAttribPointer(0, 2, GL.GL_FLOAT, GL.GL_FALSE, 0, None)
        captured = GL.glGenBuffers(1)
        GL.glBindBuffer(GL.GL_TRANSFORM_FEEDBACK_BUFFER, captured)
        GL.glBufferData(GL.GL_TRANSFORM_FEEDBACK_BUFFER, len(coords) * 24, None, GL.GL_STATIC_READ)
        GL.glBindBufferBase(GL.GL_TRANSFORM_FEEDBACK_BUFFER, 0, captured)
        GL.glEnable(GL.GL_RASTERIZER_DISCARD)
        out = []
        for frame in frames:
            GL.glUniform1f(GL.glGetUniformLocation(program, "frame"), frame)
            GL.glBeginTransformFeedback(GL.GL_POINTS)
            GL.glDrawArrays(GL.GL_POINTS, 0, len(coords))
            GL.glEndTransformFeedback()
            data = np.empty(len(coords) * 6, dtype=np.float32)
            GL.glGetBufferSubData(GL.GL_TRANSFORM_FEEDBACK_BUFFER, 0, data.nbytes, data.ctypes.data_as(ctypes.c_void_p))
            out.append(data.reshape(-1, 2, 3))
        GL.glDisable(GL.GL_RASTERIZER_DISCARD)
        GL.glDeleteBuffers(2, [source, captured])
        GL.glDeleteVertexArrays(1, [vao])
        GL.glDeleteTextures(len(handles), handles)
        GL.glDeleteProgram(program)
        GL.glDeleteShader(vertex)
    played = np.asarray(out, dtype=np.float64)
    return played[:, :, 0], played[:, :, 1]


def expected_blend(positions: np.ndarray, normals: np.ndarray, uniforms: dict) -> tuple[np.ndarray, np.ndarray]:
    """(len(FRAMES), V, 3) what the shader should give: the two keys' decoded frames, blended (normals
    normalised after)."""
    f0, f1, t = vat_shader_twin(np.array(FRAMES), uniforms)
    mixed = positions[f0] * (1 - t)[:, None, None] + positions[f1] * t[:, None, None]
    turned = normals[f0] * (1 - t)[:, None, None] + normals[f1] * t[:, None, None]
    return mixed, turned / np.linalg.norm(turned, axis=-1, keepdims=True)


def range_uniforms(played: dict) -> dict:
    return {"cb_vat_range_first": played["first_frame"], "cb_vat_range_frames": played["frames"], "cb_vat_range_loop": played["loop"],
            "cb_vat_range_before": played["before_frame"], "cb_vat_range_after": played["after_frame"]}


@pytest.mark.parametrize("integer", [False, True])
@pytest.mark.parametrize("played", [CLIP, TRANSITION], ids=["clip", "transition"])
def test_the_shader_plays_vertex_frames(played, integer):
    rng = np.random.default_rng(2)
    positions = np.cumsum(rng.normal(scale=0.05, size=(6, 40, 3)), axis=0) + rng.uniform(-1, 1, size=(1, 40, 3))
    normals = rng.normal(size=(6, 40, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    animation = encode_vat(positions, normals, max_width=16)  # 3 rows a frame: the shader's rows_per_frame is used
    uniforms = {"cb_vat_bounds_min": animation.bounds_min.tolist(), "cb_vat_bounds_max": animation.bounds_max.tolist(),
                "cb_vat_rows_per_frame": animation.layout.rows_per_frame, "cb_vat_skinned": 0, **range_uniforms(played)}
    got, got_normals = run_shader({"cb_vat_texture": animation.texels}, uniforms, vat_texcoords(animation.layout), FRAMES, integer)
    want, want_normals = expected_blend(*decode_vat(animation), played)
    assert np.abs(got - want).max() < POSITION_TOLERANCE
    assert angles_deg(got_normals, want_normals).max() < NORMAL_DEGREES


@pytest.mark.parametrize("integer", [False, True])
@pytest.mark.parametrize("played", [CLIP, TRANSITION], ids=["clip", "transition"])
def test_the_shader_skins_a_skinned_body(played, integer):
    rest, rest_normals, joints, codes, matrices = two_bone_body()
    skin = encode_skin(rest, rest_normals, joints, codes, max_width=16)
    texture = encode_joints(matrices, np.array([True, True, False]), max_width=5)
    uniforms = {"cb_vat_bounds_min": skin.bounds_min.tolist(), "cb_vat_bounds_max": skin.bounds_max.tolist(),
                "cb_vat_rows_per_frame": skin.layout.rows_per_frame, "cb_vat_skinned": 1,
                "cb_vat_joint_rows_per_frame": texture.layout.rows_per_frame, "cb_vat_joint_min": texture.minimum.tolist(),
                "cb_vat_joint_max": texture.maximum.tolist(), **range_uniforms(played)}
    got, got_normals = run_shader({"cb_vat_texture": skin.texels, "cb_vat_joints": texture.texels}, uniforms, vat_texcoords(skin.layout),
                                  FRAMES, integer)
    positions, normals = play_skin(skin, texture)
    want, want_normals = expected_blend(positions, normals, played)
    assert np.abs(got - want).max() < POSITION_TOLERANCE
    assert angles_deg(got_normals, want_normals).max() < NORMAL_DEGREES
