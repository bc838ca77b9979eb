// crowdbake export: the UV-mapped impostor (Dobbyn et al. 2006, section 5) in a fragment shader.
// GLSL 3.30 / ES 3.00. The UV map's texture coordinates look up the mesh's own diffuse array, so one
// impostor shows every texture variation; region codes in the diffuse alpha pick the outfit colour;
// the model-space normal map lights it. Impostor maps are read unfiltered (texelFetch): filtering
// would blend coordinates with the background at the silhouette.
//
// Vertex stage: a camera-facing quad of impostor.quad_size_m around the bounds centre, with
//   tile_uv in 0..1 across it ((0, 0) top-left) and `tile` = the atlas tile of the bake camera nearest
//   the real one (export.json impostor.tile_of_view), `layer` = the nearest baked frame.

uniform highp usampler2DArray cb_uv_map;  // impostor/uv.ktx2 (R32_UINT, uv32 words)
uniform sampler2DArray cb_normal_map;     // impostor/normal.ktx2
uniform sampler2DArray cb_diffuse;        // textures/<material>_diffuse.ktx2 (one material shown here)
uniform sampler2D cb_outfits;             // textures/outfits.ktx2: x = region, y = outfit
uniform int cb_tile_size;
uniform ivec4 cb_crop;                    // export.json impostor.crop: x, y, width, height of each stored tile part
uniform vec3 cb_light_dir;                // unit, towards the light, world space

const float CB_AMBIENT = 0.35;  // crowdview's ambient term (runtime/src/config.h)

// crowdview's uv32 decode (runtime/src/shaders/impostor_uv_map.glsl); services/tests/test_export_shader_mirror.py
// checks this copy and CB_AMBIENT against crowdview's sources.
struct CbUvTexel { vec2 uv; int material; bool covered; };

CbUvTexel cb_fetch_uv(ivec3 texel) {
    uint word = texelFetch(cb_uv_map, texel, 0).r;
    CbUvTexel t;
    t.uv = vec2(float(word & 0x3FFFu), float((word >> 14u) & 0x3FFFu)) / 16383.0;
    t.material = int((word >> 28u) & 7u);
    t.covered = (word >> 31u) != 0u;
    return t;
}

// Returns false where the impostor does not cover the pixel (discard it).
// cell_origin: the top-left texel of the view's cell (a * crop.width, e * crop.height); heading: the
// character's rotation about +Y (radians).
bool cb_impostor_colour(vec2 tile_uv, ivec2 cell_origin, int layer, float heading, int variation, int outfit, out vec3 colour) {
    ivec2 t = clamp(ivec2(tile_uv * float(cb_tile_size)), ivec2(0), ivec2(cb_tile_size - 1)) - cb_crop.xy;
    colour = vec3(0.0);
    if (any(lessThan(t, ivec2(0))) || any(greaterThanEqual(t, cb_crop.zw))) return false;
    ivec2 texel = cell_origin + t;
    CbUvTexel uv = cb_fetch_uv(ivec3(texel, layer));
    if (!uv.covered) return false;
    vec4 diffuse = texture(cb_diffuse, vec3(uv.uv, float(variation)));
    int region = int(diffuse.a * 255.0 / 17.0 + 0.5);
    vec3 albedo = diffuse.rgb;
    if (region != 0) albedo *= texelFetch(cb_outfits, ivec2(region, outfit), 0).rgb;
    vec3 model_normal = texelFetch(cb_normal_map, ivec3(texel, layer), 0).rgb * 2.0 - 1.0;
    float c = cos(heading), s = sin(heading);
    vec3 normal = normalize(mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c) * model_normal);
    colour = albedo * (CB_AMBIENT + (1.0 - CB_AMBIENT) * max(dot(normal, cb_light_dir), 0.0));
    return true;
}
