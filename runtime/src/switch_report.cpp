// --report's clip counts and switch measure (switch_report.h).
#include "switch_report.h"

#include <algorithm>
#include <cmath>

#include <glm/gtc/matrix_transform.hpp>

#include "pose_codec.h"

namespace crowdview {

namespace {

const char* kLodNames[3] = {"high", "low", "impostor"};

glm::vec3 feet_at(const Crowd& crowd, const Character& c, float time_s) {
    return crowd.layout == Layout::on_the_spot ? c.start : character_position(crowd, c, time_s);
}

bool on_screen(const Frustum& frustum, const CharacterModel& model, const Character& c, const glm::vec3& feet) {
    const float ch = std::cos(c.heading), sh = std::sin(c.heading);
    const glm::vec3 center = feet + glm::vec3(ch * model.center.x + sh * model.center.z, model.center.y, -sh * model.center.x + ch * model.center.z);
    return sphere_in_frustum(frustum, center, model.radius);
}

double rms_motion(const std::vector<glm::vec2>& a, const std::vector<glm::vec2>& b) {
    if (a.empty() || a.size() != b.size()) return 0;
    double sum = 0;
    for (size_t i = 0; i < a.size(); ++i) {
        const glm::vec2 d = a[i] - b[i];
        sum += double(d.x) * d.x + double(d.y) * d.y;
    }
    return std::sqrt(sum / double(a.size()));
}

double median_of(std::vector<double> v) {
    if (v.empty()) return 0;
    std::sort(v.begin(), v.end());
    return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
}

// Forward steps from loop frame `from` to loop frame `to` of a clip of `frames` frames.
uint32_t loop_steps(uint32_t from, uint32_t to, uint32_t frames) { return (to + frames - from % frames) % frames; }

// The schedule's ranges by name: clips, then transitions "FROM->TO".
std::vector<std::string> range_names(const CharacterModel& model, const ClipSchedule& schedule) {
    std::vector<std::string> names;
    for (uint32_t c = 0; c < schedule.clip_count; ++c) names.push_back(c < model.clips.size() ? model.clips[c].name : "cycle");
    for (const TransitionRange& t : schedule.transitions) {
        std::string name = transition_name(model.clips, t);
        while (std::find(names.begin(), names.end(), name) != names.end()) name += "'";  // two transitions between one pair
        names.push_back(name);
    }
    return names;
}

}  // namespace

nlohmann::json clip_counts(const Crowd& crowd, const CharacterModel& model, const FrameState& state, const Camera& camera,
                           float aspect, float time_s) {
    const ClipSchedule& schedule = state.schedule;
    const std::vector<std::string> names = range_names(model, schedule);
    std::vector<uint64_t> counts(names.size() * 3, 0);
    uint64_t switched = 0, switches = 0;
    const Frustum frustum = frustum_from(camera.projection(aspect) * camera.view());
    for (size_t i = 0; i < crowd.characters.size() && i < state.clip.size() && i < state.lod.size(); ++i) {
        const ClipState& clip = state.clip[i];
        switched += clip.switches > 0;
        switches += clip.switches;
        const Character& c = crowd.characters[i];
        if (uint8_t(state.lod[i]) > 2 || clip.range >= names.size() || !on_screen(frustum, model, c, feet_at(crowd, c, time_s))) continue;
        ++counts[clip.range * 3 + int(state.lod[i])];
    }
    nlohmann::json by_range = nlohmann::json::object();
    for (size_t r = 0; r < names.size(); ++r)
        by_range[names[r]] = {{"high", counts[r * 3]}, {"low", counts[r * 3 + 1]}, {"impostor", counts[r * 3 + 2]}};
    return {{"counts", by_range}, {"characters", crowd.characters.size()}, {"characters_switched", switched}, {"switches", switches}};
}

SwitchMeter::SwitchMeter(std::shared_ptr<const std::vector<PoseCache>> meshes, const std::vector<MeshInfo>& infos)
    : meshes_(std::move(meshes)) {
    for (uint32_t m = 0; m < infos.size() && m < meshes_->size(); ++m)
        if (infos[m].lod <= 1) parts_[infos[m].lod].push_back(m);
    if (parts_[1].empty()) parts_[1] = parts_[0];
    for (int lod = 0; lod < 2; ++lod) {
        uint64_t total = 0;
        for (uint32_t m : parts_[lod]) total += (*meshes_)[m].vertex_count;
        const uint64_t stride = std::max<uint64_t>(1, (total + kMeterVertices - 1) / kMeterVertices);
        uint64_t index = 0;  // over the parts' vertices in order
        for (uint32_t m : parts_[lod])
            for (uint32_t v = 0; v < (*meshes_)[m].vertex_count; ++v, ++index)
                if (index % stride == 0) vertices_[lod].insert(vertices_[lod].end(), {m, v});
    }
}

namespace {

// The pose a representation shows at a pose frame: a mesh its frame; an impostor the baked frames
// it blends (frame_weights, or the nearest alone without frame blending).
struct ShownPose {
    uint32_t a, b;
    float weight;
};

ShownPose shown_pose(const CharacterModel& model, const FrameState& state, Lod lod, uint32_t pose_frame, bool blend_frames) {
    if (lod != Lod::impostor || model.frame_indices.empty() || state.nearest_layer.empty()) return {pose_frame, pose_frame, 0.0f};
    const uint32_t f = std::min<uint32_t>(pose_frame, uint32_t(state.nearest_layer.size() - 1));
    FrameWeights w;
    w.layers[0] = w.layers[1] = state.nearest_layer[f];
    if (blend_frames) w = state.frame_weights[f];
    const uint32_t last = uint32_t(model.frame_indices.size() - 1);
    return {model.frame_indices[std::min(w.layers[0], last)], model.frame_indices[std::min(w.layers[1], last)], w.weight};
}

}  // namespace

void SwitchMeter::picture(int mesh_lod, const Shown& shown, const glm::mat4& to_screen, int width, int height,
                          std::vector<glm::vec2>* pixels) const {
    const std::vector<uint32_t>& list = vertices_[mesh_lod];
    pixels->resize(list.size() / 2);
    for (size_t k = 0; k + 1 < list.size(); k += 2) {
        const PoseCache& cache = (*meshes_)[list[k]];
        const uint32_t a = std::min(shown.a, cache.frame_count - 1), b = std::min(shown.b, cache.frame_count - 1);
        float pa[3], pb[3];
        decode_pose_position(cache, a, list[k + 1], pa);
        decode_pose_position(cache, b, list[k + 1], pb);
        const float w = shown.weight;
        const glm::vec4 clip = to_screen * glm::vec4((1 - w) * pa[0] + w * pb[0], (1 - w) * pa[1] + w * pb[1], (1 - w) * pa[2] + w * pb[2], 1.0f);
        const float iw = clip.w > 1e-6f ? 1.0f / clip.w : 0.0f;
        (*pixels)[k / 2] = glm::vec2((clip.x * iw + 1.0f) * 0.5f * float(width), (clip.y * iw + 1.0f) * 0.5f * float(height));
    }
}

double SwitchMeter::clip_reference(const CharacterModel& model, const FrameState& state, uint32_t clip, uint32_t steps, Lod lod,
                                   bool blend_frames, const glm::mat4& to_screen, int width, int height) const {
    const ClipSchedule::Range& range = state.schedule.ranges[clip];
    const int mesh_lod = lod == Lod::low ? 1 : 0;
    std::vector<std::vector<glm::vec2>> pictures(range.frames);
    for (uint32_t k = 0; k < range.frames; ++k) {
        const ShownPose p = shown_pose(model, state, lod, range.first_frame + k, blend_frames);
        picture(mesh_lod, {p.a, p.b, p.weight}, to_screen, width, height, &pictures[k]);
    }
    std::vector<double> motions;
    for (uint32_t k = 0; k < range.frames; ++k)
        if (const double m = rms_motion(pictures[k], pictures[(k + steps) % range.frames]); m > 0) motions.push_back(m);
    return median_of(motions);
}

struct SwitchMeter::Switch {
    Lod lod = Lod::high;
    uint32_t range_before = 0, range_after = 0;  // clips 0..C-1, then transitions
    uint32_t frame_before = 0, frame_after = 0;  // frames within those ranges
    uint32_t pose_before = 0, pose_after = 0;    // the pose frames shown
    uint32_t steps = 0;                          // pose frames stepped along the character's way
    const TransitionRange* transition = nullptr;  // the transition entered, left or passed
    glm::mat4 to_screen{1};                       // view-projection times the character's placement
};

namespace {

// The pose frames a character stepped from frame `local0` of range r0 to frame `local1` of range
// r1, and the transition it entered, left or passed (`transition`: the one its clip state names);
// 0 steps where the change is none of those.
uint32_t switch_steps(const ClipSchedule& schedule, uint32_t r0, uint32_t r1, uint32_t local0, uint32_t local1, uint32_t transition,
                      const TransitionRange** tr) {
    const uint32_t C = schedule.clip_count;
    if (r0 < C && r1 >= C) {  // entered a transition
        *tr = &schedule.transitions[r1 - C];
        return loop_steps(local0, (*tr)->leave_frame, schedule.ranges[r0].frames) + 1 + local1;
    }
    if (r0 >= C && r1 < C) {  // left one
        *tr = &schedule.transitions[r0 - C];
        return ((*tr)->frames - 1 - local0) + 1 + loop_steps((*tr)->arrive_frame, local1, schedule.ranges[r1].frames);
    }
    if (r0 < C && r1 < C && transition < schedule.transitions.size() && schedule.transitions[transition].from_clip == r0 &&
        schedule.transitions[transition].to_clip == r1) {
        *tr = &schedule.transitions[transition];  // a whole transition between two frames
        return loop_steps(local0, (*tr)->leave_frame, schedule.ranges[r0].frames) + 1 + (*tr)->frames +
               loop_steps((*tr)->arrive_frame, local1, schedule.ranges[r1].frames);
    }
    return 0;
}

}  // namespace

void SwitchMeter::pick_characters(const Crowd& crowd, const CharacterModel& model, const FrameState& state, const Frustum& frustum,
                                  size_t n, float time_s) {
    picked_ = true;
    range_names_ = range_names(model, state.schedule);
    for (int lod = 0; lod < 3; ++lod) {
        std::vector<uint32_t> candidates;
        for (uint32_t i = 0; i < n; ++i)
            if (int(state.lod[i]) == lod && on_screen(frustum, model, crowd.characters[i], feet_at(crowd, crowd.characters[i], time_s)))
                candidates.push_back(i);
        const size_t take = std::min<size_t>(kMeterCharacters, candidates.size());
        sampled_[lod] = uint32_t(take);
        for (size_t k = 0; k < take; ++k) {
            Tracked t;
            t.character = candidates[k * candidates.size() / take];
            tracked_.push_back(t);
        }
    }
}

void SwitchMeter::measure_switch(const Switch& s, const CharacterModel& model, const FrameState& state, bool blend_frames, int width,
                                 int height) {
    const int l = int(s.lod), mesh_lod = s.lod == Lod::low ? 1 : 0;
    const ClipSchedule& schedule = state.schedule;
    auto pose_picture = [&](uint32_t pose_frame, std::vector<glm::vec2>* pixels) {
        const ShownPose p = shown_pose(model, state, s.lod, pose_frame, blend_frames);
        picture(mesh_lod, {p.a, p.b, p.weight}, s.to_screen, width, height, pixels);
    };
    std::vector<glm::vec2> before, after;
    pose_picture(s.pose_before, &before);
    pose_picture(s.pose_after, &after);
    double reference = 0;
    for (uint32_t side : {s.transition->from_clip, s.transition->to_clip})
        reference = std::max(reference, clip_reference(model, state, side, s.steps, s.lod, blend_frames, s.to_screen, width, height));
    // What the clip beside the switch would have moved over the same steps had the character
    // not switched: on from its frame before the switch, or up to its frame after it.
    const bool entering = s.range_after >= schedule.clip_count;
    const ClipSchedule::Range& range = schedule.ranges[entering ? s.range_before : s.range_after];
    const uint32_t from = entering ? s.frame_before : (s.frame_after + range.frames - s.steps % range.frames) % range.frames;
    std::vector<glm::vec2> still, moved;
    pose_picture(range.first_frame + from, &still);
    pose_picture(range.first_frame + (from + s.steps) % range.frames, &moved);
    if (reference > 0)
        events_[l].push_back({rms_motion(before, after), reference, rms_motion(still, moved), s.range_before, s.range_after,
                              s.frame_before, s.frame_after});
    else
        ++unmeasured_[l];
}

void SwitchMeter::observe(const Crowd& crowd, const CharacterModel& model, const FrameState& state, const Camera& camera, int width,
                          int height, float time_s, bool blend_frames) {
    const float aspect = float(width) / float(std::max(height, 1));
    const glm::mat4 view_projection = camera.projection(aspect) * camera.view();
    const Frustum frustum = frustum_from(view_projection);
    const size_t n = std::min({crowd.characters.size(), state.lod.size(), state.clip.size()});
    if (!picked_) pick_characters(crowd, model, state, frustum, n, time_s);
    const ClipSchedule& schedule = state.schedule;
    for (Tracked& t : tracked_) {
        if (t.character >= n) continue;
        const Character& c = crowd.characters[t.character];
        const glm::vec3 feet = feet_at(crowd, c, time_s);
        const bool visible = on_screen(frustum, model, c, feet);
        const Lod lod = state.lod[t.character];
        const ClipState& clip = state.clip[t.character];
        const uint32_t pose_frame = shown_pose_frame(schedule, clip, c.rate, time_s);
        if (t.seen && t.visible && visible && t.lod == lod && t.clip.range != clip.range && uint8_t(lod) <= 2) {
            Switch s;
            s.lod = lod;
            s.range_before = t.clip.range, s.range_after = clip.range;
            s.frame_before = t.pose_frame - schedule.ranges[s.range_before].first_frame;
            s.frame_after = pose_frame - schedule.ranges[s.range_after].first_frame;
            s.pose_before = t.pose_frame, s.pose_after = pose_frame;
            s.steps = switch_steps(schedule, s.range_before, s.range_after, s.frame_before, s.frame_after, clip.transition, &s.transition);
            s.to_screen = view_projection * glm::rotate(glm::translate(glm::mat4(1), feet), c.heading, glm::vec3(0, 1, 0));
            if (s.steps == 0 || !s.transition) ++unmeasured_[int(lod)];
            else measure_switch(s, model, state, blend_frames, width, height);
        }
        t.seen = true, t.visible = visible, t.lod = lod, t.clip = clip, t.pose_frame = pose_frame;
    }
}

nlohmann::json SwitchMeter::report() const {
    nlohmann::json out = nlohmann::json::object();
    for (int l = 0; l < 3; ++l) {
        nlohmann::json r = {{"sampled_characters", sampled_[l]}, {"switches_measured", events_[l].size()}, {"switches_unmeasured", unmeasured_[l]},
                            {"largest_ratio", nullptr}, {"jump_px", nullptr}, {"reference_px", nullptr}, {"median_ratio", nullptr},
                            {"largest_ratio_same_phase", nullptr}, {"worst", nullptr}};
        if (!events_[l].empty()) {
            std::vector<double> ratios;
            size_t worst = 0;
            for (size_t k = 0; k < events_[l].size(); ++k) {
                ratios.push_back(events_[l][k].jump_px / events_[l][k].reference_px);
                if (ratios[k] > ratios[worst]) worst = k;
            }
            r["largest_ratio"] = ratios[worst];
            r["jump_px"] = events_[l][worst].jump_px;
            r["reference_px"] = events_[l][worst].reference_px;
            r["median_ratio"] = median_of(ratios);
            double same_phase = 0;
            for (const Event& e : events_[l]) same_phase = std::max(same_phase, e.jump_px / std::max(e.continued_px, e.reference_px));
            r["largest_ratio_same_phase"] = same_phase;
            const Event& e = events_[l][worst];
            auto name = [&](uint32_t r) { return r < range_names_.size() ? range_names_[r] : std::to_string(r); };
            r["worst"] = {{"from", name(e.range_before)}, {"from_frame", e.frame_before}, {"to", name(e.range_after)}, {"to_frame", e.frame_after}};
        }
        out[kLodNames[l]] = r;
    }
    return out;
}

double SwitchMeter::largest_ratio(Lod lod) const {
    double worst = 0;
    for (const Event& e : events_[int(lod)]) worst = std::max(worst, e.jump_px / e.reference_px);
    return worst;
}

}  // namespace crowdview
