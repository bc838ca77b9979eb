"""The impostor maps drawn by a shader: every view of a task in one framebuffer, already encoded.

Dobbyn et al. 2006, sections 4 and 5: per viewpoint a normal map, a detail map and a UV map. The GPU
computes exactly what they need per texel: the rasteriser finds the triangle under each texel centre and
interpolates the vertex attributes there, so the fragment shader writes the maps' texels directly, in
SPEC.md's encodings ("Impostor maps"), into four integer targets:

    0 normal  (RGBA8UI):  the unit shading normal (model space) as (n + 1) / 2, flipped towards the camera
                          on a triangle seen from behind (the inside of an open skirt, drawn double-sided),
                          the face normal where the interpolated one vanishes; A = 255
    1 uv      (RGBA16UI): u, v (glTF, wrapped into [0, 1] under REPEAT) · 65535, the material index, 65535
    2 detail  (RGBA8UI):  the material's diffuse texture at (u, v): RGB bilinear between texel centres,
                          alpha the nearest texel's (region codes are labels, not blendable)
    3 surface (RGBA8UI):  crowdbake.bake.surface_maps's codes: depth along the view's back axis from the
                          bounds centre, motion of the surface point to the next baked frame along the
                          view's right and up axes; A = 255

All four are 0 where no triangle covers the texel. The views are orthographic, so the interpolation is
affine (no perspective division): a texel's values are those of the point of the triangle at its centre,
computed in float32 and rounded to the nearest code (the test oracle crowdbake.reference.impostor_maps
computes them in float64 from a triangle-id render). The framebuffer is not multisampled, so no texel
mixes two triangles on the silhouette.

Used through crowdbake.render.impostor.BakeRenderer, which owns the GL context; the impostor task
(crowdbake.stages.impostors.render_task) then fills the maps' backgrounds, in numpy.
"""
from __future__ import annotations

import ctypes
from dataclasses import dataclass
from typing import Callable

import numpy as np

from crowdbake.bake import impostor_views, shading, surface_maps
from crowdbake.bake.impostor_views import OrthoView


# The GLSL: one vertex shader, the maps pass and the reference pass (a shared fragment prelude each), and the
# box filter that averages a reference's samples per texel. Encodings as SPEC.md's "Impostor maps".
VERTEX_SHADER = """#version 330 core
in vec3 position;
in vec3 normal;
in vec2 uv;
in vec3 next_position;
in vec3 face_normal;
uniform vec3 center;
uniform vec3 right;
uniform vec3 up;
uniform vec3 back;
uniform float radius;
out vec3 v_normal;
out vec2 v_uv;
out vec3 v_surface;
flat out vec3 v_face_normal;

void main() {
    // SPEC.md's orthographic view: the square of 2 radii round the centre fills the viewport; depth along
    // back spans [-radius, radius] inside the bounds, mapped into the clip range with margin (nearer the
    // camera, i.e. larger along back, is smaller z).
    vec3 offset = position - center;
    float along = dot(offset, back);
    gl_Position = vec4(dot(offset, right) / radius, dot(offset, up) / radius, -along / (1.5 * radius), 1.0);
    vec3 moved = next_position - position;
    v_normal = normal;
    v_uv = uv;
    v_face_normal = face_normal;
    v_surface = vec3(along, dot(moved, right), dot(moved, up));
}
"""

ATTRIBUTES = (("position", 3), ("normal", 3), ("uv", 2), ("next_position", 3), ("face_normal", 3))

# What both passes' fragment shaders share: the shading normal, the wrapped UV and the diffuse texel.
FRAGMENT_COMMON = """#version 330 core
in vec3 v_normal;
in vec2 v_uv;
in vec3 v_surface;
flat in vec3 v_face_normal;
uniform vec3 back;
uniform sampler2D diffuse;

// The unit normal, flipped towards the camera where it sees the triangle's back: the side the camera
// sees decides, by the face normal (crowdbake.reference.coverage.shading_normals_at).
vec3 shading_normal() {
    float facing = dot(v_face_normal, back) < 0.0 ? -1.0 : 1.0;
    vec3 n = v_normal * facing;
    if (length(n) <= 1e-12) {
        n = v_face_normal * facing;
    }
    return normalize(n);
}

// glTF's REPEAT: coordinates inside [0, 1] are kept as they are (1 stays 1), others wrap.
vec2 wrapped_uv() {
    bvec2 outside = greaterThan(abs(v_uv - 0.5), vec2(0.5));
    return mix(v_uv, v_uv - floor(v_uv), vec2(outside));
}

// A texel of the diffuse texture under REPEAT (texelFetch does not wrap).
vec4 texel(ivec2 at, ivec2 size) {
    return texelFetch(diffuse, ivec2(mod(vec2(at), vec2(size))), 0);
}

// The diffuse texture at uv, 0..1: RGB bilinear between texel centres, by hand in float32 (a sampler's
// own filter has 8-bit weights on llvmpipe, rounding otherwise than the numpy reference); alpha the
// nearest texel's (region codes are labels, not blendable). crowdbake.bake.impostor_views.sample_texture.
vec4 diffuse_at(vec2 uv) {
    ivec2 size = textureSize(diffuse, 0);
    vec2 at = uv * vec2(size) - 0.5;
    vec2 low = floor(at);
    vec2 f = at - low;
    ivec2 corner = ivec2(low);
    vec3 rgb = texel(corner, size).rgb * (1.0 - f.x) * (1.0 - f.y) + texel(corner + ivec2(1, 0), size).rgb * f.x * (1.0 - f.y)
             + texel(corner + ivec2(0, 1), size).rgb * (1.0 - f.x) * f.y + texel(corner + ivec2(1, 1), size).rgb * f.x * f.y;
    return vec4(rgb, texel(ivec2(floor(uv * vec2(size))), size).a);
}
"""

MAPS_FRAGMENT_SHADER = FRAGMENT_COMMON + """
uniform float material;
uniform float depth_limit;
uniform float motion_limit;
layout(location = 0) out uvec4 out_normal;
layout(location = 1) out uvec4 out_uv;
layout(location = 2) out uvec4 out_detail;
layout(location = 3) out uvec4 out_surface;

// x in [0, top] rounded to the nearest integer code (SPEC.md's encodings round to nearest).
uvec4 codes(vec4 x, float top) {
    return uvec4(floor(clamp(x, 0.0, top) + 0.5));
}

void main() {
    vec2 uv = wrapped_uv();
    vec3 limits = vec3(depth_limit, motion_limit, motion_limit);
    out_normal = codes(vec4((shading_normal() + 1.0) * 127.5, 255.0), 255.0);
    out_uv = codes(vec4(uv * 65535.0, material, 65535.0), 65535.0);
    out_detail = codes(diffuse_at(uv) * 255.0, 255.0);
    out_surface = codes(vec4((clamp(v_surface, -limits, limits) + limits) / (2.0 * limits) * 255.0, 255.0), 255.0);
}
"""

# The fidelity stage's mesh reference per sample (crowdbake.reference.mesh_reference): the diffuse
# colour tinted by its region's outfit colour, lit by Lambert with an ambient term from a light fixed to
# the camera; covered samples get alpha 1.
REFERENCE_FRAGMENT_SHADER = FRAGMENT_COMMON + """
uniform vec3 light;
uniform vec3 outfit[16];
uniform float ambient;
uniform float diffuse_weight;
layout(location = 0) out vec4 out_colour;

void main() {
    vec4 sampled = diffuse_at(wrapped_uv());
    int region = int(clamp(floor(sampled.a * 255.0 / 17.0 + 0.5), 0.0, 15.0));
    vec3 tint = region == 0 ? vec3(1.0) : outfit[region];
    float intensity = ambient + diffuse_weight * max(0.0, dot(shading_normal(), light));
    out_colour = vec4(sampled.rgb * tint * intensity, 1.0);
}
"""

# Each texel's footprint: the reference pass's samples without their shading (the vertex shader, and so
# the rasterised samples, are the same), so the box filter's alpha is the reference's to the bit for less
# work a sample: what the impostor maps keep as each texel's share of the character. RGB is the sample's
# shading normal, so the box filter's RGB is the normals' sum over the samples the mesh covers (over
# supersample²): the normal map keeps its direction, as the reference's pixel averages the shading there.
FOOTPRINT_FRAGMENT_SHADER = FRAGMENT_COMMON + """
layout(location = 0) out vec4 out_colour;

void main() {
    out_colour = vec4(shading_normal(), 1.0);
}
"""


# The reference's box filter on the GPU, so that only the filtered picture is read back (a ninth of the
# samples): one fragment a filtered texel, the mean of its k x k samples. A triangle covering the viewport,
# made from the vertex index (no attributes).
BOX_VERTEX_SHADER = """#version 330 core
void main() {
    vec2 corner = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(corner * 2.0 - 1.0, 0.0, 1.0);
}
"""

BOX_FRAGMENT_SHADER = """#version 330 core
uniform sampler2D samples;
uniform int factor;
uniform int skipped;  // filtered rows below the used part of the framebuffer
layout(location = 0) out vec4 out_mean;

void main() {
    ivec2 first = (ivec2(gl_FragCoord.xy) + ivec2(0, skipped)) * factor;
    vec4 total = vec4(0.0);
    for (int y = 0; y < factor; ++y) {
        for (int x = 0; x < factor; ++x) {
            total += texelFetch(samples, first + ivec2(x, y), 0);
        }
    }
    out_mean = total / float(factor * factor);
}
"""

# Widest framebuffer row of views, in texels (and never wider than the context's GL_MAX_TEXTURE_SIZE,
# 16384 on llvmpipe): float32 interpolation loses precision far from the framebuffer's origin.
MAX_ROW_TEXELS = 8192

@dataclass(frozen=True)
class _Pass:
    """A fragment shader and its targets: (internal format, pixel format, read-back type, numpy type)."""

    name: str
    fragment_shader: str
    targets: tuple[tuple[str, str, str, type], ...]
    uniforms: tuple[str, ...]


MAPS = _Pass("maps", MAPS_FRAGMENT_SHADER,
             (("GL_RGBA8UI", "GL_RGBA_INTEGER", "GL_UNSIGNED_BYTE", np.uint8), ("GL_RGBA16UI", "GL_RGBA_INTEGER", "GL_UNSIGNED_SHORT", np.uint16),
              ("GL_RGBA8UI", "GL_RGBA_INTEGER", "GL_UNSIGNED_BYTE", np.uint8), ("GL_RGBA8UI", "GL_RGBA_INTEGER", "GL_UNSIGNED_BYTE", np.uint8)),
             ("material", "depth_limit", "motion_limit"))
REFERENCE = _Pass("reference", REFERENCE_FRAGMENT_SHADER, (("GL_RGBA32F", "GL_RGBA", "GL_FLOAT", np.float32),),
                  ("light", "outfit", "ambient", "diffuse_weight"))
FOOTPRINT = _Pass("footprint", FOOTPRINT_FRAGMENT_SHADER, (("GL_RGBA32F", "GL_RGBA", "GL_FLOAT", np.float32),), ())
_VIEW_UNIFORMS = ("center", "right", "up", "back", "radius", "diffuse")  # -1 where a pass does not use one: set in vain
# Texels a reference pass draws at once (the rest waits for the next): 4 M RGBA32F texels are 64 MB.
MAX_PASS_TEXELS = 1 << 22


@dataclass(frozen=True)
class ShaderMaps:
    """The maps of V views of size S (module docstring), rows top first, 0 where nothing covers a texel.

    mask (V, S, S) bool: texels a triangle covers; normal, detail, surface (V, S, S, 4) uint8; uv
    (V, S, S, 4) uint16.
    """

    mask: np.ndarray
    normal: np.ndarray
    uv: np.ndarray
    detail: np.ndarray
    surface: np.ndarray


def corner_attributes(positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray, next_positions: np.ndarray,
                      faces: np.ndarray) -> np.ndarray:
    """(3T, 14) float32 vertex data of unwelded corners, triangle by triangle: position, normal, uv, next
    position and the triangle's face normal (the same at its three corners)."""
    corners = np.asarray(faces, dtype=np.int64).reshape(-1)
    # Gathered straight into the float32 columns: every map and reference draw makes one (the probes ~100 a range).
    vertices = np.empty((corners.size, 14), dtype=np.float32)
    vertices[:, 0:3] = np.asarray(positions)[corners]
    vertices[:, 3:6] = np.asarray(normals)[corners]
    vertices[:, 6:8] = np.asarray(uvs)[corners]
    vertices[:, 8:11] = np.asarray(next_positions)[corners]
    vertices[:, 11:14].reshape(-1, 3, 3)[:] = impostor_views.face_normals(positions, faces)[:, None, :]
    return vertices


class MapShader:
    """A pass's GL program and framebuffer (MAPS or REFERENCE), drawing views of one size S side by side.
    Every method needs the owning context current (crowdbake.render.offscreen.Offscreen.current); GL
    objects die with that context."""

    def __init__(self, size: int, shader_pass: _Pass = MAPS):
        self.size = int(size)
        self.shader_pass = shader_pass
        self._program = None
        self._locations: dict[str, int] = {}
        self._vao = self._buffer = None
        self._framebuffer = self._depth = None
        self._targets: list[int] = []
        self._grid = (0, 0)  # (columns, rows) of views the framebuffer holds
        self._textures: list[int] = []
        self._uploaded: list[np.ndarray] = []  # the diffuse arrays the textures hold (held, so their ids stay theirs)
        self._box: dict | None = None  # the box filter's program, framebuffer and target (_box_filter)
        self._max_texture_size = MAX_ROW_TEXELS  # the context's, once the program is made

    def draw(self, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray,
             next_positions: np.ndarray, faces: np.ndarray, triangle_material: np.ndarray, diffuse: list[np.ndarray],
             uniforms: Callable[[int, OrthoView], dict[str, np.ndarray]], box: int = 1) -> list[np.ndarray]:
        """Every view of one mesh: positions, normals, next_positions (P, 3) model space (metres), uvs (P, 2),
        faces (T, 3), triangle_material (T,) index into diffuse, a (h, w, 4) uint8 texture per material;
        uniforms(material, view): the pass's uniforms for that draw. Returns each target's (V, S, S, 4)
        array, rows top first; box > 1 (a pass of one float target): its (V, S / box, S / box, 4) means
        of box x box texels instead, filtered on the GPU."""
        from OpenGL import GL

        if not views:
            raise ValueError("MapShader.draw: no views")
        if any(view.size != self.size for view in views):
            raise ValueError(f"MapShader.draw: views must all be {self.size}²")
        triangle_material = np.asarray(triangle_material, dtype=np.int64)
        self._ensure_program()
        columns = max(1, min(len(views), min(MAX_ROW_TEXELS, self._max_texture_size) // self.size))
        self._ensure_framebuffer(columns, -(-len(views) // columns))
        # Triangles grouped by material, so that each material is one draw with its texture bound.
        order = np.argsort(triangle_material, kind="stable")
        ranges = np.searchsorted(triangle_material[order], np.arange(len(diffuse) + 1)) * 3
        self._upload_mesh(corner_attributes(positions, normals, uvs, next_positions, np.asarray(faces)[order]))
        self._upload_textures(diffuse)

        width, height = self._framebuffer_size()
        targets = self.shader_pass.targets
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._framebuffer)
        GL.glDrawBuffers(len(targets), [GL.GL_COLOR_ATTACHMENT0 + k for k in range(len(targets))])
        GL.glViewport(0, 0, width, height)
        GL.glDisable(GL.GL_SCISSOR_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glColorMask(GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE)
        for k, (_, pixel_format, _, _) in enumerate(targets):  # glClear's float colour is undefined on integer targets
            if pixel_format == "GL_RGBA_INTEGER":
                GL.glClearBufferuiv(GL.GL_COLOR, k, np.zeros(4, dtype=np.uint32))
            else:
                GL.glClearBufferfv(GL.GL_COLOR, k, np.zeros(4, dtype=np.float32))
        GL.glClearBufferfv(GL.GL_DEPTH, 0, np.ones(1, dtype=np.float32))
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDisable(GL.GL_CULL_FACE)  # double-sided: garments are open
        GL.glDisable(GL.GL_BLEND)
        GL.glUseProgram(self._program)
        GL.glBindVertexArray(self._vao)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glUniform1i(self._locations["diffuse"], 0)
        rows = self._grid[1]
        for k, view in enumerate(views):
            column, row = k % columns, k // columns
            GL.glViewport(column * self.size, (rows - 1 - row) * self.size, self.size, self.size)  # GL's rows grow upwards
            for name in ("center", "right", "up", "back"):
                GL.glUniform3f(self._locations[name], *np.asarray(getattr(view, name), dtype=np.float64).tolist())
            GL.glUniform1f(self._locations["radius"], view.radius)
            for material, texture in enumerate(self._textures):
                first, last = int(ranges[material]), int(ranges[material + 1])
                if last > first:
                    GL.glBindTexture(GL.GL_TEXTURE_2D, texture)
                    for name, value in uniforms(material, view).items():
                        self._set_uniform(name, value)
                    GL.glDrawArrays(GL.GL_TRIANGLES, first, last - first)
        if box > 1:
            if len(targets) != 1 or targets[0][1] != "GL_RGBA" or self.size % box:
                raise ValueError(f"MapShader.draw: box filtering needs one float target and a size divisible by {box}")
            rows_used = -(-len(views) // columns)
            image = self._box_filter(box, columns * self.size, rows_used * self.size)
            GL.glBindVertexArray(0)
            GL.glUseProgram(0)
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
            return [tiles_of(image, self.size // box, columns, len(views))]
        images = []
        for k, (_, pixel_format, read_type, dtype) in enumerate(targets):
            GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0 + k)
            image = np.empty((height, width, 4), dtype=dtype)
            GL.glReadPixels(0, 0, width, height, getattr(GL, pixel_format), getattr(GL, read_type), image.ctypes.data_as(ctypes.c_void_p))
            images.append(tiles_of(image[::-1], self.size, columns, len(views)))  # GL's rows grow upwards
        GL.glBindVertexArray(0)
        GL.glUseProgram(0)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        return images

    def _box_filter(self, factor: int, width: int, height: int) -> np.ndarray:
        """The top-left width x height texels of the framebuffer's first target averaged over factor x factor
        blocks by BOX_FRAGMENT_SHADER into a target of its own, read back: (height / factor, width / factor,
        4) float32, rows top first."""
        from OpenGL import GL
        from OpenGL.GL import shaders

        full_height = self._framebuffer_size()[1]
        small = (width // factor, height // factor)
        skipped = (full_height - height) // factor  # GL's rows grow upwards: the used rows are the top ones
        if self._box is None:
            program = shaders.compileProgram(shaders.compileShader(BOX_VERTEX_SHADER, GL.GL_VERTEX_SHADER),
                                             shaders.compileShader(BOX_FRAGMENT_SHADER, GL.GL_FRAGMENT_SHADER), validate=False)
            self._box = {"program": program, "size": None, "framebuffer": GL.glGenFramebuffers(1), "target": int(GL.glGenTextures(1))}
        box = self._box
        if box["size"] != small:
            GL.glBindTexture(GL.GL_TEXTURE_2D, box["target"])
            GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA32F, small[0], small[1], 0, GL.GL_RGBA, GL.GL_FLOAT, None)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, box["framebuffer"])
            GL.glFramebufferTexture2D(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_TEXTURE_2D, box["target"], 0)
            box["size"] = small
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, box["framebuffer"])
        GL.glDrawBuffers(1, [GL.GL_COLOR_ATTACHMENT0])
        GL.glViewport(0, 0, small[0], small[1])
        GL.glDisable(GL.GL_DEPTH_TEST)
        GL.glUseProgram(box["program"])
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, self._targets[0])
        GL.glUniform1i(GL.glGetUniformLocation(box["program"], "samples"), 0)
        GL.glUniform1i(GL.glGetUniformLocation(box["program"], "factor"), factor)
        GL.glUniform1i(GL.glGetUniformLocation(box["program"], "skipped"), skipped)
        GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        image = np.empty((small[1], small[0], 4), dtype=np.float32)
        GL.glReadPixels(0, 0, small[0], small[1], GL.GL_RGBA, GL.GL_FLOAT, image.ctypes.data_as(ctypes.c_void_p))
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
        return image[::-1]

    def delete(self) -> None:
        """Free the GL objects (the context must be current)."""
        from OpenGL import GL

        if self._box is not None:
            GL.glDeleteFramebuffers(1, [self._box["framebuffer"]])
            GL.glDeleteTextures(1, [self._box["target"]])
            GL.glDeleteProgram(self._box["program"])
        if self._textures:
            GL.glDeleteTextures(len(self._textures), self._textures)
        self._textures, self._uploaded = [], []
        self._delete_framebuffer()
        if self._buffer is not None:
            GL.glDeleteBuffers(1, [self._buffer])
            GL.glDeleteVertexArrays(1, [self._vao])
        if self._program is not None:
            GL.glDeleteProgram(self._program)
        self.__init__(self.size, self.shader_pass)

    def _set_uniform(self, name: str, value) -> None:
        from OpenGL import GL

        value = np.asarray(value, dtype=np.float32)
        location = self._locations[name]
        if value.ndim == 0:
            GL.glUniform1f(location, float(value))
        elif value.ndim == 1:
            GL.glUniform3f(location, *value.tolist())
        else:
            GL.glUniform3fv(location, len(value), np.ascontiguousarray(value))

    def _ensure_program(self) -> None:
        from OpenGL import GL
        from OpenGL.GL import shaders

        if self._program is not None:
            return
        self._program = shaders.compileProgram(
            shaders.compileShader(VERTEX_SHADER, GL.GL_VERTEX_SHADER),
            shaders.compileShader(self.shader_pass.fragment_shader, GL.GL_FRAGMENT_SHADER),
            validate=False,  # validation needs a bound VAO, which core profile contexts lack at this point
        )
        self._locations = {name: GL.glGetUniformLocation(self._program, name) for name in (*_VIEW_UNIFORMS, *self.shader_pass.uniforms)}
        self._max_texture_size = int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_SIZE))
        self._vao = GL.glGenVertexArrays(1)
        self._buffer = GL.glGenBuffers(1)
        GL.glBindVertexArray(self._vao)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._buffer)
        stride = sum(width for _, width in ATTRIBUTES) * 4
        offset = 0
        for name, width in ATTRIBUTES:
            location = GL.glGetAttribLocation(self._program, name)
            if location >= 0:  # -1: a pass that reads no output made from it (the reference's motion)
                GL.glEnableVertexAttribArray(location)
                GL.glVertexAttribPointer(location, width, GL.GL_FLOAT, GL.GL_FALSE, stride, ctypes.c_void_p(offset))
            offset += width * 4
        GL.glBindVertexArray(0)

    def _framebuffer_size(self) -> tuple[int, int]:
        return self._grid[0] * self.size, self._grid[1] * self.size

    def _ensure_framebuffer(self, columns: int, rows: int) -> None:
        from OpenGL import GL

        if self._framebuffer is not None and columns <= self._grid[0] and rows <= self._grid[1]:
            return
        self._delete_framebuffer()
        self._grid = (max(columns, self._grid[0]), max(rows, self._grid[1]))
        width, height = self._framebuffer_size()
        targets = self.shader_pass.targets
        self._framebuffer = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._framebuffer)
        self._targets = [int(name) for name in np.atleast_1d(GL.glGenTextures(len(targets)))]
        for k, (texture, (internal, pixel_format, read_type, _)) in enumerate(zip(self._targets, targets)):
            GL.glBindTexture(GL.GL_TEXTURE_2D, texture)
            GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, getattr(GL, internal), width, height, 0, getattr(GL, pixel_format), getattr(GL, read_type), None)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
            GL.glFramebufferTexture2D(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0 + k, GL.GL_TEXTURE_2D, texture, 0)
        self._depth = GL.glGenRenderbuffers(1)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._depth)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT24, width, height)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._depth)
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"the map shader's framebuffer ({width}x{height}, {[t[0] for t in targets]}) is incomplete: status 0x{int(status):x}")

    def _delete_framebuffer(self) -> None:
        from OpenGL import GL

        if self._framebuffer is None:
            return
        GL.glDeleteFramebuffers(1, [self._framebuffer])
        GL.glDeleteRenderbuffers(1, [self._depth])
        GL.glDeleteTextures(len(self._targets), self._targets)
        self._framebuffer = self._depth = None
        self._targets = []

    def _upload_mesh(self, vertices: np.ndarray) -> None:
        from OpenGL import GL

        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._buffer)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, vertices.nbytes, np.ascontiguousarray(vertices), GL.GL_STREAM_DRAW)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)

    def _upload_textures(self, diffuse: list[np.ndarray]) -> None:
        from OpenGL import GL

        if len(self._uploaded) == len(diffuse) and all(held is image for held, image in zip(self._uploaded, diffuse)):
            return  # a bake draws one scene's textures again and again (every frame and view)
        if len(self._textures) != len(diffuse):
            if self._textures:
                GL.glDeleteTextures(len(self._textures), self._textures)
            self._textures = [int(name) for name in np.atleast_1d(GL.glGenTextures(len(diffuse)))] if diffuse else []
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        for texture, image in zip(self._textures, diffuse):
            image = np.ascontiguousarray(image, dtype=np.uint8)
            if image.ndim != 3 or image.shape[2] != 4:
                raise ValueError(f"MapShader: a diffuse texture must be (h, w, 4) uint8, got {image.shape}")
            GL.glBindTexture(GL.GL_TEXTURE_2D, texture)
            GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA8, image.shape[1], image.shape[0], 0, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE, image)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAX_LEVEL, 0)  # texelFetch of level 0 only
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 4)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
        self._uploaded = list(diffuse)


def draw_maps(shader: MapShader, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray,
              next_positions: np.ndarray, faces: np.ndarray, triangle_material: np.ndarray, diffuse: list[np.ndarray]) -> ShaderMaps:
    """The MAPS pass (module docstring) of every view; arguments as MapShader.draw."""
    if shader.shader_pass is not MAPS:
        raise ValueError("draw_maps needs a MapShader of the MAPS pass")

    def uniforms(material: int, view: OrthoView) -> dict:
        return {"material": float(material), "depth_limit": surface_maps.DEPTH_RANGE * view.radius,
                "motion_limit": surface_maps.MOTION_RANGE * view.radius}

    normal, uv, detail, surface = shader.draw(views, positions, normals, uvs, next_positions, faces, triangle_material, diffuse, uniforms)
    return ShaderMaps(uv[..., 3] > 0, normal, uv, detail, surface)


def draw_references(shader: MapShader, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray,
                    faces: np.ndarray, triangle_material: np.ndarray, diffuse: list[np.ndarray], outfit_row: np.ndarray,
                    supersample: int, with_coverage: bool = False) -> np.ndarray:
    """The fidelity stage's mesh references (crowdbake.reference.mesh_reference) of views of size
    S · supersample: each sample shaded by the REFERENCE pass, box-filtered down to (V, S, S, 3) float32
    in 0..1, black background; with_coverage: (V, S, S, 4), alpha the share of the texel's samples the
    mesh covers. diffuse: per material, the texture as the runtime holds it; outfit_row:
    (16, 4) uint8, one row of the outfit map. Views are drawn MAX_PASS_TEXELS at a time; the box filter
    runs on the GPU (BOX_FRAGMENT_SHADER)."""
    if shader.shader_pass is not REFERENCE:
        raise ValueError("draw_references needs a MapShader of the REFERENCE pass")
    outfit = np.asarray(outfit_row, dtype=np.float32)[:, :3] / np.float32(255.0)

    def uniforms(material: int, view: OrthoView) -> dict:
        return {"light": shading.camera_light(view), "outfit": outfit, "ambient": shading.AMBIENT, "diffuse_weight": shading.DIFFUSE}

    most = max(1, MAX_PASS_TEXELS // (shader.size * shader.size))
    batch = -(-len(views) // -(-len(views) // most))  # as even as the fewest passes allow
    images = []
    for first in range(0, len(views), batch):
        (colour,) = shader.draw(views[first:first + batch], positions, normals, uvs, positions, faces, triangle_material, diffuse,
                                uniforms, box=supersample)
        images.append(colour if with_coverage else colour[..., :3])
    return np.concatenate(images)


def draw_footprints(shader: MapShader, views: list[OrthoView], positions: np.ndarray, normals: np.ndarray, faces: np.ndarray,
                    triangle_material: np.ndarray, material_count: int, supersample: int) -> np.ndarray:
    """Each texel's footprint from views of size S · supersample, (V, S, S, 4) float32: RGB the mean over the
    texel's supersample² samples of the shading normal (0 where the mesh misses a sample), alpha the share of
    them the mesh covers, as draw_references' alpha. normals: (P, 3) vertex normals, as for the maps."""
    if shader.shader_pass is not FOOTPRINT:
        raise ValueError("draw_footprints needs a MapShader of the FOOTPRINT pass")
    positions = np.asarray(positions)
    textures = [_BLANK_TEXTURE] * material_count  # bound in vain: the pass samples none
    no_uvs = np.zeros((len(positions), 2), dtype=np.float32)
    most = max(1, MAX_PASS_TEXELS // (shader.size * shader.size))
    batch = -(-len(views) // -(-len(views) // most))  # as draw_references batches
    images = []
    for first in range(0, len(views), batch):
        (footprint,) = shader.draw(views[first:first + batch], positions, normals, no_uvs, positions, faces, triangle_material, textures,
                                   lambda material, view: {}, box=supersample)
        images.append(footprint)
    return np.concatenate(images)


_BLANK_TEXTURE = np.zeros((1, 1, 4), dtype=np.uint8)


def tiles_of(image: np.ndarray, size: int, columns: int, count: int) -> np.ndarray:
    """The first `count` size² tiles of an (H, W, C) image laid out `columns` to a row, rows top first:
    (count, size, size, C)."""
    rows = -(-count // columns)
    grid = image[:rows * size, :columns * size].reshape(rows, size, columns, size, -1).swapaxes(1, 2)
    return np.ascontiguousarray(grid.reshape(rows * columns, size, size, -1)[:count])
