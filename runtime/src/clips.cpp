// Clip playback (clips.h): the switch schedule and the per-range impostor tables.
#include "clips.h"

#include <algorithm>
#include <cmath>

namespace crowdview {

namespace {

// A character enters a range this fraction of a frame past its start, so float rounding of
// t * rate + phase (about 1e-3 frames at t = 300 s) never shows the frame before it.
constexpr double kEntryFrames = 0.01;

// A uniform number in [0, 1) for draw `kind` (0: dwell, 1: transition) after `switches` switches
// of character `index`: splitmix64's finaliser over the four, so no state is needed to replay it.
double draw(uint64_t seed, uint32_t index, uint32_t switches, uint32_t kind) {
    uint64_t z = seed ^ (uint64_t(index) * 0x9E3779B97F4A7C15ull) ^ ((uint64_t(switches) * 2 + kind + 1) * 0xD1B54A32D192ED03ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    z ^= z >> 31;
    return double(z >> 11) * (1.0 / 9007199254740992.0);
}

bool has_way_out(const ClipSchedule& s, uint32_t clip) { return s.out_begin[clip + 1] > s.out_begin[clip]; }

// The end of a dwell that starts at `arrival_s` in `clip`: INFINITY where nothing leaves it.
double dwell_end(const ClipSchedule& s, uint32_t index, uint32_t clip, uint32_t switches, double arrival_s) {
    if (!has_way_out(s, clip)) return INFINITY;
    const double lo = s.switch_after_s[0], hi = std::max(s.switch_after_s[0], s.switch_after_s[1]);
    return arrival_s + lo + (hi - lo) * draw(s.seed, index, switches, 0);
}

}  // namespace

std::string transition_name(const std::vector<ClipRange>& clips, const TransitionRange& t) {
    auto name = [&](uint32_t c) { return c < clips.size() ? clips[c].name : std::to_string(c); };
    return name(t.from_clip) + "->" + name(t.to_clip);
}

ClipSchedule make_clip_schedule(const std::vector<ClipRange>& clips, const std::vector<TransitionRange>& transitions,
                                uint32_t pose_frames, double frames_per_second, const ClipPlan& plan, uint64_t seed) {
    ClipSchedule s;
    s.frames_per_second = frames_per_second > 0 ? frames_per_second : 24;
    s.seed = seed;
    s.switch_after_s[0] = std::max(plan.switch_after_s[0], kMinDwellS);
    s.switch_after_s[1] = std::max(plan.switch_after_s[1], s.switch_after_s[0]);
    if (clips.empty()) {
        s.ranges.push_back({0, std::max(pose_frames, 1u), 0});
    } else {
        for (const ClipRange& c : clips) s.ranges.push_back({c.first_frame, std::max(c.frames, 1u), 0});
    }
    s.clip_count = uint32_t(s.ranges.size());
    for (const TransitionRange& t : transitions) {
        if (t.from_clip >= s.clip_count || t.to_clip >= s.clip_count || s.transitions.size() >= kNoTransition) continue;
        s.transitions.push_back(t);
        s.ranges.push_back({t.first_frame, std::max(t.frames, 1u), 1});
    }
    auto weight = [&](uint32_t clip) {
        if (plan.weights.empty()) return 1.0f;
        return clip < plan.weights.size() ? std::max(plan.weights[clip], 0.0f) : 0.0f;
    };
    s.out_begin.assign(1, 0);
    for (uint32_t c = 0; c < s.clip_count; ++c) {
        float total = 0;
        for (size_t k = 0; k < s.transitions.size(); ++k) {
            const TransitionRange& t = s.transitions[k];
            if (t.from_clip != c || !(weight(t.to_clip) > 0)) continue;
            total += weight(t.to_clip);
            s.outgoing.push_back(uint16_t(k));
            s.cumulative.push_back(total);
        }
        s.out_begin.push_back(uint32_t(s.outgoing.size()));
    }
    return s;
}

ClipState initial_clip_state(const ClipSchedule& schedule, uint32_t index, uint32_t clip, float phase_s) {
    ClipState state;
    state.range = uint16_t(std::min(clip, schedule.clip_count - 1));
    state.phase_s = phase_s;
    state.next_event_s = float(dwell_end(schedule, index, state.range, 0, 0.0));
    return state;
}

void advance_clip_state(const ClipSchedule& s, uint32_t index, float rate, float time_s, ClipState* state) {
    const double fps = s.frames_per_second, speed = double(rate) * fps;  // pose frames per second
    // Each pass handles one event; a dwell is at least a frame's worth of events apart, so the loop
    // ends, but a bound keeps a hostile rate or range from spinning.
    for (int events = 0; events < 1 << 16 && time_s >= state->next_event_s; ++events) {
        const double now = state->next_event_s;
        const ClipSchedule::Range& range = s.ranges[state->range];
        double next = INFINITY;
        if (range.transition) {
            // Arrive: loop frame arrive_frame of to_clip follows the transition's last frame.
            const TransitionRange& t = s.transitions[state->range - s.clip_count];
            state->range = uint16_t(t.to_clip);
            state->phase_s = float((t.arrive_frame + kEntryFrames) / fps - now * rate);
            if (state->switches < 0xffff) ++state->switches;
            state->waiting = 0;
            next = dwell_end(s, index, t.to_clip, state->switches, now);
        } else if (!state->waiting) {
            // The dwell is over: choose a way out by its target's weight, then wait for its leave frame.
            const uint32_t clip = state->range, begin = s.out_begin[clip], end = s.out_begin[clip + 1];
            if (begin == end) {
                state->next_event_s = INFINITY;
                break;
            }
            const float pick = float(draw(s.seed, index, state->switches, 1)) * s.cumulative[end - 1];
            uint32_t k = begin;
            while (k + 1 < end && s.cumulative[k] <= pick) ++k;
            state->transition = s.outgoing[k];
            state->waiting = 1;
            // The loop shows frame leave_frame while its position p (mod frames) is in
            // [leave, leave + 1): it leaves when p next reaches leave + 1.
            const TransitionRange& t = s.transitions[state->transition];
            const double frames = range.frames, boundary = t.leave_frame + 1.0;
            const double position = (now * rate + state->phase_s) * fps;
            const double leave_at = boundary + frames * std::ceil((position - boundary) / frames);
            next = std::max(now, (leave_at / fps - state->phase_s) / rate);
        } else {
            // Leave: the transition's frame 0 follows loop frame leave_frame.
            const TransitionRange& t = s.transitions[state->transition];
            state->range = uint16_t(s.clip_count + state->transition);
            state->phase_s = float(kEntryFrames / fps - now * rate);
            state->waiting = 0;
            next = now + double(std::max(t.frames, 1u)) / speed;
        }
        // Stored as float: the next pass and every frame read the same value.
        state->next_event_s = float(std::max(next, now));
        if (state->next_event_s == float(now) && next > now) state->next_event_s = std::nextafter(float(now), INFINITY);
    }
}

void impostor_frame_tables(const std::vector<uint32_t>& frame_indices, const ClipSchedule& schedule, uint32_t pose_frames,
                           std::vector<uint32_t>* nearest_layer, std::vector<FrameWeights>* frame_weights) {
    const uint32_t frames = std::max(pose_frames, 1u);
    nearest_layer->assign(frames, 0);
    frame_weights->assign(frames, FrameWeights());
    if (frame_indices.empty()) return;
    // Every pose frame first from all baked frames round the whole bundle (v1's rule), so frames
    // outside every range, or in a range without a baked frame, still get a layer.
    std::vector<uint32_t> local;
    for (uint32_t f = 0; f < frames; ++f) {
        uint32_t best = 0, best_gap = UINT32_MAX;
        for (uint32_t k = 0; k < frame_indices.size(); ++k) {
            const uint32_t d = f > frame_indices[k] ? f - frame_indices[k] : frame_indices[k] - f;
            const uint32_t gap = std::min(d, frames > d ? frames - d : d);
            if (gap < best_gap) best = k, best_gap = gap;
        }
        (*nearest_layer)[f] = best;
        (*frame_weights)[f] = blend_frame_weights(f, frame_indices, frames);
    }
    for (const ClipSchedule::Range& r : schedule.ranges) {
        const uint64_t end = std::min<uint64_t>(uint64_t(r.first_frame) + r.frames, frames);
        const auto lo = std::lower_bound(frame_indices.begin(), frame_indices.end(), r.first_frame);
        const auto hi = std::lower_bound(lo, frame_indices.end(), uint32_t(std::min<uint64_t>(end, UINT32_MAX)));
        if (lo == hi || r.first_frame >= end) continue;
        const uint32_t offset = uint32_t(lo - frame_indices.begin());
        local.assign(lo, hi);
        for (uint32_t& f : local) f -= r.first_frame;
        for (uint32_t f = r.first_frame; f < end; ++f) {
            const uint32_t k = f - r.first_frame;  // frame within the range
            FrameWeights w;
            uint32_t nearest = 0;
            if (!r.transition) {  // round the loop
                w = blend_frame_weights(k, local, r.frames);
                uint32_t best_gap = UINT32_MAX;
                for (uint32_t j = 0; j < local.size(); ++j) {
                    const uint32_t d = k > local[j] ? k - local[j] : local[j] - k;
                    const uint32_t gap = std::min(d, r.frames > d ? r.frames - d : d);
                    if (gap < best_gap) nearest = j, best_gap = gap;
                }
            } else {  // once through, clamped at both ends
                uint32_t j = 0;
                while (j + 1 < local.size() && local[j + 1] <= k) ++j;
                if (k <= local.front() || j + 1 == local.size()) {
                    w.layers[0] = w.layers[1] = k <= local.front() ? 0 : j;
                } else {
                    w.layers[0] = j, w.layers[1] = j + 1;
                    w.weight = float(double(k - local[j]) / double(local[j + 1] - local[j]));
                }
                nearest = w.weight > 0.5f ? w.layers[1] : w.layers[0];  // ties to the earlier, as round a loop
            }
            w.layers[0] += offset, w.layers[1] += offset;
            (*nearest_layer)[f] = nearest + offset;
            (*frame_weights)[f] = w;
        }
    }
}

}  // namespace crowdview
