#version 330 core
#include "../config.h"
#include "impostor_uv_map.glsl"
#if !defined(CV_VIEW_SAMPLES) || !defined(CV_FRAME_SAMPLES)
#error "the renderer defines CV_VIEW_SAMPLES (1 or 4) and CV_FRAME_SAMPLES (1 or 2)"
#endif
#if CV_MAX_MATERIALS != 4
#error albedo_at samples materials 0 to 3, keep it in step with CV_MAX_MATERIALS
#endif
// The paper's UV-mapped impostor (section 5): the UV map's texture coordinates look up the
// same diffuse arrays as the mesh, so one impostor shows every texture variation; region
// codes in the diffuse alpha pick the outfit colour; the normal map lights it dynamically.
// Impostor maps are read with texelFetch: filtering would blend texture coordinates with
// the background at the silhouette, the artefact the paper describes.
//
// Blending (view_blend.h, README "Impostor blending"): up to four views times two frames.
// Each sample reads its own view's UV map texel and looks up the diffuse texture with that
// exact coordinate; only the resulting colours, normals and coverage are blended.

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
uniform sampler2DArray u_diffuse[CV_MAX_MATERIALS];
uniform int u_variations[CV_MAX_MATERIALS];
uniform bool u_has_regions[CV_MAX_MATERIALS];
uniform int u_material_count;
uniform sampler2D u_outfits;
uniform int u_tile_size;
uniform vec3 u_light_dir;
#include "impostor_warp.glsl"

out vec4 o_color;

// Colour (filtered, with explicit gradients, so it may sit in a per-fragment branch) and the
// unfiltered region alpha of material m. GLSL 3.30 indexes sampler arrays only with
// constants, so each material is its own block. Every material the bundle has is sampled
// (a uniform branch) and the texel's own kept.
#define CV_SAMPLE_MATERIAL(m)                                                                 \
    if (u_material_count > m) {                                                               \
        float layer = float(v_variation % uint(u_variations[m]));                            \
        vec3 colour = textureGrad(u_diffuse[m], vec3(uv, layer), dx, dy).rgb;                \
        ivec2 size = textureSize(u_diffuse[m], 0).xy;                                         \
        ivec2 texel = clamp(ivec2(uv * vec2(size)), ivec2(0), size - 1);                      \
        float a = u_has_regions[m] ? texelFetch(u_diffuse[m], ivec3(texel, int(layer)), 0).a : 0.0; \
        albedo = material == m ? colour : albedo;                                             \
        alpha = material == m ? a : alpha;                                                    \
    }

// The outfit-coloured diffuse colour at UV map texel `t`.
vec3 albedo_at(UvTexel t, vec2 dx, vec2 dy) {
    vec2 uv = t.uv;
    int material = t.material;
    vec3 albedo = vec3(1.0, 0.0, 1.0);  // magenta: a material index this build cannot address
    float alpha = 0.0;                  // region code * 17 / 255; 0 where a material has no regions
    CV_SAMPLE_MATERIAL(0)
    CV_SAMPLE_MATERIAL(1)
    CV_SAMPLE_MATERIAL(2)
    CV_SAMPLE_MATERIAL(3)
    int region = int(alpha * 255.0 / CV_REGION_SCALE + 0.5);
    if (region != 0) albedo *= texelFetch(u_outfits, ivec2(region, int(v_outfit)), 0).rgb;
    return albedo;
}

#if CV_WARP
// The colour read bilinearly round `point` (tile texels) in the sample's cell, over the taps the character
// covers (a background tap has no texture coordinate). A covered sample's own texel is one of them, of weight
// a quarter or more, so the sum is never 0. Each tap looks the diffuse up with its own coordinate at the
// sample's gradients.
vec3 filtered_albedo(ivec2 origin, vec2 point, int layer, vec2 dx, vec2 dy) {
    ivec2 texels[4];
    int count;
    vec4 w = bilinear_taps(point, texels, count);
    vec3 albedo = vec3(0.0);
    float sum = 0.0;
    for (int k = 0; k < count; ++k) {
        UvTexel t = fetch_uv_map(ivec3(origin + texels[k], layer));
        if (t.covered && w[k] > 0.0) {
            albedo += w[k] * albedo_at(t, dx, dy);
            sum += w[k];
        }
    }
    return albedo / max(sum, 1e-6);
}
#endif

void main() {
    vec2 pixel = v_tile_uv * float(u_tile_size);
    ViewBasis target = view_basis(v_to_camera);
    // Neighbours across the silhouette or a UV seam would ask for a far too coarse mip level;
    // clamp the gradients to a few tile texels' worth of footprint.
    float limit = 4.0 * max(length(dFdx(v_tile_uv)), length(dFdy(v_tile_uv))) + 1e-6;
    SampleBlend blend = no_samples();
    // Constant bounds (the renderer's CV_VIEW_SAMPLES, CV_FRAME_SAMPLES: 1 or 4, 1 or 2), so
    // the loops unroll; with blending off this is the paper's single lookup.
    for (int j = 0; j < CV_FRAME_SAMPLES; ++j) {
        float frame_weight = j == 0 ? 1.0 - v_frame_weight : v_frame_weight;
        // The earlier baked frame moves forward by the frame weight, the later one back by the rest.
        float fraction = v_layers[0] == v_layers[1] ? 0.0 : (j == 0 ? v_frame_weight : v_frame_weight - 1.0);
        for (int i = 0; i < CV_VIEW_SAMPLES; ++i) {
            float share, miss;
            vec2 point;
            ivec2 origin = ivec2(v_tile_x[i], v_tile_y[i]);
            ivec3 texel = sample_texel(origin, v_layers[j], pixel, target, fraction, share, miss, point);
            UvTexel t = fetch_uv_map(max(texel, ivec3(0)));
            t.covered = t.covered && texel.x >= 0;
            vec2 dx = dFdx(t.uv), dy = dFdy(t.uv);
            dx *= min(1.0, limit / max(length(dx), 1e-9));
            dy *= min(1.0, limit / max(length(dy), 1e-9));
            if (t.covered) {
#if CV_WARP
                vec3 albedo = filtered_albedo(origin, point, v_layers[j], dx, dy);
                vec3 normal = filtered_normal(origin, point, v_layers[j]);
#else
                vec3 albedo = albedo_at(t, dx, dy), normal = sample_normal(texel);
#endif
                add_sample(blend, v_view_weights[i] * frame_weight * share, miss, albedo, normal);
            }
        }
    }
    // Where the samples' silhouettes disagree the pixel is partly transparent (edge_alpha), blended
    // over what is behind it (renderer.cpp); where none covers enough, nothing is drawn.
    float alpha = edge_alpha(blend.coverage);
    if (alpha <= 0.0 || blend.coverage <= 0.0) discard;
    vec3 albedo, model_normal;
    blend_colour(blend, albedo, model_normal);
    float c = cos(v_heading), s = sin(v_heading);
    vec3 normal = normalize(mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c) * model_normal);
    float light = CV_AMBIENT + (1.0 - CV_AMBIENT) * max(dot(normal, u_light_dir), 0.0);
    o_color = vec4(albedo * light, alpha);
}
