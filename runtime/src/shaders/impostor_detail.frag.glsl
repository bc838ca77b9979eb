#version 330 core
#include "../config.h"
#include "impostor_uv_map.glsl"
#if !defined(CV_VIEW_SAMPLES) || !defined(CV_FRAME_SAMPLES)
#error "the renderer defines CV_VIEW_SAMPLES (1 or 4) and CV_FRAME_SAMPLES (1 or 2)"
#endif
// The detail-mapped impostor the paper compares against (Geopostors): the diffuse colour of
// variation 0 is baked into the detail map, alpha carries the region code. Coverage comes
// from the UV map (impostor_uv_map.glsl), since region 0 inside the character also has alpha 0.
// Blended over views and frames like the UV impostor (impostor_uv.frag.glsl).

in vec2 v_tile_uv;
flat in ivec4 v_tile_x;
flat in ivec4 v_tile_y;
flat in vec4 v_view_weights;
flat in ivec2 v_layers;
flat in float v_frame_weight;
flat in float v_heading;
flat in uint v_variation;
flat in uint v_outfit;
flat in vec3 v_to_camera;  // model space, unit

uniform sampler2DArray u_normal_map;
uniform sampler2DArray u_detail_map;
uniform sampler2D u_outfits;
uniform int u_tile_size;
uniform vec3 u_light_dir;
#include "impostor_warp.glsl"

out vec4 o_color;

#if CV_VIEW_SAMPLES * CV_FRAME_SAMPLES == 1
// Blending off: the paper's single lookup, leaving at once outside the silhouette (on a
// software rasterizer the accumulating loop below costs half as much again).
void main() {
    ivec2 t = clamp(ivec2(v_tile_uv * float(u_tile_size)), ivec2(0), ivec2(u_tile_size - 1));
    if (!in_crop(t)) discard;
    ivec3 texel = ivec3(ivec2(v_tile_x[0], v_tile_y[0]) + t, v_layers[0]);
    // Drawn where the character covers over half the texel (edge_alpha unmoved; the surface map's alpha).
    if (!fetch_uv_map(texel).covered || (u_has_surface && texelFetch(u_surface_map, texel, 0).a <= 0.5)) discard;
    vec4 detail = texelFetch(u_detail_map, texel, 0);
    vec3 albedo = detail.rgb;
    int region = int(detail.a * 255.0 / CV_REGION_SCALE + 0.5);
    if (region != 0) albedo *= texelFetch(u_outfits, ivec2(region, int(v_outfit)), 0).rgb;
    vec3 model_normal = sample_normal(texel);
    float alpha = 1.0;
#else
void main() {
    vec2 pixel = v_tile_uv * float(u_tile_size);
    ViewBasis target = view_basis(v_to_camera);
    SampleBlend blend = no_samples();
    // Constant bounds (the renderer's CV_VIEW_SAMPLES, CV_FRAME_SAMPLES: 1 or 4, 1 or 2), so
    // the loops unroll.
    for (int j = 0; j < CV_FRAME_SAMPLES; ++j) {
        float frame_weight = j == 0 ? 1.0 - v_frame_weight : v_frame_weight;
        float fraction = v_layers[0] == v_layers[1] ? 0.0 : (j == 0 ? v_frame_weight : v_frame_weight - 1.0);  // see impostor_uv
        for (int i = 0; i < CV_VIEW_SAMPLES; ++i) {
            float share, miss;
            vec2 point;
            ivec2 origin = ivec2(v_tile_x[i], v_tile_y[i]);
            ivec3 texel = sample_texel(origin, v_layers[j], pixel, target, fraction, share, miss, point);
            if (texel.x < 0 || !fetch_uv_map(texel).covered) continue;
            vec4 detail = texelFetch(u_detail_map, texel, 0);
            vec3 colour = detail.rgb;
            int region = int(detail.a * 255.0 / CV_REGION_SCALE + 0.5);
            if (region != 0) colour *= texelFetch(u_outfits, ivec2(region, int(v_outfit)), 0).rgb;
#if CV_WARP
            vec3 normal = filtered_normal(origin, point, v_layers[j]);  // as the UV impostor's (impostor_warp.glsl)
#else
            vec3 normal = sample_normal(texel);
#endif
            add_sample(blend, v_view_weights[i] * frame_weight * share, miss, colour, normal);
        }
    }
    float alpha = edge_alpha(blend.coverage);  // see impostor_uv.frag.glsl
    if (alpha <= 0.0 || blend.coverage <= 0.0) discard;
    vec3 albedo, model_normal;
    blend_colour(blend, albedo, model_normal);
#endif
    float c = cos(v_heading), s = sin(v_heading);
    vec3 normal = normalize(mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c) * model_normal);
    float light = CV_AMBIENT + (1.0 - CV_AMBIENT) * max(dot(normal, u_light_dir), 0.0);
    o_color = vec4(albedo * light, alpha);
}
