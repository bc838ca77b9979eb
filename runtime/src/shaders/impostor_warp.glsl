// Which texel of a (view, frame) impostor sample a fragment reads. Both impostor shaders include this.
//
// CV_WARP 0: the texel under the fragment, at the same offset in every sample's tile (plain blending).
// CV_WARP 1: the sample reprojected with the bundle's surface map (SPEC.md "Impostor maps"; the bake's
// numpy copy is crowdbake.bake.impostor_warp, scored in fidelity.json's `runtime` section). A tile texel
// holds the surface point its view saw: its depth along the view axis and its motion in the tile's plane
// over one baked step (its velocity at that baked frame). A camera between baked views, or a cycle frame between baked frames, sees
// that point elsewhere; a fragment can only gather, so the reprojection is inverted by a fixed-point
// iteration, as parallax occlusion mapping does: start where the fragment's ray crosses the plane through
// the bounds centre, read depth and motion there (bilinear: the map is dilated into the background),
// move the point by the frame fraction, project it to the camera and shift the tile coordinate by the
// screen miss, mapped into the tile's axes. Everything is in the character's model frame, lengths in
// tile texels or metres as named.
#if !defined(CV_WARP) || !defined(CV_NORMAL_VIEW_XY)
#error "the renderer defines CV_WARP and CV_NORMAL_VIEW_XY (0 or 1 each)"
#endif

struct ViewBasis {
    vec3 right, up, back;  // model space; back points from the bounds centre towards the camera
};

// The bake's orthographic view looking back along `back` (SPEC.md "Impostor maps": +Y up, and +Z up
// where +Y is parallel to the view).
ViewBasis view_basis(vec3 back) {
    vec3 right = cross(vec3(0.0, 1.0, 0.0), back);
    if (length(right) < 1e-6) right = cross(vec3(0.0, 0.0, 1.0), back);
    right = normalize(right);
    ViewBasis b;
    b.right = right;
    b.up = cross(back, right);
    b.back = back;
    return b;
}

uniform float u_azimuths_deg[CV_MAX_AZIMUTHS];
uniform float u_elevations_deg[CV_MAX_ELEVATIONS];
uniform float u_radius;
// The part of every tile the atlas stores (SPEC.md "Impostor maps"): x, y, width, height in tile
// texels; an atlas cell is width x height. A sample's `origin` is where tile texel (0, 0) would lie
// in the atlas, so tile texel t is atlas texel origin + t inside the crop.
uniform ivec4 u_crop;

bool in_crop(ivec2 t) {
    return all(greaterThanEqual(t, u_crop.xy)) && all(lessThan(t, u_crop.xy + u_crop.zw));
}

// The baked view of the cell holding atlas texel `texel` (any texel of the cell).
ViewBasis tile_basis(ivec2 texel) {
    float a = radians(u_azimuths_deg[(texel.x / u_crop.z) % CV_MAX_AZIMUTHS]);
    float e = radians(u_elevations_deg[(texel.y / u_crop.w) % CV_MAX_ELEVATIONS]);
    return view_basis(vec3(sin(a) * cos(e), sin(e), cos(a) * cos(e)));
}

// The model-space normal at atlas texel `texel`, to be blended and then normalised. CV_NORMAL_VIEW_XY
// (the bc5 normal map, SPEC.md "Impostor maps"): R, G are the normal's components along the tile's
// right and up, the third, towards the camera, is sqrt(1 - x² - y²); otherwise RGB is (n + 1) / 2.
vec3 sample_normal(ivec3 texel) {
    vec3 n = texelFetch(u_normal_map, texel, 0).rgb * 2.0 - 1.0;
#if CV_NORMAL_VIEW_XY
    ViewBasis b = tile_basis(texel.xy);
    float z = sqrt(max(0.0, 1.0 - dot(n.xy, n.xy)));
    return n.x * b.right + n.y * b.up + z * b.back;
#else
    return n;
#endif
}

uniform sampler2DArray u_surface_map;  // bilinear, no mipmaps
uniform bool u_has_surface;            // false: the bundle has none (u_surface_map is a stand-in)

#if CV_WARP

// (depth along back, motion along right, motion along up) in metres at tile texel coordinate xy,
// filtered within the cell (texel centres at +0.5, clamped so no neighbouring cell is read).
vec3 surface_at(ivec2 origin, vec2 xy, int layer) {
    vec2 p = clamp(xy, vec2(u_crop.xy) + 0.5, vec2(u_crop.xy + u_crop.zw) - 0.5) + vec2(origin);
    vec3 c = texture(u_surface_map, vec3(p / vec2(textureSize(u_surface_map, 0).xy), float(layer))).rgb * 2.0 - 1.0;
    return vec3(c.r * CV_SURFACE_DEPTH_RANGE, c.g * CV_SURFACE_MOTION_RANGE, c.b * CV_SURFACE_MOTION_RANGE) * u_radius;
}

// Where `pixel` (target tile texels, x right, y down) finds its surface point in the source tile;
// `fraction` of the stored motion is applied (+: towards the next baked frame).
vec2 reproject(ViewBasis s, ViewBasis t, vec2 pixel, ivec2 origin, int layer, float fraction, out float miss) {
    float k = float(u_tile_size) / (2.0 * u_radius);  // texels a metre
    vec3 o = (pixel.x / k - u_radius) * t.right + (u_radius - pixel.y / k) * t.up;
    vec2 xy = vec2((dot(o, s.right) + u_radius) * k, (u_radius - dot(o, s.up)) * k);
    // A screen miss (right, down) as a move in the source tile's (right, down).
    mat2 step = mat2(dot(t.right, s.right), -dot(t.right, s.up), -dot(t.up, s.right), dot(t.up, s.up));
    for (int n = 0; n <= CV_WARP_ITERATIONS; ++n) {
        vec3 f = surface_at(origin, xy, layer);
        vec3 p = (xy.x / k - u_radius + fraction * f.y) * s.right + (u_radius - xy.y / k + fraction * f.z) * s.up + f.x * s.back;
        vec2 seen = vec2((dot(p, t.right) + u_radius) * k, (u_radius - dot(p, t.up)) * k);
        xy += step * (pixel - seen);
        miss = length(pixel - seen);
    }
    return xy;
}
#endif

// The atlas texel of the sample with tile origin `origin` and layer `layer` for the fragment at
// `pixel` (tile texels); x < 0 where the sample falls outside the stored crop (not covered).
// `target`: the camera's view in model space; `fraction`: see reproject.
// `share`: the part of the fragment the sample's silhouette covers (SPEC.md "Impostor maps": the
// surface map's alpha, filtered at the reprojected point, the texel's own unmoved; 1 in a bc1 surface
// map or without one, whose silhouette is the UV map's alone). `miss`: target texels the reprojection's last step missed by.
ivec3 sample_texel(ivec2 origin, int layer, vec2 pixel, ViewBasis target, float fraction, out float share, out float miss) {
#if CV_WARP
    vec2 xy = reproject(tile_basis(origin + u_crop.xy), target, pixel, origin, layer, fraction, miss);
    vec2 p = clamp(xy, vec2(u_crop.xy) + 0.5, vec2(u_crop.xy + u_crop.zw) - 0.5) + vec2(origin);
    share = texture(u_surface_map, vec3(p / vec2(textureSize(u_surface_map, 0).xy), float(layer))).a;
    ivec2 t = ivec2(floor(xy));
#else
    miss = 0.0;
    ivec2 t = clamp(ivec2(pixel), ivec2(0), ivec2(u_tile_size - 1));
    share = u_has_surface && in_crop(t) ? texelFetch(u_surface_map, ivec3(origin + t, layer), 0).a : 1.0;
#endif
    return in_crop(t) ? ivec3(origin + t, layer) : ivec3(-1);
}
