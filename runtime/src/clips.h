// Clip playback (SPEC.md "Playback"), without GL: per character a clip, a phase and a play rate,
// and a deterministic schedule of switches that go only through the transitions the bake simulated.
//
// A character dwells in a clip for a time drawn in [switch_after_s[0], switch_after_s[1]] seconds,
// then picks one of the transitions leaving its clip (weighted by the clip mix weight of the clip it
// leads to; none with a weight above 0: it stays), keeps looping until that transition's leave
// frame has been shown, plays the transition once and arrives at its arrive frame of the next clip,
// where it dwells again. Every draw comes from a hash of (seed, character, switch count), so the
// schedule is a function of time alone: the same at any frame rate, and the same in every run.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "view_blend.h"

namespace crowdview {

// A bundle's ranges of pose frames as the crowd needs them (bundle.h ClipInfo, TransitionInfo).
struct ClipRange {
    std::string name;
    uint32_t first_frame = 0, frames = 1;
};
struct TransitionRange {
    uint32_t from_clip = 0, to_clip = 0;          // clip indices
    uint32_t leave_frame = 0, arrive_frame = 0;  // loop frames of from_clip and to_clip
    uint32_t first_frame = 0, frames = 1;
    bool operator==(const TransitionRange& o) const {
        return from_clip == o.from_clip && to_clip == o.to_clip && leave_frame == o.leave_frame &&
               arrive_frame == o.arrive_frame && first_frame == o.first_frame && frames == o.frames;
    }
};

// The range's name for reports: the clip's name, or "FROM->TO" for a transition.
std::string transition_name(const std::vector<ClipRange>& clips, const TransitionRange& t);

// Seconds a character dwells in a clip before it looks for a way out (--switch-after): long enough
// to read as a motion, short enough that a 10 s shot shows switches.
constexpr float kDefaultSwitchAfterS[2] = {4, 10};

// The shortest dwell a schedule plays (a shorter switch_after_s is raised to it): a character then
// switches at most about ten times a second whatever the description asks, so the schedule's
// events per frame stay a handful even for 1-frame clips at the highest frame rate a bundle may
// have (SPEC.md "Crowd description").
constexpr float kMinDwellS = 0.1f;

// How an archetype's characters use the clips: the mix and the dwell range.
struct ClipPlan {
    std::vector<float> weights;  // per clip of the bundle, >= 0; empty: every clip weighs 1
    float switch_after_s[2] = {kDefaultSwitchAfterS[0], kDefaultSwitchAfterS[1]};
    bool operator==(const ClipPlan& o) const {
        return weights == o.weights && switch_after_s[0] == o.switch_after_s[0] && switch_after_s[1] == o.switch_after_s[1];
    }
};

constexpr uint16_t kNoTransition = 0xffff;

// One character's playback (16 bytes; build_frame keeps one per character). The range it is in
// shows frame floor((t * rate + phase_s) * fps) of the range: wrapped round a clip, clamped in a
// transition. Nothing changes before next_event_s.
struct ClipState {
    float phase_s = 0;
    float next_event_s = 0;           // INFINITY: no change to come (e.g. a clip nothing leaves)
    uint16_t range = 0;               // clips 0..C-1, then transitions C..C+T-1
    uint16_t transition = kNoTransition;  // the transition chosen last
    uint16_t switches = 0;            // clips arrived in after the first (saturating)
    uint8_t waiting = 0;              // 1: the dwell is over, it loops on until `transition` leaves
    uint8_t unused = 0;
};
static_assert(sizeof(ClipState) == 16, "one cache line holds four");

// The tables the schedule reads, built once per archetype from its ranges and plan.
struct ClipSchedule {
    struct Range {
        uint32_t first_frame = 0, frames = 1;
        uint32_t transition = 0;  // 1 for a transition (played once, clamped)
    };
    std::vector<Range> ranges;  // clips, then transitions
    std::vector<TransitionRange> transitions;
    uint32_t clip_count = 1;
    // Per clip c: the transitions leaving it with a target weight > 0, outgoing[out_begin[c] ..
    // out_begin[c + 1]), and their running sum of target weights (cumulative[..] ascending).
    std::vector<uint32_t> out_begin;
    std::vector<uint16_t> outgoing;
    std::vector<float> cumulative;
    float switch_after_s[2] = {kDefaultSwitchAfterS[0], kDefaultSwitchAfterS[1]};
    double frames_per_second = 24;
    uint64_t seed = 0;
};

// The schedule for ranges `clips` and `transitions` (no clips: one clip over all `pose_frames`),
// played at `frames_per_second`. plan.weights empty: every clip weighs 1; otherwise clips past its
// end weigh 0. The dwell range is plan.switch_after_s, each end at least kMinDwellS. Transitions naming a clip that does not exist are left out.
ClipSchedule make_clip_schedule(const std::vector<ClipRange>& clips, const std::vector<TransitionRange>& transitions,
                                uint32_t pose_frames, double frames_per_second, const ClipPlan& plan, uint64_t seed);

// Character `index` at time 0: in clip `clip` (clamped to the clips) with phase `phase_s`.
ClipState initial_clip_state(const ClipSchedule& schedule, uint32_t index, uint32_t clip, float phase_s);

// Plays every change of character `index` (play rate `rate` > 0) due at or before `time_s`:
// dwell over (a transition is chosen and its leave time set), leave, arrive. Call when
// time_s >= state->next_event_s; times must not go back (start again from initial_clip_state).
void advance_clip_state(const ClipSchedule& schedule, uint32_t index, float rate, float time_s, ClipState* state);

// floor(x) for |x| < 2^63, float or double, without a libm call (x86-64's baseline SSE2 has no
// rounding instruction).
template <typename Real>
inline Real fast_floor(Real x) {
    const Real t = Real(int64_t(x));
    return t > x ? t - Real(1) : t;
}

// The loop frame floor((t * rate + phase) * fps) mod frames, as crowd.h cycle_frame, computed
// in the same precision (float time and phase, double product), so a v1 bundle shows the same
// frames on either path.
inline uint32_t loop_frame(float scaled_time_s, float phase_s, double frames_per_second, uint32_t frame_count) {
    if (frame_count == 0) return 0;
    const double f = fast_floor(double(scaled_time_s + phase_s) * frames_per_second);
    if (f > -2147483647.0 && f < 2147483647.0) {  // a 32-bit remainder: a fraction of a 64-bit one's latency
        const int32_t wrapped = int32_t(f) % int32_t(frame_count);
        return uint32_t(wrapped < 0 ? wrapped + int32_t(frame_count) : wrapped);
    }
    const int64_t wrapped = int64_t(f) % int64_t(frame_count);
    return uint32_t(wrapped < 0 ? wrapped + frame_count : wrapped);
}

// The pose frame (bundle-wide) a character in `state` shows at `time_s`: its range's frame,
// wrapped round a clip, clamped in a transition. build_frame's hot loop inlines this.
inline uint32_t shown_pose_frame(const ClipSchedule& schedule, const ClipState& state, float rate, float time_s) {
    const ClipSchedule::Range& r = schedule.ranges[state.range];
    if (!r.transition) return r.first_frame + loop_frame(time_s * rate, state.phase_s, schedule.frames_per_second, r.frames);
    const double f = fast_floor(double(time_s * rate + state.phase_s) * schedule.frames_per_second);
    return r.first_frame + uint32_t(f <= 0 ? 0.0 : f >= double(r.frames - 1) ? double(r.frames - 1) : f);
}

// Per pose frame, the impostor's nearest baked layer and the two layers it blends, from the baked
// layers of the range holding the frame (SPEC.md "Playback", impostors): in a clip they wrap round
// the clip's range; in a transition they do not (before its first baked frame or after its last,
// that one alone). A range without a baked frame (not a valid bundle) uses the nearest over all.
// frame_indices ascending, not empty; both outputs get pose_frames entries.
void impostor_frame_tables(const std::vector<uint32_t>& frame_indices, const ClipSchedule& schedule, uint32_t pose_frames,
                           std::vector<uint32_t>* nearest_layer, std::vector<FrameWeights>* frame_weights);

}  // namespace crowdview
