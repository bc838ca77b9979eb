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
// screen miss, mapped into the tile's axes. The iteration converges to the surface nearest its start, which
// at a depth jump (an arm before the torso) need not be the one the camera sees; so it starts where the
// pixel's ray, marched from the camera's side, first passes behind a covered texel's surface (first_hit).
// The sample's normal and colour are then read bilinearly round the point found (filtered_normal; the
// UV impostor's filtered_albedo), as the mesh's anti-aliased pixel averages what it covers. Everything
// is in the character's model frame, lengths in tile texels or metres as named.
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

// The surface map's texel at tile texel coordinate xy, filtered within the cell (texel centres at +0.5,
// clamped so no neighbouring cell is read).
vec4 surface_texel(ivec2 origin, vec2 xy, int layer) {
    vec2 p = clamp(xy, vec2(u_crop.xy) + 0.5, vec2(u_crop.xy + u_crop.zw) - 0.5) + vec2(origin);
    return texture(u_surface_map, vec3(p / vec2(textureSize(u_surface_map, 0).xy), float(layer)));
}

// (depth along back, motion along right, motion along up) in metres at tile texel coordinate xy.
vec3 surface_at(ivec2 origin, vec2 xy, int layer) {
    vec3 c = surface_texel(origin, xy, layer).rgb * 2.0 - 1.0;
    return vec3(c.r * CV_SURFACE_DEPTH_RANGE, c.g * CV_SURFACE_MOTION_RANGE, c.b * CV_SURFACE_MOTION_RANGE) * u_radius;
}

// Tile texel coordinate of model-space point q (from the bounds centre) in view s (k: texels a metre).
vec2 tile_point(ViewBasis s, vec3 q, float k) {
    return vec2((dot(q, s.right) + u_radius) * k, (u_radius - dot(q, s.up)) * k);
}

// Whether the point `depth` metres along the target's back from `o` (on the plane through the bounds
// centre) lies behind the surface of a covered texel of the source view; `xy`: where it falls in the tile.

bool behind_surface(ViewBasis s, ViewBasis t, vec3 o, float depth, ivec2 origin, int layer, float k, out vec2 xy) {
    vec3 q = o + depth * t.back;
    xy = tile_point(s, q, k);
    if (any(lessThan(xy, vec2(u_crop.xy))) || any(greaterThanEqual(xy, vec2(u_crop.xy + u_crop.zw)))) return false;
    vec4 c = surface_texel(origin, xy, layer);
    return c.a > 0.5 && dot(q, s.back) <= (c.r * 2.0 - 1.0) * CV_SURFACE_DEPTH_RANGE * u_radius;
}

// (lowest, highest): the depths along t.back, within +-reach, between which the ray through `o` projects
// into the source view's crop (a slab per tile axis); lowest > highest where it never does.
vec2 march_span(ViewBasis s, ViewBasis t, vec3 o, float k, float reach) {
    vec2 p = tile_point(s, o, k);
    vec2 v = k * vec2(dot(t.back, s.right), -dot(t.back, s.up));  // texels a metre of depth
    vec2 lo = vec2(-reach), hi = vec2(reach);
    for (int i = 0; i < 2; ++i) {
        float a = (float(u_crop[i]) - p[i]) / v[i], b = (float(u_crop[i] + u_crop[i + 2]) - p[i]) / v[i];
        bool still = abs(v[i]) < 1e-6;
        bool inside = p[i] >= float(u_crop[i]) && p[i] < float(u_crop[i] + u_crop[i + 2]);
        lo[i] = still ? (inside ? -reach : reach) : min(a, b);
        hi[i] = still ? (inside ? reach : -reach) : max(a, b);
    }
    return vec2(max(-reach, max(lo.x, lo.y)), min(reach, min(hi.x, hi.y)));
}

// Where the ray of the pixel whose point on the centre plane is `o` first passes behind the source view's
// surface: marched from the camera's side of the bounds to the far side, one step for each source texel
// its points cross (at most CV_MARCH_STEPS), then refined by halving; `start` where it never does (the ray
// misses what that view saw).
vec2 first_hit(ViewBasis s, ViewBasis t, vec3 o, ivec2 origin, int layer, float k, vec2 start) {
    float crossed = float(u_tile_size) * length(cross(s.back, t.back));  // texels the ray's points span in s
    // The sample's own view: every depth lands on the start (no steps). Loops, not branches, skip the work:
    // a software rasteriser runs both sides of a branch for its whole group of fragments.
    int steps = crossed < 0.01 ? 0 : clamp(int(ceil(crossed)), 1, CV_MARCH_STEPS);
    float reach = CV_SURFACE_DEPTH_RANGE * u_radius;
    float spacing = 2.0 * reach / float(max(steps, 1));
    // Only steps whose points fall in the source's crop can pass behind its surface: the march keeps its
    // steps where they were and skips the others (the first kept one's predecessor is in front).
    vec2 span = march_span(s, t, o, k, reach);
    int first = max(1, int(floor((reach - span.y) / spacing)));
    int last = min(steps, int(ceil((reach - span.x) / spacing)));
    float front = reach - float(first - 1) * spacing, back = reach;
    bool found = false;
    vec2 xy;
    for (int n = first; n <= last && !found; ++n) {
        float depth = reach - float(n) * spacing;
        found = behind_surface(s, t, o, depth, origin, layer, k, xy);
        if (found) back = depth; else front = depth;
    }
    for (int h = 0; h < (found ? CV_MARCH_REFINE : 0); ++h) {
        float middle = 0.5 * (front + back);
        if (behind_surface(s, t, o, middle, origin, layer, k, xy)) back = middle; else front = middle;
    }
    // The last point still in front starts the fixed-point steps: nearer the camera's surface than the
    // first behind it (the robot halfway between 8 azimuths: SSIM 0.854 against 0.849; services/benchmarks/LOG.md).
    return found ? tile_point(s, o + front * t.back, k) : start;
}

// Where `pixel` (target tile texels, x right, y down) finds its surface point in the source tile;
// `fraction` of the stored motion is applied (+: towards the next baked frame).
vec2 reproject(ViewBasis s, ViewBasis t, vec2 pixel, ivec2 origin, int layer, float fraction, out float miss) {
    float k = float(u_tile_size) / (2.0 * u_radius);  // texels a metre
    vec3 o = (pixel.x / k - u_radius) * t.right + (u_radius - pixel.y / k) * t.up;
    vec2 xy = first_hit(s, t, o, origin, layer, k, tile_point(s, o, k));
    // At the sample's own view and frame every step would land on the pixel: it is read as it is.
    bool own = fraction == 0.0 && float(u_tile_size) * length(cross(s.back, t.back)) < 0.01;
    xy = own ? pixel : xy;
    miss = 0.0;
    // A screen miss (right, down) as a move in the source tile's (right, down).
    mat2 step = mat2(dot(t.right, s.right), -dot(t.right, s.up), -dot(t.up, s.right), dot(t.up, s.up));
    for (int n = 0; n <= (own ? -1 : CV_WARP_ITERATIONS); ++n) {
        vec3 f = surface_at(origin, xy, layer);
        vec3 p = (xy.x / k - u_radius + fraction * f.y) * s.right + (u_radius - xy.y / k + fraction * f.z) * s.up + f.x * s.back;
        vec2 seen = tile_point(t, p, k);
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
// `point`: the tile texel coordinate the sample is read at (filtered_normal, filtered_albedo).
ivec3 sample_texel(ivec2 origin, int layer, vec2 pixel, ViewBasis target, float fraction, out float share, out float miss,
                   out vec2 point) {
#if CV_WARP
    vec2 xy = reproject(tile_basis(origin + u_crop.xy), target, pixel, origin, layer, fraction, miss);
    point = xy;
    share = surface_texel(origin, xy, layer).a;
    ivec2 t = ivec2(floor(xy));
#else
    miss = 0.0;
    point = pixel;
    ivec2 t = clamp(ivec2(pixel), ivec2(0), ivec2(u_tile_size - 1));
    share = u_has_surface && in_crop(t) ? texelFetch(u_surface_map, ivec3(origin + t, layer), 0).a : 1.0;
#endif
    return in_crop(t) ? ivec3(origin + t, layer) : ivec3(-1);
}

// The bilinear weights (x, y, z, w) of the four tile texels round tile texel coordinate `point` (top left,
// top right, bottom left, bottom right; clamped to the crop); `count`: the taps to read, 1 at a texel's
// centre (its own, weight 1), else 4.
vec4 bilinear_taps(vec2 point, out ivec2 texels[4], out int count) {
    vec2 q = point - 0.5;
    ivec2 corner = ivec2(floor(q));
    vec2 f = q - vec2(corner);
    for (int n = 0; n < 4; ++n) texels[n] = clamp(corner + ivec2(n % 2, n / 2), u_crop.xy, u_crop.xy + u_crop.zw - 1);
    count = f == vec2(0.0) ? 1 : 4;
    return vec4((1.0 - f.x) * (1.0 - f.y), f.x * (1.0 - f.y), (1.0 - f.x) * f.y, f.x * f.y);
}

// The normal (unnormalised) read bilinearly round `point` in the sample's cell: the normal map is filled
// into the background from the nearest covered texel, so every tap holds a normal of the character.
vec3 filtered_normal(ivec2 origin, vec2 point, int layer) {
    ivec2 texels[4];
    int count;
    vec4 w = bilinear_taps(point, texels, count);
    vec3 n = vec3(0.0);
    for (int k = 0; k < count; ++k) n += w[k] * sample_normal(ivec3(origin + texels[k], layer));
    return n;
}
