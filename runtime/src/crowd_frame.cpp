// One frame's instances for one archetype or many (crowd.h build_frame, build_frames): the hot loop
// of a crowd. Two passes over chunks of characters. The first steps the clip state (clips.h: a
// compare until the next switch), places the bounds centre, tests it against the frustum and picks
// the LOD (a dot product along the view, with hysteresis); counting what each chunk holds at each
// level gives every chunk its place in the instance lists (FrameInstances' vectors, or memory an
// InstanceStorage hands out: mapped GL buffers). The second fills those places: for
// impostors the view (two arctangents, the view choice and weights, in a branch-free loop over
// arrays the compiler vectorises) and the frame blend (a table lookup). Chunks touch only their own
// characters and places, so any number of threads builds the frame one thread builds.
// Everything that does not change between frames sits in FrameState.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <thread>
#include <vector>

#include "crowd.h"

namespace crowdview {

namespace {

constexpr float kPi = 3.14159265358979323846f;
constexpr float kDegrees = 180.0f / kPi;

// atan(x) for |x| <= 1: an odd minimax polynomial, within 1e-5 rad (6e-4 degrees) of the true
// value, far below the baked views' 10-30 degree spacing (Abramowitz and Stegun 4.4.49's form).
inline float atan_unit(float x) {
    const float x2 = x * x;
    return x * (0.99997726f + x2 * (-0.33262347f + x2 * (0.19354346f + x2 * (-0.11643287f + x2 * (0.05265332f + x2 * -0.01172120f)))));
}

// atan2(y, x) in radians, to atan_unit's accuracy; 0 for (0, 0).
inline float fast_atan2(float y, float x) {
    const float ax = std::fabs(x), ay = std::fabs(y);
    const float big = std::max(ax, ay);
    if (big == 0) return 0;
    float a = atan_unit(std::min(ax, ay) / big);
    if (ay > ax) a = 0.5f * kPi - a;
    if (x < 0) a = kPi - a;
    return y < 0 ? -a : a;
}

// view_angles_deg (view_blend.h) without turning the vector: the azimuth in the character's
// frame is the world azimuth less the heading; the elevation does not depend on the heading.
inline glm::vec2 fast_view_angles_deg(const glm::vec3& to_camera, float heading) {
    const float horizontal = std::sqrt(to_camera.x * to_camera.x + to_camera.z * to_camera.z);
    return glm::vec2((fast_atan2(to_camera.x, to_camera.z) - heading) * kDegrees, fast_atan2(to_camera.y, horizontal) * kDegrees);
}

bool same_ranges(const std::vector<ClipRange>& a, const std::vector<ClipRange>& b) {
    return std::equal(a.begin(), a.end(), b.begin(), b.end(), [](const ClipRange& x, const ClipRange& y) {
        return x.first_frame == y.first_frame && x.frames == y.frames;
    });
}

bool same_views_and_frames(const CharacterModel& a, const CharacterModel& b) {
    return a.frame_count == b.frame_count && a.frames_per_second == b.frames_per_second && a.center == b.center &&
           a.azimuths_deg == b.azimuths_deg && a.elevations_deg == b.elevations_deg && a.frame_indices == b.frame_indices &&
           same_ranges(a.clips, b.clips) && a.transitions == b.transitions;
}

// The clip schedule for the model's ranges and the crowd's plan, and every character's state at
// time 0: rebuilt when either changes, the crowd is another, or time goes back.
void prepare_clips(const Crowd& crowd, const CharacterModel& model, float time_s, bool tables_rebuilt, FrameState* s) {
    const bool new_plan = !(s->schedule_plan == crowd.clip_plan) || s->schedule_seed != crowd.clip_seed;
    if (tables_rebuilt || new_plan || s->schedule.ranges.empty()) {
        s->schedule = make_clip_schedule(model.clips, model.transitions, model.frame_count, model.frames_per_second,
                                         crowd.clip_plan, crowd.clip_seed);
        s->schedule_plan = crowd.clip_plan;
        s->schedule_seed = crowd.clip_seed;
        s->clip.clear();
    }
    if (s->clip.size() != crowd.characters.size() || time_s < s->clip_time_s) {
        s->clip.resize(crowd.characters.size());
        for (size_t i = 0; i < crowd.characters.size(); ++i)
            s->clip[i] = initial_clip_state(s->schedule, uint32_t(i), crowd.characters[i].clip, crowd.characters[i].phase_s);
        s->next_switch_s.resize(crowd.characters.size());
        for (size_t i = 0; i < crowd.characters.size(); ++i) s->next_switch_s[i] = s->clip[i].next_event_s;
    }
    s->clip_time_s = time_s;
}

// Returns whether the per-frame tables were rebuilt.
bool build_tables(const Crowd& crowd, const CharacterModel& model, FrameState* s) {
    if (s->crowd != &crowd || s->center_offset.size() != crowd.characters.size() || !(s->tables_for.center == model.center)) {
        s->crowd = &crowd;
        s->center_offset.resize(crowd.characters.size());
        s->heading.resize(crowd.characters.size());
        for (std::vector<float>* v : {&s->center_x, &s->center_y, &s->center_z}) v->resize(crowd.characters.size());
        for (size_t i = 0; i < crowd.characters.size(); ++i) {
            const float h = crowd.characters[i].heading, ch = std::cos(h), sh = std::sin(h);
            s->heading[i] = h;
            s->center_offset[i] = glm::vec2(ch * model.center.x + sh * model.center.z, -sh * model.center.x + ch * model.center.z);
            const glm::vec3& feet = crowd.characters[i].start;  // on the spot; walking crowds overwrite them every frame
            s->center_x[i] = feet.x + s->center_offset[i].x, s->center_y[i] = feet.y + model.center.y, s->center_z[i] = feet.z + s->center_offset[i].y;
        }
        s->tables_for.center = glm::vec3(NAN);  // the frame tables below are rebuilt with the centre
    }
    if (same_views_and_frames(s->tables_for, model) && !s->nearest_layer.empty()) return false;
    s->tables_for = model;
    // Only the ranges matter to the impostor tables; the plan does not.
    const ClipSchedule ranges = make_clip_schedule(model.clips, model.transitions, model.frame_count, model.frames_per_second, {}, 0);
    impostor_frame_tables(model.frame_indices, ranges, model.frame_count, &s->nearest_layer, &s->frame_weights);
    const auto [lowest, highest] = std::minmax_element(model.elevations_deg.begin(), model.elevations_deg.end());
    s->lowest_elevation = uint32_t(lowest - model.elevations_deg.begin());
    s->highest_elevation = uint32_t(highest - model.elevations_deg.begin());
    // Evenly spaced ascending azimuths round the full circle: index = (azimuth - first) / step.
    const size_t n = model.azimuths_deg.size();
    s->even_azimuths = n > 0;
    s->azimuth0_deg = n ? model.azimuths_deg[0] : 0;
    s->azimuth_step_deg = n ? 360.0f / float(n) : 0;
    for (size_t k = 0; k < n && s->even_azimuths; ++k)
        s->even_azimuths = std::fabs(model.azimuths_deg[k] - (s->azimuth0_deg + float(k) * s->azimuth_step_deg)) < 1e-3f;
    return true;
}

// Within this fraction of a view step of a tie between two nearest views, the fast angles are
// not trusted to pick the side view_angles_deg picks: 0.01 of a 10-30 degree step is 0.1-0.3
// degrees, hundreds of times atan_unit's error.
constexpr float kTieMargin = 0.01f;

// On evenly spaced azimuths, in one pass: the nearest tile (nearest_view_weights' rule, ties to
// the lower index) and, with `blend`, the bilinear weights (blend_view_weights' rule). Returns
// whether `angles` lie near a tie of the nearest choice (azimuth or elevation half way between
// two baked ones), where the caller recomputes them exactly.
bool even_view_choice(const glm::vec2& angles, const FrameState& s, const std::vector<float>& elevations_deg, uint32_t columns,
                      bool blend, uint32_t* nearest_tile, ViewWeights* views) {
    float t = (angles.x - s.azimuth0_deg) / s.azimuth_step_deg;
    t -= float(columns) * fast_floor(t / float(columns));
    const uint32_t a0 = std::min(uint32_t(t), columns - 1), a1 = columns < 2 ? a0 : (a0 + 1) % columns;
    const float frac = t - float(a0);
    const uint32_t azimuth = frac < 0.5f ? a0 : frac > 0.5f ? a1 : std::min(a0, a1);
    // Elevation: the nearest row (and how near the runner-up is), and for blending the rows
    // either side of the elevation clamped to the baked range.
    const float clamped = glm::clamp(angles.y, elevations_deg[s.lowest_elevation], elevations_deg[s.highest_elevation]);
    uint32_t elevation = 0, e0 = s.lowest_elevation, e1 = s.highest_elevation;
    float best = INFINITY, second = INFINITY;
    for (uint32_t e = 0; e < elevations_deg.size(); ++e) {
        const float v = elevations_deg[e], gap = std::fabs(angles.y - v);
        if (gap < best) second = best, best = gap, elevation = e;
        else if (gap < second) second = gap;
        if (v <= clamped && v > elevations_deg[e0]) e0 = e;
        if (v >= clamped && v < elevations_deg[e1]) e1 = e;
    }
    *nearest_tile = azimuth + elevation * columns;
    if (blend) {
        const float wa = columns < 2 ? 0.0f : frac;
        const float span = elevations_deg[e1] - elevations_deg[e0];
        const float we = span > 0 ? (clamped - elevations_deg[e0]) / span : 0.0f;
        views->tiles[0] = a0 + e0 * columns, views->weights[0] = (1 - wa) * (1 - we);
        views->tiles[1] = a1 + e0 * columns, views->weights[1] = wa * (1 - we);
        views->tiles[2] = a0 + e1 * columns, views->weights[2] = (1 - wa) * we;
        views->tiles[3] = a1 + e1 * columns, views->weights[3] = wa * we;
    }
    return std::fabs(frac - 0.5f) < kTieMargin || second - best < kTieMargin * s.azimuth_step_deg;
}

}  // namespace

namespace {

// Characters per chunk: the work a thread takes at a time, and the length of the view pass's arrays
// (on the stack, a few tens of kilobytes).
constexpr size_t kChunk = 2048;

// The vectorised loops are built twice, for SSE2 (x86-64's baseline) and AVX2 (twice as wide), and
// the loader picks what the CPU has. Neither uses FMA, so both give the same bits.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define VECTOR_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define VECTOR_CLONES
#endif

// fast_atan2 without branches, for the vectorised view pass: the same operations, so the same result
// bit for bit (the branches become selects; 0 for (0, 0) as there).
inline float select_atan2(float y, float x) {
    const float ax = std::fabs(x), ay = std::fabs(y);
    const float big = ax < ay ? ay : ax, small = ay < ax ? ay : ax;
    const float ratio = big > 0 ? small / big : 0.0f;
    float a = atan_unit(ratio);
    a = ay > ax ? 0.5f * kPi - a : a;
    a = x < 0 ? kPi - a : a;
    return y < 0 ? -a : a;
}

// select_lod and lod_without_history (crowd.cpp) with the rule's levels and boundaries worked out
// once a frame instead of once a character: the same comparisons on the same values.
struct LodSteps {
    Lod levels[3];
    float boundaries[2], coarser_beyond[2];
    int count;
};

LodSteps lod_steps(const LodRule& rule) {
    LodSteps r{};
    if (rule.has_low && rule.low_fraction < 1.0f) {
        r.levels[0] = Lod::high, r.levels[1] = Lod::low, r.levels[2] = Lod::impostor, r.count = 3;
        r.boundaries[0] = rule.impostor_distance * rule.low_fraction, r.boundaries[1] = rule.impostor_distance;
    } else {
        r.levels[0] = Lod::high, r.levels[1] = Lod::impostor, r.count = 2;
        r.boundaries[0] = rule.impostor_distance;
    }
    for (int i = 0; i + 1 < r.count; ++i) r.coarser_beyond[i] = r.boundaries[i] * (1.0f + rule.hysteresis);
    return r;
}

inline Lod pick_lod(float distance, Lod previous, const LodSteps& r) {
    int i = 0;
    while (i < r.count - 1 && r.levels[i] != previous) ++i;
    if (r.levels[i] != previous) {  // no history (or a level the rule lacks): by distance alone
        i = 0;
        while (i < r.count - 1 && distance >= r.boundaries[i]) ++i;
        return r.levels[i];
    }
    while (i < r.count - 1 && distance > r.coarser_beyond[i]) ++i;
    while (i > 0 && distance < r.boundaries[i - 1]) --i;
    return r.levels[i];
}

// What every pass of one archetype's frame reads.
struct Pass {
    const Crowd* crowd;
    const CharacterModel* model;
    const LodRule* rule;
    FrameState* state;
    FrameInstances* out;
    InstancePlaces places;  // where the lists go (place_chunks)
    size_t chunks;
    bool on_the_spot, has_views, fast_views;  // fast_views: even azimuths, at most 4 elevations
    bool nearest_samples;                     // no views, but the storage wants samples: the nearest alone
    float elevations[4];                      // padded with +infinity, which no test below picks
    LodSteps lod_steps;
};

struct FrameSetup {
    Frustum frustum;
    glm::vec3 eye, forward;
    LodMode mode;
    float time_s;
    bool blend_views, blend_frames;
};

// sphere_in_frustum (crowd.h) and the depth along the view for characters [begin, end), over arrays:
// vectorised. All six planes without an early exit: no branch at all.
VECTOR_CLONES void visibility(const FrameState& s, float radius, const FrameSetup& f, size_t begin, size_t end, int32_t* visible, float* depth) {
    const float* __restrict cx = s.center_x.data() + begin;
    const float* __restrict cy = s.center_y.data() + begin;
    const float* __restrict cz = s.center_z.data() + begin;
    const int32_t n = int32_t(end - begin);
    const float reach = -radius, ex = f.eye.x, ey = f.eye.y, ez = f.eye.z, fx = f.forward.x, fy = f.forward.y, fz = f.forward.z;
    for (int32_t k = 0; k < n; ++k) {
        const float x = cx[k], y = cy[k], z = cz[k];
        bool inside = true;
        for (const glm::vec4& q : f.frustum.planes) inside &= q.x * x + q.y * y + q.z * z + q.w >= reach;
        visible[k] = inside;
        depth[k] = (x - ex) * fx + (y - ey) * fy + (z - ez) * fz;
    }
}

// Pass 1 over one chunk: clip state, centre, culling and LOD; counts per level (and culled).
void cull_chunk(const Pass& p, const FrameSetup& f, size_t chunk) {
    FrameState& s = *p.state;
    const CharacterModel& model = *p.model;
    const size_t begin = chunk * kChunk, end = std::min(begin + kChunk, p.crowd->characters.size());
    const Character* characters = p.crowd->characters.data();
    // Clip state: nothing to do until the character's next switch event (a few times a minute).
    float* next_switch = s.next_switch_s.data();
    for (size_t i = begin; i < end; ++i)
        if (f.time_s >= next_switch[i]) {
            advance_clip_state(s.schedule, uint32_t(i), characters[i].rate, f.time_s, &s.clip[i]);
            next_switch[i] = s.clip[i].next_event_s;
        }
    // Centres: fixed on the spot (build_tables placed them), moved along paths.
    if (!p.on_the_spot)
        for (size_t i = begin; i < end; ++i) {
            const glm::vec3 feet = s.feet[i] = character_position(*p.crowd, characters[i], f.time_s);
            s.center_x[i] = feet.x + s.center_offset[i].x, s.center_y[i] = feet.y + model.center.y, s.center_z[i] = feet.z + s.center_offset[i].y;
        }
    // sphere_in_frustum and the depth along the view over arrays (vectorised), then the LOD.
    float depth[kChunk];
    int32_t visible[kChunk];
    visibility(s, model.radius, f, begin, end, visible, depth);
    // The level, without a branch on visibility (half the characters of a street view are culled,
    // in no order a predictor learns): a culled character keeps its history and shows 3.
    const bool automatic = f.mode == LodMode::automatic;
    const Lod fixed = f.mode == LodMode::high  ? Lod::high
                      : f.mode == LodMode::low ? (model.has_low ? Lod::low : Lod::high)
                                               : Lod::impostor;
    Lod* history = s.lod.data();
    uint8_t* shown = s.shown.data();
    uint32_t counts[4] = {0, 0, 0, 0};
    for (size_t i = begin; i < end; ++i) {
        const Lod lod = automatic ? pick_lod(depth[i - begin], history[i], p.lod_steps) : fixed;
        const bool seen = visible[i - begin] != 0;
        history[i] = seen ? lod : history[i];
        shown[i] = seen ? uint8_t(lod) : uint8_t(3);
        ++counts[shown[i]];
    }
    std::copy(counts, counts + 4, s.chunk_counts.begin() + 4 * chunk);
}

// The view pass's results for a chunk, one array per field: the nearest tile and the samples'
// tiles and weights, sorted as impostor_samples sorts them.
struct ChunkViews {
    int32_t nearest[kChunk], tiles[4][kChunk], tie[kChunk];
    float weights[4][kChunk];
};

// even_view_choice for characters [begin, end) from their centres and headings, with the fast angles,
// written so the compiler vectorises it (-fopt-info-vec): fixed trip counts, selects, no calls.
// Equal to even_view_choice(fast_view_angles_deg(...)) bit for bit; `tie` marks where the caller
// must decide with the exact angles.
VECTOR_CLONES void even_views(const Pass& p, const FrameSetup& f, size_t begin, size_t end, ChunkViews* v) {
    const FrameState& s = *p.state;
    const float* __restrict cx = s.center_x.data() + begin;
    const float* __restrict cy = s.center_y.data() + begin;
    const float* __restrict cz = s.center_z.data() + begin;
    const float* __restrict heading = s.heading.data() + begin;
    const int32_t columns = int32_t(p.model->azimuths_deg.size());
    const float columns_f = float(columns), az0 = s.azimuth0_deg, step = s.azimuth_step_deg;
    const float lowest = p.model->elevations_deg[s.lowest_elevation], highest = p.model->elevations_deg[s.highest_elevation];
    const float lowest_i = float(s.lowest_elevation), highest_i = float(s.highest_elevation);
    const float e[4] = {p.elevations[0], p.elevations[1], p.elevations[2], p.elevations[3]};
    const float ex = f.eye.x, ey = f.eye.y, ez = f.eye.z, tie_gap = kTieMargin * step;
    const float azimuth_weight = columns < 2 ? 0.0f : 1.0f;  // one azimuth: none blended (a 0 weight may be -0: unused alike)
    const int32_t n = int32_t(end - begin);
    for (int32_t k = 0; k < n; ++k) {
        const float x = ex - cx[k], y = ey - cy[k], z = ez - cz[k];
        const float horizontal = std::sqrt(x * x + z * z);
        const float azimuth = (select_atan2(x, z) - heading[k]) * kDegrees, elevation = select_atan2(y, horizontal) * kDegrees;
        float t = (azimuth - az0) / step;
        const float q = t / columns_f, qt = float(int32_t(q));
        t -= columns_f * (qt > q ? qt - 1.0f : qt);
        // t >= 0 up to rounding: truncating to int32 is the uint32 truncation there. The indices are
        // small whole numbers held in floats, exact, since SSE2 has float min and no 32-bit integer one.
        const float a0 = std::min(float(int32_t(t)), columns_f - 1), a1 = a0 + 1 == columns_f ? 0.0f : a0 + 1;  // one column: a0 = a1 = 0
        const float frac = t - a0;
        const float azimuth_i = frac < 0.5f ? a0 : frac > 0.5f ? a1 : std::min(a0, a1);
        const float clamped = std::min(std::max(elevation, lowest), highest);
        float nearest_e = 0, r0 = lowest_i, r1 = highest_i;
        float v0 = lowest, v1 = highest, best = INFINITY, second = INFINITY;
#pragma GCC unroll 4
        for (int32_t j = 0; j < 4; ++j) {
            const float ev = e[j], gap = std::fabs(elevation - ev);
            const bool better = gap < best, runner_up = !better & (gap < second);
            second = better ? best : runner_up ? gap : second;
            nearest_e = better ? float(j) : nearest_e;
            best = better ? gap : best;
            const bool below = (ev <= clamped) & (ev > v0), above = (ev >= clamped) & (ev < v1);
            r0 = below ? float(j) : r0, v0 = below ? ev : v0;
            r1 = above ? float(j) : r1, v1 = above ? ev : v1;
        }
        const float span = v1 - v0;
        const float wa = frac * azimuth_weight, we = span > 0 ? (clamped - v0) / span : 0.0f;
        v->nearest[k] = int32_t(azimuth_i + nearest_e * columns_f);
        v->tie[k] = (std::fabs(frac - 0.5f) < kTieMargin) | (second - best < tie_gap);
        // Bilinear weights, then impostor_samples' order (heaviest first, ties by index: the
        // stable sort) by a sorting network of five compare-exchanges, without branches.
        float w[4] = {(1 - wa) * (1 - we), wa * (1 - we), (1 - wa) * we, wa * we};
        float tile[4] = {a0 + r0 * columns_f, a1 + r0 * columns_f, a0 + r1 * columns_f, a1 + r1 * columns_f};
        float index[4] = {0, 1, 2, 3};
        auto order = [&](int i, int j) {  // entry i before entry j
            const bool swap = (w[j] > w[i]) | ((w[j] == w[i]) & (index[j] < index[i]));
            const float wi = w[i], ti = tile[i], ii = index[i];
            w[i] = swap ? w[j] : wi, tile[i] = swap ? tile[j] : ti, index[i] = swap ? index[j] : ii;
            w[j] = swap ? wi : w[j], tile[j] = swap ? ti : tile[j], index[j] = swap ? ii : index[j];
        };
        order(0, 1), order(2, 3), order(0, 2), order(1, 3), order(1, 2);
        for (int m = 0; m < 4; ++m) {  // weight-0 entries repeat the heaviest tile
            v->tiles[m][k] = int32_t(w[m] > 0 ? tile[m] : tile[0]);
            v->weights[m][k] = w[m] > 0 ? w[m] : 0.0f;
        }
    }
}

// The samples' tiles and view weights as the shader reads them: heaviest first, weight-0 entries
// last (repeating the heaviest tile); an insertion sort of four, stable as std::stable_sort is.
inline void sort_views(const ViewWeights& views, ImpostorSamples* samples) {
    int order[4] = {0, 1, 2, 3};
    for (int k = 1; k < 4; ++k)
        for (int j = k; j > 0 && views.weights[order[j]] > views.weights[order[j - 1]]; --j) std::swap(order[j], order[j - 1]);
    for (int k = 0; k < 4; ++k) {
        const bool used = views.weights[order[k]] > 0;
        samples->tiles[k] = used ? views.tiles[order[k]] : views.tiles[order[0]];
        samples->view_weights[k] = used ? views.weights[order[k]] : 0.0f;
    }
}

// The views of an impostor the view pass leaves out (near a tie, or a bundle it does not cover):
// even_view_choice, near a tie with the exact angles (view_blend.h) so the choice is the one they
// make, or view_blend.h's search for uneven azimuths. Without view blending, the nearest alone.
ViewWeights exact_views(const Pass& p, const FrameSetup& f, const glm::vec3& center, float heading, uint32_t* nearest_tile) {
    const FrameState& s = *p.state;
    const CharacterModel& model = *p.model;
    const uint32_t columns = uint32_t(model.azimuths_deg.size());
    const glm::vec3 to_camera = f.eye - center;
    ViewWeights views;
    if (s.even_azimuths) {
        if (p.fast_views || even_view_choice(fast_view_angles_deg(to_camera, heading), s, model.elevations_deg, columns, f.blend_views,
                                             nearest_tile, &views))
            even_view_choice(view_angles_deg(to_camera, heading), s, model.elevations_deg, columns, f.blend_views, nearest_tile, &views);
    } else {
        const glm::vec2 angles = view_angles_deg(to_camera, heading);
        *nearest_tile = nearest_view_weights(angles, model.azimuths_deg, model.elevations_deg).tiles[0];
        if (f.blend_views) views = blend_view_weights(angles, model.azimuths_deg, model.elevations_deg);
    }
    if (!f.blend_views) {
        for (uint32_t& t : views.tiles) t = *nearest_tile;
        views.weights[0] = 1, views.weights[1] = views.weights[2] = views.weights[3] = 0;
    }
    return views;
}

// Pass 2 over one chunk: the instances (and impostor samples) of its shown characters, at the places
// pass 1's counts gave it. Built once per blend choice, so the loop tests no flag per character, and
// with every array read through a local pointer, as the stores through Instance* might otherwise alias
// them and reload them each time.
template <bool kBlendViews, bool kBlendFrames>
void fill_chunk(const Pass& p, const FrameSetup& f, size_t chunk) {
    const FrameState& s = *p.state;
    const size_t begin = chunk * kChunk, end = std::min(begin + kChunk, p.crowd->characters.size());
    if (s.chunk_counts[4 * chunk + 3] == end - begin) return;  // all culled
    uint32_t place[3];
    std::copy(s.chunk_offsets.begin() + 3 * chunk, s.chunk_offsets.begin() + 3 * chunk + 3, place);
    const bool has_views = p.has_views, fast_views = p.fast_views, on_the_spot = p.on_the_spot;
    const bool impostors = s.chunk_counts[4 * chunk + 2] > 0 && has_views;
    ChunkViews views_of;
    if (impostors && fast_views) even_views(p, f, begin, end, &views_of);
    const Character* characters = p.crowd->characters.data();
    const uint8_t* shown = s.shown.data();
    const ClipState* clip = s.clip.data();
    const glm::vec3* walked = s.feet.data();
    const uint32_t* nearest_layer = s.nearest_layer.data();
    const FrameWeights* frame_weights = s.frame_weights.data();
    const uint32_t last_pose = uint32_t(s.nearest_layer.size() - 1);
    const ClipSchedule& schedule = s.schedule;
    const float time_s = f.time_s;
    Instance* const lists[3] = {p.places.by_lod[0], p.places.by_lod[1], p.places.by_lod[2]};
    ImpostorSamples* const samples = p.places.impostor_samples;
    const bool nearest_samples = p.nearest_samples;
    for (size_t i = begin; i < end; ++i) {
        const uint8_t lod = shown[i];
        if (lod > 2) continue;
        const Character& c = characters[i];
        const glm::vec3 feet = on_the_spot ? c.start : walked[i];
        Instance inst;
        inst.position[0] = feet.x, inst.position[1] = feet.y, inst.position[2] = feet.z;
        inst.heading = c.heading;
        const uint32_t frame = shown_pose_frame(schedule, clip[i], c.rate, time_s);
        inst.frame = uint16_t(frame);
        inst.variation = uint16_t(c.variation);
        inst.outfit = uint16_t(c.outfit);
        inst.tile = 0;
        if (lod == uint8_t(Lod::impostor) && has_views) {
            const size_t k = i - begin;
            ImpostorSamples& out = samples[place[2]];
            uint32_t nearest_tile;
            if (fast_views && !views_of.tie[k]) {
                nearest_tile = uint32_t(views_of.nearest[k]);
                for (int m = 0; m < 4; ++m) {
                    out.tiles[m] = uint16_t(kBlendViews ? uint32_t(views_of.tiles[m][k]) : nearest_tile);
                    out.view_weights[m] = kBlendViews ? views_of.weights[m][k] : m == 0 ? 1.0f : 0.0f;
                }
            } else {
                const ViewWeights views = exact_views(p, f, glm::vec3(s.center_x[i], s.center_y[i], s.center_z[i]), c.heading, &nearest_tile);
                sort_views(views, &out);
            }
            const uint32_t pose = std::min(frame, last_pose);
            FrameWeights frames;
            if (kBlendFrames) frames = frame_weights[pose];
            else frames.layers[0] = frames.layers[1] = nearest_layer[pose];
            out.layers[0] = uint16_t(frames.layers[0]), out.layers[1] = uint16_t(frames.layers[1]);
            out.frame_weight = frames.weight;
            inst.tile = uint16_t(nearest_tile);
            inst.frame = uint16_t(frames.layers[frames.weight > 0.5f ? 1 : 0]);
            lists[2][place[2]++] = inst;
            continue;
        }
        if (lod == uint8_t(Lod::impostor) && nearest_samples) {  // upload_instances' samples for a frame without them
            ImpostorSamples& out = samples[place[2]];
            out = ImpostorSamples{};
            for (uint16_t& t : out.tiles) t = inst.tile;
            out.view_weights[0] = 1;
            out.layers[0] = out.layers[1] = inst.frame;
        }
        lists[lod][place[lod]++] = inst;
    }
}

// Runs task(0) .. task(count - 1) on up to `threads` threads, the calling one among them, each taking
// the next task as it finishes one (chunks of a crowd cost what their characters cost).
void run_tasks(size_t count, unsigned threads, const std::function<void(size_t)>& task) {
    std::atomic<size_t> next{0};
    auto work = [&]() {
        for (size_t t = next.fetch_add(1); t < count; t = next.fetch_add(1)) task(t);
    };
    std::vector<std::thread> helpers;
    for (size_t h = 1; h < std::min<size_t>(std::max(threads, 1u), count); ++h) helpers.emplace_back(work);
    work();
    for (std::thread& helper : helpers) helper.join();
}

// Everything of one archetype's frame before the passes: tables, clip schedule, per-frame arrays.
Pass prepare_pass(const ArchetypeFrame& a, float time_s) {
    FrameState* state = a.state;
    FrameInstances* out = a.out;
    const Crowd& crowd = *a.crowd;
    const CharacterModel& model = *a.model;
    const size_t n = crowd.characters.size();
    if (state->lod.size() != n) state->lod.assign(n, Lod(255));  // 255: no history yet
    if (crowd.layout == Layout::on_the_spot && !state->feet.empty()) {  // it walked: its fixed centres are gone
        state->feet.clear();
        state->crowd = nullptr;
    }
    const bool rebuilt = build_tables(crowd, model, state);
    prepare_clips(crowd, model, time_s, rebuilt, state);
    Pass p{&crowd, &model, a.rule, state, out, {}, (n + kChunk - 1) / kChunk, crowd.layout == Layout::on_the_spot, false, false, false, {}, {}};
    p.has_views = !model.azimuths_deg.empty() && !model.elevations_deg.empty();
    p.fast_views = p.has_views && state->even_azimuths && model.elevations_deg.size() <= 4;
    p.lod_steps = lod_steps(*a.rule);
    for (size_t e = 0; e < 4; ++e) p.elevations[e] = e < model.elevations_deg.size() ? model.elevations_deg[e] : INFINITY;
    state->shown.resize(n);
    if (!p.on_the_spot) state->feet.resize(n);
    state->chunk_counts.assign(4 * p.chunks, 0);
    state->chunk_offsets.assign(3 * p.chunks, 0);
    return p;
}

// Between the passes: each chunk's places, and room for the lists: FrameInstances' vectors, sized
// to hold them (growing only; no element is written twice), or the storage's memory.
void place_chunks(Pass* p, size_t archetype, InstanceStorage* storage) {
    FrameState& s = *p->state;
    FrameInstances& out = *p->out;
    uint32_t total[4] = {0, 0, 0, 0};
    for (size_t c = 0; c < p->chunks; ++c) {
        for (int l = 0; l < 3; ++l) s.chunk_offsets[3 * c + l] = total[l];
        for (int l = 0; l < 4; ++l) total[l] += s.chunk_counts[4 * c + l];
    }
    std::copy(total, total + 3, out.shown);
    out.culled = total[3];
    out.in_storage = storage != nullptr;
    if (storage) {
        for (std::vector<Instance>& list : out.by_lod) list.clear();
        out.impostor_samples.clear();
        p->nearest_samples = !p->has_views && storage->always_samples();
        p->places = storage->open(archetype, total, p->has_views || p->nearest_samples);
        return;
    }
    for (int l = 0; l < 3; ++l) out.by_lod[l].resize(total[l]), p->places.by_lod[l] = out.by_lod[l].data();
    out.impostor_samples.resize(p->has_views ? total[2] : 0);
    p->places.impostor_samples = out.impostor_samples.data();
}

}  // namespace

void build_frames(const std::vector<ArchetypeFrame>& archetypes, const Camera& camera, float aspect, LodMode mode, float time_s,
                  ImpostorBlend blend, unsigned threads, InstanceStorage* storage) {
    const bool all = blend == ImpostorBlend::full || blend == ImpostorBlend::warp;
    const FrameSetup setup{frustum_from(camera.projection(aspect) * camera.view()), camera.position, camera.forward(), mode, time_s,
                           blend == ImpostorBlend::views || all, blend == ImpostorBlend::frames || all};
    std::vector<Pass> passes;
    std::vector<std::pair<uint32_t, uint32_t>> tasks;  // (archetype, chunk)
    for (const ArchetypeFrame& a : archetypes) {
        a.out->blend = blend;
        passes.push_back(prepare_pass(a, time_s));
        for (size_t c = 0; c < passes.back().chunks; ++c) tasks.emplace_back(uint32_t(passes.size() - 1), uint32_t(c));
    }
    run_tasks(tasks.size(), threads, [&](size_t t) { cull_chunk(passes[tasks[t].first], setup, tasks[t].second); });
    for (size_t a = 0; a < passes.size(); ++a) place_chunks(&passes[a], a, storage);
    auto fill = setup.blend_views ? (setup.blend_frames ? fill_chunk<true, true> : fill_chunk<true, false>)
                                  : (setup.blend_frames ? fill_chunk<false, true> : fill_chunk<false, false>);
    run_tasks(tasks.size(), threads, [&](size_t t) { fill(passes[tasks[t].first], setup, tasks[t].second); });
    if (storage) storage->close();
}

void build_frame(const Crowd& crowd, const CharacterModel& model, const Camera& camera, float aspect, LodMode mode,
                 const LodRule& rule, float time_s, FrameState* state, FrameInstances* out, ImpostorBlend blend) {
    build_frames({ArchetypeFrame{&crowd, &model, &rule, state, out}}, camera, aspect, mode, time_s, blend, 1);
}

unsigned frame_threads() { return std::max(1u, std::thread::hardware_concurrency()); }

}  // namespace crowdview
