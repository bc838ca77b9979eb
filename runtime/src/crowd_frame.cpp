// One frame's instances for one archetype (crowd.h build_frame): the hot loop of a crowd.
// Per character it does a sphere-frustum test, a depth along the view (a dot product) for the
// LOD, a compare and a table lookup for the clip state (clips.h) and, for impostors, two
// arctangents for the view;
// everything that does not change between frames sits in FrameState.
#include <algorithm>
#include <cmath>
#include <thread>
#include <vector>

#include "crowd.h"

namespace crowdview {

namespace {

constexpr float kPi = 3.14159265358979323846f;
constexpr float kDegrees = 180.0f / kPi;

// floor(x) for |x| < 2^31 without a libm call (x86-64's baseline SSE2 has no rounding instruction).
inline float fast_floor(float x) {
    const float t = float(int32_t(x));
    return t > x ? t - 1.0f : t;
}

// sphere_in_frustum (crowd.h), inlined.
// All six planes without an early exit: one well-predicted branch instead of six.
inline bool sphere_visible(const Frustum& frustum, const glm::vec3& c, float radius) {
    bool inside = true;
    for (const glm::vec4& p : frustum.planes) inside &= p.x * c.x + p.y * c.y + p.z * c.z + p.w >= -radius;
    return inside;
}

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
    }
    s->clip_time_s = time_s;
}

// Returns whether the per-frame tables were rebuilt.
bool build_tables(const Crowd& crowd, const CharacterModel& model, FrameState* s) {
    if (s->crowd != &crowd || s->center_offset.size() != crowd.characters.size() || !(s->tables_for.center == model.center)) {
        s->crowd = &crowd;
        s->center_offset.resize(crowd.characters.size());
        for (size_t i = 0; i < crowd.characters.size(); ++i) {
            const float h = crowd.characters[i].heading, ch = std::cos(h), sh = std::sin(h);
            s->center_offset[i] = glm::vec2(ch * model.center.x + sh * model.center.z, -sh * model.center.x + ch * model.center.z);
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

void build_frame(const Crowd& crowd, const CharacterModel& model, const Camera& camera, float aspect, LodMode mode,
                 const LodRule& rule, float time_s, FrameState* state, FrameInstances* out, ImpostorBlend blend) {
    for (auto& list : out->by_lod) list.clear();
    out->impostor_samples.clear();
    out->blend = blend;
    out->culled = 0;
    const bool all = blend == ImpostorBlend::full || blend == ImpostorBlend::warp;
    const bool blend_views = blend == ImpostorBlend::views || all;
    const bool blend_frames = blend == ImpostorBlend::frames || all;
    const size_t n = crowd.characters.size();
    if (state->lod.size() != n) state->lod.assign(n, Lod(255));  // 255: no history yet
    const bool rebuilt = build_tables(crowd, model, state);
    prepare_clips(crowd, model, time_s, rebuilt, state);
    const FrameState& s = *state;
    const ClipSchedule& schedule = s.schedule;
    ClipState* clip_states = state->clip.data();
    const uint32_t columns = uint32_t(model.azimuths_deg.size());
    const bool has_views = columns > 0 && !model.elevations_deg.empty();
    const Frustum frustum = frustum_from(camera.projection(aspect) * camera.view());
    const glm::vec3 forward = camera.forward();
    for (size_t i = 0; i < n; ++i) {
        const Character& c = crowd.characters[i];
        // Clip state: nothing to do until the character's next switch event (a few times a minute).
        ClipState& clip = clip_states[i];
        if (time_s >= clip.next_event_s) advance_clip_state(schedule, uint32_t(i), c.rate, time_s, &clip);
        const glm::vec3 feet = crowd.layout == Layout::on_the_spot ? c.start : character_position(crowd, c, time_s);
        const glm::vec3 center(feet.x + s.center_offset[i].x, feet.y + model.center.y, feet.z + s.center_offset[i].y);
        if (!sphere_visible(frustum, center, model.radius)) {
            ++out->culled;
            continue;
        }
        Lod lod;
        switch (mode) {
        case LodMode::high: lod = Lod::high; break;
        case LodMode::low: lod = model.has_low ? Lod::low : Lod::high; break;
        case LodMode::impostor: lod = Lod::impostor; break;
        default: {
            const float depth = glm::dot(center - camera.position, forward);
            const Lod previous = state->lod[i];
            lod = uint8_t(previous) > 2 ? lod_without_history(depth, rule) : select_lod(depth, previous, rule);
        }
        }
        state->lod[i] = lod;
        Instance inst;
        inst.position[0] = feet.x, inst.position[1] = feet.y, inst.position[2] = feet.z;
        inst.heading = c.heading;
        inst.frame = shown_pose_frame(schedule, clip, c.rate, time_s);
        inst.variation = c.variation;
        inst.outfit = c.outfit;
        inst.tile = 0;
        if (lod == Lod::impostor && has_views) {
            ViewWeights views;
            uint32_t nearest_tile;
            if (s.even_azimuths) {
                const glm::vec2 angles = fast_view_angles_deg(camera.position - center, c.heading);
                // Near a tie, the exact angles (view_blend.h), so the choice is the one it makes.
                if (even_view_choice(angles, s, model.elevations_deg, columns, blend_views, &nearest_tile, &views))
                    even_view_choice(view_angles_deg(camera.position - center, c.heading), s, model.elevations_deg, columns, blend_views,
                                     &nearest_tile, &views);
            } else {
                const glm::vec2 angles = view_angles_deg(camera.position - center, c.heading);
                nearest_tile = nearest_view_weights(angles, model.azimuths_deg, model.elevations_deg).tiles[0];
                if (blend_views) views = blend_view_weights(angles, model.azimuths_deg, model.elevations_deg);
            }
            if (!blend_views) {
                for (uint32_t& t : views.tiles) t = nearest_tile;
                views.weights[0] = 1, views.weights[1] = views.weights[2] = views.weights[3] = 0;
            }
            const uint32_t pose = std::min(inst.frame, uint32_t(s.nearest_layer.size() - 1));
            FrameWeights frames;
            frames.layers[0] = frames.layers[1] = s.nearest_layer[pose];
            if (blend_frames) frames = s.frame_weights[pose];
            inst.tile = nearest_tile;
            inst.frame = frames.layers[frames.weight > 0.5f ? 1 : 0];
            // Heaviest first, weight-0 entries last (repeating the heaviest tile): an insertion
            // sort of four, stable as std::stable_sort is.
            int order[4] = {0, 1, 2, 3};
            for (int k = 1; k < 4; ++k)
                for (int j = k; j > 0 && views.weights[order[j]] > views.weights[order[j - 1]]; --j) std::swap(order[j], order[j - 1]);
            ImpostorSamples samples;
            for (int k = 0; k < 4; ++k) {
                const bool used = views.weights[order[k]] > 0;
                samples.tiles[k] = used ? views.tiles[order[k]] : views.tiles[order[0]];
                samples.view_weights[k] = used ? views.weights[order[k]] : 0.0f;
            }
            samples.layers[0] = frames.layers[0], samples.layers[1] = frames.layers[1];
            samples.frame_weight = frames.weight;
            samples.unused = 0;
            out->impostor_samples.push_back(samples);
        }
        out->by_lod[int(lod)].push_back(inst);
    }
}

void for_each_archetype(size_t count, unsigned threads, const std::function<void(size_t)>& build_one) {
    const size_t step = std::max<size_t>(1, std::min<size_t>(threads, count));
    auto work = [&](size_t first) {
        for (size_t a = first; a < count; a += step) build_one(a);
    };
    std::vector<std::thread> helpers;
    for (size_t t = 1; t < step; ++t) helpers.emplace_back(work, t);
    work(0);
    for (std::thread& helper : helpers) helper.join();
}

unsigned archetype_threads(size_t count) {
    return unsigned(std::max<size_t>(1, std::min<size_t>(count, std::max(1u, std::thread::hardware_concurrency()))));
}

}  // namespace crowdview
