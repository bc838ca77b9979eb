#version 330 core
#include "../config.h"
// Diffuse variation from a texture array, outfit colour by the alpha region code, Lambert light.

in vec2 v_uv;
in vec3 v_normal;
flat in uint v_variation;
flat in uint v_outfit;

uniform sampler2DArray u_diffuse;
uniform int u_variations;    // layers of u_diffuse
uniform bool u_has_regions;  // false for bc1 diffuse maps, which carry no alpha
uniform sampler2D u_outfits;
uniform vec3 u_light_dir;    // unit, towards the light

out vec4 o_color;

void main() {
    float layer = float(v_variation % uint(u_variations));
    vec3 albedo = texture(u_diffuse, vec3(v_uv, layer)).rgb;
    // Region codes are read unfiltered: blending two codes names a third, unrelated region.
    ivec2 size = textureSize(u_diffuse, 0).xy;
    ivec2 texel = clamp(ivec2(fract(v_uv) * vec2(size)), ivec2(0), size - 1);
    int region = u_has_regions ? int(texelFetch(u_diffuse, ivec3(texel, int(layer)), 0).a * 255.0 / CV_REGION_SCALE + 0.5) : 0;
    if (region != 0) albedo *= texelFetch(u_outfits, ivec2(region, int(v_outfit)), 0).rgb;
    vec3 normal = normalize(gl_FrontFacing ? v_normal : -v_normal);  // garments show their inside
    float light = CV_AMBIENT + (1.0 - CV_AMBIENT) * max(dot(normal, u_light_dir), 0.0);
    o_color = vec4(albedo * light, 1.0);
}
