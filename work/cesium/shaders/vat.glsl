// crowdbake export: play a vertex-animation texture (VAT) in a vertex shader. GLSL 3.30 / ES 3.00.
// Include in a vertex shader; docs/export.md shows a whole program. Values come from export.json
// (lods[].parts[].vat) or the glTF mesh's extras.crowdbake.vat.
//
// The position VAT is 16-bit unsigned normalised RGBA. Bind it as a normalised texture (RGBA16, sampled
// with texelFetch as floats 0..1) or, where 16-bit normalised textures are missing (WebGL2 without
// EXT_texture_norm16), as RGBA16UI and define CB_VAT_INTEGER so the values are divided here. The normal
// VAT is 8-bit RGBA, a normalised texture everywhere.

#ifdef CB_VAT_INTEGER
#define CB_VAT_SAMPLER highp usampler2D
#define CB_VAT_READ(t, c) (vec4(texelFetch(t, c, 0)) / 65535.0)
#else
#define CB_VAT_SAMPLER highp sampler2D
#define CB_VAT_READ(t, c) texelFetch(t, c, 0)
#endif

uniform CB_VAT_SAMPLER cb_vat_position;
uniform highp sampler2D cb_vat_normal;
uniform vec3 cb_vat_bounds_min;     // vat.bounds_min
uniform vec3 cb_vat_bounds_max;     // vat.bounds_max
uniform int cb_vat_rows_per_frame;  // vat.rows_per_frame
// The animation played (export.json animations[].vat): a clip or a transition, a range of pose frames.
uniform int cb_vat_range_first;     // first_frame
uniform int cb_vat_range_frames;    // frames
uniform int cb_vat_range_loop;      // loop: 1 wraps round the range (a clip), 0 plays it once (a transition)
uniform int cb_vat_range_before;    // before_frame: a transition's key 0, the from clip's leave pose
uniform int cb_vat_range_after;     // after_frame: the pose after the range's last frame

// The pose frame of key j of the animation: a clip's keys are its frames (key `frames` is its first again);
// a transition's key 0 is before_frame, keys 1..frames its frames, key frames + 1 after_frame.
int cb_vat_key_frame(int j) {
    if (cb_vat_range_loop != 0) return j < cb_vat_range_frames ? cb_vat_range_first + j : cb_vat_range_after;
    if (j <= 0) return cb_vat_range_before;
    if (j > cb_vat_range_frames) return cb_vat_range_after;
    return cb_vat_range_first + j - 1;
}

// Position and normal of the vertex whose TEXCOORD_1 is `vat_uv` at `frame` = seconds into the animation
// times frames_per_second (any real number: a clip wraps, a transition holds its ends), the two nearest
// keys blended linearly, as the glTF animation of the same name plays.
void cb_vat_sample(vec2 vat_uv, float frame, out vec3 position, out vec3 normal) {
    ivec2 size = textureSize(cb_vat_position, 0);
    ivec2 texel = ivec2(vat_uv * vec2(size));  // frame 0's texel (TEXCOORD_1 is its centre)
    float n = float(cb_vat_range_frames);
    bool loop = cb_vat_range_loop != 0;
    float x = loop ? mod(frame, n) : clamp(frame, 0.0, n + 1.0);
    int j0 = min(int(floor(x)), loop ? cb_vat_range_frames - 1 : cb_vat_range_frames);
    float t = x - float(j0);
    ivec2 c0 = texel + ivec2(0, cb_vat_key_frame(j0) * cb_vat_rows_per_frame);
    ivec2 c1 = texel + ivec2(0, cb_vat_key_frame(j0 + 1) * cb_vat_rows_per_frame);
    vec3 q = mix(CB_VAT_READ(cb_vat_position, c0).rgb, CB_VAT_READ(cb_vat_position, c1).rgb, t);
    position = cb_vat_bounds_min + q * (cb_vat_bounds_max - cb_vat_bounds_min);
    vec3 m = mix(texelFetch(cb_vat_normal, c0, 0).rgb, texelFetch(cb_vat_normal, c1, 0).rgb, t);
    normal = normalize(m * 2.0 - 1.0);
}
