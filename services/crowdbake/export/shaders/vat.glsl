// crowdbake export: play a vertex-animation texture (VAT) in a vertex shader. GLSL 3.30 / ES 3.00.
// Include in a vertex shader; docs/export.md shows a whole program. Values come from export.json
// (lods[].parts[].vat) or the glTF mesh's extras.crowdbake.vat.
//
// Every VAT is 16-bit unsigned normalised RGBA. Bind them as normalised textures (RGBA16, sampled with
// texelFetch as floats 0..1) or, where 16-bit normalised textures are missing (WebGL2 without
// EXT_texture_norm16), as RGBA16UI and define CB_VAT_INTEGER so the values are divided here.
// vat.kind "frames": vat.texture holds per pose frame each vertex's position (rgb) and octahedral normal (a).
// vat.kind "skin": vat.texture holds per vertex its rest position and normal, four joints and four weights,
// and vat.joints per pose frame each joint's 3 x 4 matrix; the vertex is skinned as crowdview skins it
// (runtime/src/shaders/mesh.vert.glsl).

#ifdef CB_VAT_INTEGER
#define CB_VAT_SAMPLER highp usampler2D
#define CB_VAT_READ(t, c) (vec4(texelFetch(t, c, 0)) / 65535.0)
#else
#define CB_VAT_SAMPLER highp sampler2D
#define CB_VAT_READ(t, c) texelFetch(t, c, 0)
#endif

uniform CB_VAT_SAMPLER cb_vat_texture;   // vat.texture
uniform CB_VAT_SAMPLER cb_vat_joints;    // vat.joints (a skin's; unused for frames)
uniform vec3 cb_vat_bounds_min;          // vat.bounds_min
uniform vec3 cb_vat_bounds_max;          // vat.bounds_max
uniform int cb_vat_rows_per_frame;       // vat.rows_per_frame
uniform int cb_vat_skinned;              // 1 where vat.kind is "skin", 0 for "frames"
uniform int cb_vat_joint_rows_per_frame; // vat.joints.rows_per_frame
uniform vec4 cb_vat_joint_min;           // vat.joints.min
uniform vec4 cb_vat_joint_max;           // vat.joints.max
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

// A normal's octahedral word (the alpha, w = a * 65535: u = w % 256, v = w / 256, 8 bits each; Meyer et al.
// 2010, section 3.3: the lower half of the octahedron folded over the upper's square).
vec3 cb_vat_octahedral(float a) {
    float word = floor(a * 65535.0 + 0.5);
    vec2 e = vec2(mod(word, 256.0), floor(word / 256.0)) * (2.0 / 255.0) - 1.0;
    vec3 n = vec3(e, 1.0 - abs(e.x) - abs(e.y));
    if (n.z < 0.0) n.xy = (1.0 - abs(e.yx)) * vec2(e.x >= 0.0 ? 1.0 : -1.0, e.y >= 0.0 ? 1.0 : -1.0);
    return normalize(n);
}

// Row `row` (0..2) of joint `joint`'s skinning matrix at pose frame `frame`: texel index 3 * joint + row of
// the frame's rows, each channel between vat.joints.min and max.
vec4 cb_vat_joint_row(int frame, int joint, int row) {
    int width = textureSize(cb_vat_joints, 0).x;
    int i = 3 * joint + row;
    vec4 q = CB_VAT_READ(cb_vat_joints, ivec2(i % width, frame * cb_vat_joint_rows_per_frame + i / width));
    return cb_vat_joint_min + q * (cb_vat_joint_max - cb_vat_joint_min);
}

// Linear blend skinning at one pose frame: p = sum w_k M_k (rest, 1), n = normalize(sum w_k L_k rest_normal)
// (L the 3 x 3 block), as the bundle's frames are.
void cb_vat_skin(vec4 rest, vec3 rest_normal, ivec4 joints, vec4 weights, int frame, out vec3 position, out vec3 normal) {
    position = vec3(0.0);
    normal = vec3(0.0);
    for (int k = 0; k < 4; ++k) {
        vec4 r0 = cb_vat_joint_row(frame, joints[k], 0), r1 = cb_vat_joint_row(frame, joints[k], 1), r2 = cb_vat_joint_row(frame, joints[k], 2);
        position += weights[k] * vec3(dot(r0, rest), dot(r1, rest), dot(r2, rest));
        normal += weights[k] * vec3(dot(r0.xyz, rest_normal), dot(r1.xyz, rest_normal), dot(r2.xyz, rest_normal));
    }
    normal = normalize(normal);
}

// Position and normal of the vertex whose TEXCOORD_1 is `vat_uv` at `frame` = seconds into the animation
// times frames_per_second (any real number: a clip wraps, a transition holds its ends), the two nearest
// keys blended linearly, as the glTF animation of the same name plays.
void cb_vat_sample(vec2 vat_uv, float frame, out vec3 position, out vec3 normal) {
    ivec2 size = textureSize(cb_vat_texture, 0);
    ivec2 texel = ivec2(vat_uv * vec2(size));  // block 0's texel (TEXCOORD_1 is its centre)
    float n = float(cb_vat_range_frames);
    bool loop = cb_vat_range_loop != 0;
    float x = loop ? mod(frame, n) : clamp(frame, 0.0, n + 1.0);
    int j0 = min(int(floor(x)), loop ? cb_vat_range_frames - 1 : cb_vat_range_frames);
    float t = x - float(j0);
    int f0 = cb_vat_key_frame(j0), f1 = cb_vat_key_frame(j0 + 1);
    vec3 extent = cb_vat_bounds_max - cb_vat_bounds_min;
    if (cb_vat_skinned != 0) {
        vec4 rest = CB_VAT_READ(cb_vat_texture, texel);
        ivec4 joints = ivec4(CB_VAT_READ(cb_vat_texture, texel + ivec2(0, cb_vat_rows_per_frame)) * 65535.0 + 0.5);
        vec4 weights = CB_VAT_READ(cb_vat_texture, texel + ivec2(0, 2 * cb_vat_rows_per_frame));
        vec4 rest_position = vec4(cb_vat_bounds_min + rest.rgb * extent, 1.0);
        vec3 rest_normal = cb_vat_octahedral(rest.a), p0, n0, p1, n1;
        cb_vat_skin(rest_position, rest_normal, joints, weights, f0, p0, n0);
        cb_vat_skin(rest_position, rest_normal, joints, weights, f1, p1, n1);
        position = mix(p0, p1, t);
        normal = normalize(mix(n0, n1, t));
    } else {
        vec4 a = CB_VAT_READ(cb_vat_texture, texel + ivec2(0, f0 * cb_vat_rows_per_frame));
        vec4 b = CB_VAT_READ(cb_vat_texture, texel + ivec2(0, f1 * cb_vat_rows_per_frame));
        position = cb_vat_bounds_min + mix(a.rgb, b.rgb, t) * extent;
        normal = normalize(mix(cb_vat_octahedral(a.a), cb_vat_octahedral(b.a), t));
    }
}
