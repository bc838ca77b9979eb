// Clip playback (clips.h): the switch schedule and the per-range impostor tables, on small ranges
// whose answers are known by construction.
#include <cmath>
#include <map>

#include "check.h"
#include "clips.h"
#include "crowd.h"

using namespace crowdview;

namespace {

// Three clips: a (8 frames), b (6), c (5, nothing leaves it); a -> b leaves a at 5 and arrives at
// b's 2 over 3 frames; b -> a leaves b at 0 and arrives at a's 7 over 4 frames. 26 pose frames.
std::vector<ClipRange> kClips = {{"a", 0, 8}, {"b", 8, 6}, {"c", 14, 5}};
std::vector<TransitionRange> kTransitions = {{0, 1, 5, 2, 19, 3}, {1, 0, 0, 7, 22, 4}};
constexpr uint32_t kPoseFrames = 26;
constexpr double kFps = 24;

ClipSchedule schedule(const ClipPlan& plan = ClipPlan(), uint64_t seed = 7) {
    return make_clip_schedule(kClips, kTransitions, kPoseFrames, kFps, plan, seed);
}

ClipPlan quick_plan() {
    ClipPlan plan;
    plan.switch_after_s[0] = 0.2f, plan.switch_after_s[1] = 0.9f;
    return plan;
}

// The clip frame of pose frame `f` in range `r`.
uint32_t local(const ClipSchedule& s, uint32_t r, uint32_t f) { return f - s.ranges[r].first_frame; }

// Played at `hz` samples a second for `seconds`: every sample's (range, pose frame).
std::vector<std::pair<uint32_t, uint32_t>> play(const ClipSchedule& s, uint32_t index, uint32_t clip, float phase, float rate,
                                                double hz, double seconds) {
    std::vector<std::pair<uint32_t, uint32_t>> shown;
    ClipState state = initial_clip_state(s, index, clip, phase);
    for (int k = 0; k <= int(seconds * hz); ++k) {
        const float t = float(k / hz);
        if (t >= state.next_event_s) advance_clip_state(s, index, rate, t, &state);
        shown.push_back({state.range, shown_pose_frame(s, state, rate, t)});
    }
    return shown;
}

void test_switches_go_through_transitions_at_their_frames() {
    const ClipSchedule s = schedule(quick_plan());
    CHECK(s.clip_count == 3 && s.ranges.size() == 5);
    int enters = 0, leaves = 0;
    for (uint32_t index = 0; index < 40; ++index) {
        const float rate = 0.8f + 0.01f * float(index);
        // 480 samples a second: every pose frame (24 fps at most 1.2x) is seen at least once.
        const auto shown = play(s, index, index % 2, 0.1f * float(index), rate, 480, 20);
        for (size_t k = 1; k < shown.size(); ++k) {
            const auto [r0, f0] = shown[k - 1];
            const auto [r1, f1] = shown[k];
            CHECK(f1 >= s.ranges[r1].first_frame && f1 < s.ranges[r1].first_frame + s.ranges[r1].frames);
            if (r0 == r1) continue;
            if (r0 < 3) {  // a clip into a transition: one leaving this clip, right after its leave frame
                CHECK_MSG(r1 >= 3, "clip to clip without a transition");
                const TransitionRange& t = s.transitions[r1 - 3];
                CHECK(t.from_clip == r0 && local(s, r0, f0) == t.leave_frame && local(s, r1, f1) == 0);
                ++enters;
            } else {  // a transition into the clip it leads to, at its arrive frame, after its last frame
                const TransitionRange& t = s.transitions[r0 - 3];
                CHECK(r1 == t.to_clip && local(s, r0, f0) == t.frames - 1 && local(s, r1, f1) == t.arrive_frame);
                ++leaves;
            }
        }
        // Inside a clip frames step forward round the loop, inside a transition forward once.
        for (size_t k = 1; k < shown.size(); ++k)
            if (shown[k].first == shown[k - 1].first) {
                const uint32_t r = shown[k].first, a = local(s, r, shown[k - 1].second), b = local(s, r, shown[k].second);
                CHECK(b == a || b == (a + 1) % s.ranges[r].frames);
            }
    }
    CHECK_MSG(enters > 100 && leaves > 100, "switches happened: " + std::to_string(enters) + " in, " + std::to_string(leaves) + " out");
}

void test_schedule_is_a_function_of_time() {
    // The same character sampled at 30 Hz and at 7 Hz shows the same frame at whole seconds, where
    // both sample, and a second run at 30 Hz shows what the first did.
    const ClipSchedule s = schedule(quick_plan());
    for (uint32_t index = 0; index < 10; ++index) {
        const auto fine = play(s, index, 0, 0.05f * float(index), 1.1f, 30, 30);
        const auto coarse = play(s, index, 0, 0.05f * float(index), 1.1f, 7, 30);
        const auto again = play(s, index, 0, 0.05f * float(index), 1.1f, 30, 30);
        CHECK(fine == again);
        for (int second = 0; second <= 30; ++second) CHECK(fine[size_t(second) * 30] == coarse[size_t(second) * 7]);
    }
    // Another seed gives another schedule.
    const auto one = play(schedule(quick_plan(), 1), 3, 0, 0, 1, 30, 30), two = play(schedule(quick_plan(), 2), 3, 0, 0, 1, 30, 30);
    CHECK(one != two);
}

void test_a_clip_nothing_leaves_keeps_its_characters() {
    const ClipSchedule s = schedule(quick_plan());
    const ClipState state = initial_clip_state(s, 0, 2, 0);
    CHECK(state.range == 2 && std::isinf(state.next_event_s));
    for (const auto& [range, frame] : play(s, 5, 2, 0.3f, 1, 30, 60)) CHECK(range == 2 && frame >= 14 && frame < 19);
    // A mix without b: nothing leads out of a with a weight, so a's characters stay in a.
    ClipPlan only_a = quick_plan();
    only_a.weights = {1, 0, 0};
    for (const auto& [range, frame] : play(schedule(only_a), 1, 0, 0, 1, 30, 60)) CHECK(range == 0 && frame < 8);
    // Weights pick among the ways out of a clip (one here) and never lead into a weight-0 clip.
    ClipPlan no_c = quick_plan();
    no_c.weights = {1, 1, 0};
    int switched = 0;
    for (const auto& [range, frame] : play(schedule(no_c), 2, 0, 0, 1, 30, 60)) {
        switched += range != 0;
        CHECK(range != 2 && frame < kPoseFrames);
    }
    CHECK(switched > 0);
}

void test_one_clip_shows_the_cycle_frame() {
    // No clips given (a v1 bundle read without ranges): one loop over every pose frame, and the
    // frame cycle_frame gives, as crowdview showed before clips.
    const ClipSchedule s = make_clip_schedule({}, {}, 40, 24, ClipPlan(), 3);
    CHECK(s.clip_count == 1 && s.ranges.size() == 1 && s.ranges[0].frames == 40);
    const ClipState state = initial_clip_state(s, 0, 0, 0.37f);
    CHECK(std::isinf(state.next_event_s));
    for (int k = 0; k < 2000; ++k) {
        const float t = float(k) / 30.0f, rate = 0.9f + 0.0001f * float(k);
        CHECK(shown_pose_frame(s, state, rate, t) == cycle_frame(t * rate, 0.37f, 24, 40));
    }
}

void test_impostor_tables_per_range() {
    // Baked: a at 0 and 4; b at 8 and 12; c at 16; a -> b (19..21) at 19 and 21; b -> a (22..25) at 22, 25.
    const std::vector<uint32_t> baked = {0, 4, 8, 12, 16, 19, 21, 22, 25};
    const ClipSchedule s = schedule();
    std::vector<uint32_t> nearest;
    std::vector<FrameWeights> weights;
    impostor_frame_tables(baked, s, kPoseFrames, &nearest, &weights);
    CHECK(nearest.size() == kPoseFrames && weights.size() == kPoseFrames);
    // In clip a the blend wraps round a's 8 frames: frame 6 is half layer 1 (frame 4), half layer 0.
    CHECK(weights[6].layers[0] == 1 && weights[6].layers[1] == 0 && std::fabs(weights[6].weight - 0.5f) < 1e-6f);
    CHECK(nearest[7] == 0);  // frame 7 is next to a's frame 0 round the loop, not b's frame 8
    // Clip b wraps within its 6 frames: frame 13 is 1/2 of the way from 12 to 8 (8 + 6).
    CHECK(weights[13].layers[0] == 3 && weights[13].layers[1] == 2 && std::fabs(weights[13].weight - 0.5f) < 1e-6f);
    // Clip c has one baked frame: it alone.
    for (uint32_t f = 14; f < 19; ++f) CHECK(nearest[f] == 4 && weights[f].layers[0] == 4 && weights[f].layers[1] == 4);
    // Transitions clamp: 19 is layer 5 alone, 20 halfway to 21, 21 layer 6 alone; never layers of b -> a.
    CHECK(weights[19].layers[0] == 5 && weights[19].layers[1] == 5 && weights[19].weight == 0);
    CHECK(weights[20].layers[0] == 5 && weights[20].layers[1] == 6 && std::fabs(weights[20].weight - 0.5f) < 1e-6f);
    CHECK(weights[21].layers[0] == 6 && weights[21].layers[1] == 6 && nearest[21] == 6);
    CHECK(weights[24].layers[0] == 7 && weights[24].layers[1] == 8 && std::fabs(weights[24].weight - 2.0f / 3.0f) < 1e-6f);
    CHECK(nearest[23] == 7 && nearest[24] == 8);
    // One range over everything is v1's tables.
    const ClipSchedule one = make_clip_schedule({}, {}, 10, 24, ClipPlan(), 0);
    const std::vector<uint32_t> v1 = {0, 3, 6};
    impostor_frame_tables(v1, one, 10, &nearest, &weights);
    for (uint32_t f = 0; f < 10; ++f) {
        const FrameWeights w = blend_frame_weights(f, v1, 10);
        CHECK(nearest[f] == impostor_layer(f, v1, 10) && weights[f].layers[0] == w.layers[0] && weights[f].layers[1] == w.layers[1] &&
              weights[f].weight == w.weight);
    }
}

void test_build_frame_plays_clips() {
    // build_frame steps every character's clip state: over 20 s at 30 Hz each of 50 characters that
    // starts in a or b switches, and every instance frame lies in the range its state says.
    CharacterModel model;
    model.frames_per_second = float(kFps);
    model.frame_count = kPoseFrames;
    model.clips = kClips;
    model.transitions = kTransitions;
    model.azimuths_deg = {0, 90, 180, 270};
    model.elevations_deg = {0};
    model.frame_indices = {0, 4, 8, 12, 16, 19, 21, 22, 25};
    CrowdDesc desc;
    desc.count = 50;
    Crowd crowd = make_crowd(desc, 1, 1, 1);
    crowd.clip_plan = quick_plan();
    crowd.clip_plan.weights = {1, 1, 0};
    assign_clips(&crowd, crowd.clip_plan.weights, {8 / 24.0f, 6 / 24.0f, 5 / 24.0f}, 11);
    std::map<uint32_t, int> first_clips;
    for (const Character& c : crowd.characters) ++first_clips[c.clip];
    CHECK(first_clips.size() == 2 && first_clips.count(2) == 0);
    const Camera camera = camera_for_crowd(crowd, 2, 16.0f / 9.0f, 0.35f);
    FrameState state;
    FrameInstances frame;
    for (int k = 0; k < 600; ++k) {
        build_frame(crowd, model, camera, 16.0f / 9.0f, LodMode::high, LodRule(), float(k) / 30.0f, &state, &frame);
        CHECK(frame.by_lod[0].size() + frame.culled == 50);
    }
    int switched = 0;
    for (const ClipState& c : state.clip) switched += c.switches > 0;
    CHECK_MSG(switched == 50, std::to_string(switched) + " of 50 switched");
    // Time going back starts the schedule again from time 0.
    build_frame(crowd, model, camera, 16.0f / 9.0f, LodMode::high, LodRule(), 0.0f, &state, &frame);
    for (size_t i = 0; i < crowd.characters.size(); ++i) CHECK(state.clip[i].switches == 0 && state.clip[i].range == crowd.characters[i].clip);
}

}  // namespace

// Regression: switch_after_s [0, 0] on 1-frame clips and transitions at 1000 fps (the most a
// bundle may have) made every character switch many times a frame; 20,000 characters drew 30
// frames in 559 s. The dwell is at least kMinDwellS, so 10 s hold at most 10 / 0.1 switches.
void test_a_zero_dwell_is_raised_to_the_minimum() {
    ClipPlan plan;
    plan.switch_after_s[0] = plan.switch_after_s[1] = 0;
    const std::vector<ClipRange> clips = {{"a", 0, 1}, {"b", 1, 1}};
    const std::vector<TransitionRange> transitions = {{0, 1, 0, 0, 2, 1}, {1, 0, 0, 0, 3, 1}};
    const ClipSchedule s = make_clip_schedule(clips, transitions, 4, 1000, plan, 3);
    CHECK(s.switch_after_s[0] == kMinDwellS && s.switch_after_s[1] == kMinDwellS);
    ClipState state = initial_clip_state(s, 0, 0, 0);
    for (int frame = 0; frame <= 240; ++frame) {
        const float t = float(frame) / 24;
        if (t >= state.next_event_s) advance_clip_state(s, 0, 4.0f, t, &state);
    }
    CHECK_MSG(state.switches >= 50 && state.switches <= 10 / kMinDwellS, std::to_string(state.switches) + " switches in 10 s");
}

int main() {
    test_switches_go_through_transitions_at_their_frames();
    test_schedule_is_a_function_of_time();
    test_a_clip_nothing_leaves_keeps_its_characters();
    test_one_clip_shows_the_cycle_frame();
    test_impostor_tables_per_range();
    test_build_frame_plays_clips();
    test_a_zero_dwell_is_raised_to_the_minimum();
    return check::exit_code();
}
