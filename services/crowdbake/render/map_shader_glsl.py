"""The GLSL of crowdbake.render.map_shader: one vertex shader, the maps pass and the reference pass (a
shared fragment prelude each), and the box filter that averages a reference's samples per texel.
Encodings as SPEC.md's "Impostor maps"; see map_shader's docstring for what each target holds.
"""
from __future__ import annotations

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
