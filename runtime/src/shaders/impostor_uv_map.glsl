// The impostor UV map in either of its formats (SPEC.md); the renderer defines CV_UV_MAP_UV32
// to 1 for uv32 and to 0 for rgba16. Both shaders that read the map include this, so the two
// programs agree on coverage. Read with texelFetch only: the map is not filterable data.
//   uv32:   one uint a texel: u bits 0..13, v 14..27 (value / 16383), material 28..30, coverage 31.
//   rgba16: normalised RG = u, v; B = material / 65535; A = coverage.
#ifndef CV_UV_MAP_UV32
#error "the renderer defines CV_UV_MAP_UV32 (0: rgba16, 1: uv32)"
#endif

struct UvTexel {
    vec2 uv;
    int material;
    bool covered;
};

#if CV_UV_MAP_UV32
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
