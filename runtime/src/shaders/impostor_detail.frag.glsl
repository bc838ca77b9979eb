#version 330 core
#include "../config.h"
#include "impostor_uv_map.glsl"
// The detail-mapped impostor the paper compares against (Geopostors): the diffuse colour of
// variation 0 is baked into the detail map, alpha carries the region code. Coverage comes
// from the UV map (impostor_uv_map.glsl), since region 0 inside the character also has alpha 0.

in vec2 v_tile_uv;
flat in ivec3 v_tile;
flat in float v_heading;
flat in uint v_variation;
flat in uint v_outfit;

uniform sampler2DArray u_normal_map;
uniform sampler2DArray u_detail_map;
uniform sampler2D u_outfits;
uniform int u_tile_size;
uniform vec3 u_light_dir;

out vec4 o_color;

void main() {
    ivec3 texel = ivec3(v_tile.xy + clamp(ivec2(v_tile_uv * float(u_tile_size)), ivec2(0), ivec2(u_tile_size - 1)), v_tile.z);
    if (!fetch_uv_map(texel).covered) discard;
    vec4 detail = texelFetch(u_detail_map, texel, 0);
    vec3 albedo = detail.rgb;
    int region = int(detail.a * 255.0 / CV_REGION_SCALE + 0.5);
    if (region != 0) albedo *= texelFetch(u_outfits, ivec2(region, int(v_outfit)), 0).rgb;

    vec3 model_normal = texelFetch(u_normal_map, texel, 0).rgb * 2.0 - 1.0;
    float c = cos(v_heading), s = sin(v_heading);
    vec3 normal = normalize(mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c) * model_normal);
    float light = CV_AMBIENT + (1.0 - CV_AMBIENT) * max(dot(normal, u_light_dir), 0.0);
    o_color = vec4(albedo * light, 1.0);
}
