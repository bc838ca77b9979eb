// The impostor UV map in any of its formats (SPEC.md); the renderer defines CV_UV_MAP_UV32 to 1
// for uv32 and CV_UV_MAP_UVBLOCK to 1 for uvblock (both 0: rgba16). Both shaders that read the
// map include this, so the two programs agree on coverage. Read with texelFetch only: the map
// is not filterable data.
//   uv32:    one uint a texel: u bits 0..13, v 14..27 (value / 16383), material 28..30, coverage 31.
//   uvblock: 4x4 texels in six uints, three RG32UI texels in a row (decoded below, bundle.h).
//   rgba16:  normalised RG = u, v; B = material / 65535; A = coverage.
#if !defined(CV_UV_MAP_UV32) || !defined(CV_UV_MAP_UVBLOCK)
#error "the renderer defines CV_UV_MAP_UV32 and CV_UV_MAP_UVBLOCK (0 or 1 each)"
#endif

struct UvTexel {
    vec2 uv;
    int material;
    bool covered;
};

#if CV_UV_MAP_UVBLOCK
uniform usampler2DArray u_uv_map;

// SPEC.md pixel format 6. w0: 2-bit texel states (0 outside, 1..3 subset); w1 | w2 << 32: three
// 21-bit subset headers (u base 8, v base 8 in units of 16/4095, material 2, shift 3); w3..w5:
// texel i's 3-bit u and v offsets at stream bits 6i and 6i + 3.
UvTexel fetch_uv_map(ivec3 texel) {
    ivec3 block = ivec3((texel.x / 4) * 3, texel.y / 4, texel.z);
    int i = (texel.x % 4) + 4 * (texel.y % 4);
    uvec2 w01 = texelFetch(u_uv_map, block, 0).rg;
    uvec2 w23 = texelFetch(u_uv_map, block + ivec3(1, 0, 0), 0).rg;
    uvec2 w45 = texelFetch(u_uv_map, block + ivec3(2, 0, 0), 0).rg;
    uint state = (w01.x >> uint(2 * i)) & 3u;
    UvTexel t;
    t.uv = vec2(0.0);
    t.material = 0;
    t.covered = state != 0u;
    uint header = state == 1u ? w01.y : (state == 2u ? (w01.y >> 21u) | (w23.x << 11u) : w23.x >> 10u);
    header &= 0x1FFFFFu;
    uint bit = uint(6 * i), shift_in = bit & 31u, word = bit >> 5u;
    uint low = word == 0u ? w23.y : (word == 1u ? w45.x : w45.y);
    uint high = word == 0u ? w45.x : (word == 1u ? w45.y : 0u);
    uint field = ((low >> shift_in) | (shift_in > 26u ? high << (32u - shift_in) : 0u)) & 63u;
    uint shift = (header >> 18u) & 7u;
    uvec2 q = uvec2(16u * (header & 255u) + ((field & 7u) << shift), 16u * ((header >> 8u) & 255u) + ((field >> 3u) << shift));
    if (t.covered) {
        t.uv = vec2(q) / 4095.0;
        t.material = int((header >> 16u) & 3u);
    }
    return t;
}
#elif CV_UV_MAP_UV32
uniform usampler2DArray u_uv_map;

UvTexel fetch_uv_map(ivec3 texel) {
    uint word = texelFetch(u_uv_map, texel, 0).r;
    UvTexel t;
    t.uv = vec2(float(word & 0x3FFFu), float((word >> 14u) & 0x3FFFu)) / 16383.0;
    t.material = int((word >> 28u) & 7u);
    t.covered = (word >> 31u) != 0u;
    return t;
}
#else
uniform sampler2DArray u_uv_map;

UvTexel fetch_uv_map(ivec3 texel) {
    vec4 v = texelFetch(u_uv_map, texel, 0);
    UvTexel t;
    t.uv = v.rg;
    t.material = int(v.b * 65535.0 + 0.5);
    t.covered = v.a >= 0.5;
    return t;
}
#endif

// The blend of a pixel's (view, frame) samples, shared by both impostor shaders. Each sample counts
// with its weight times the part of the pixel its silhouette covers; where its reprojection did not
// converge (its last step still misses the pixel: the surface the pixel needs is hidden in that view,
// config.h CV_MISS_LOW) its colour is not trusted. The colour is the trusted samples' where they hold
// over CV_TRUSTED_SHARE of the coverage, else every sample's; the silhouette counts every sample.
struct SampleBlend {
    float coverage, trusted;
    vec3 albedo, normal, trusted_albedo, trusted_normal;
};

SampleBlend no_samples() {
    return SampleBlend(0.0, 0.0, vec3(0.0), vec3(0.0), vec3(0.0), vec3(0.0));
}

void add_sample(inout SampleBlend b, float weight, float miss, vec3 albedo, vec3 normal) {
    float sure = weight * (1.0 - smoothstep(CV_MISS_LOW, CV_MISS_HIGH, miss));
    b.coverage += weight;
    b.albedo += weight * albedo;
    b.normal += weight * normal;
    b.trusted += sure;
    b.trusted_albedo += sure * albedo;
    b.trusted_normal += sure * normal;
}

// The blend's albedo and (unnormalised) model-space normal; needs b.coverage > 0.
void blend_colour(SampleBlend b, out vec3 albedo, out vec3 normal) {
    bool sure = b.trusted > CV_TRUSTED_SHARE * b.coverage;
    albedo = sure ? b.trusted_albedo / b.trusted : b.albedo / b.coverage;
    normal = sure ? b.trusted_normal : b.normal;
}

// Opacity of a pixel whose blended samples cover `coverage` (0..1) of their weight. Reprojected
// (CV_WARP), the samples' silhouettes disagree by a texel or two: a smooth step (config.h
// CV_EDGE_LOW), 0.5 at a tie. Unmoved, they can disagree by a whole limb: the pixel is drawn where
// coverage is over one half (at a tie, where both agree); on the synthetic bundle of tests/test_render
// soft edges there drew a faint second limb (SSIM 0.787 against 0.830 for `full` blending).
// Each sample counts with the share of the pixel its silhouette covers where the surface map holds
// it (SPEC.md "Impostor maps"), so at a baked view the edge is anti-aliased as the mesh's.
float edge_alpha(float coverage) {
#if CV_WARP
    return smoothstep(CV_EDGE_LOW, 1.0 - CV_EDGE_LOW, coverage);
#else
    return coverage > 0.5 ? 1.0 : 0.0;
#endif
}
