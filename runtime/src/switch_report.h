// --report's clip figures, without GL: characters per clip (and transition) and LOD, and how far a
// character jumps on screen when it switches clips, measured on the CPU from the pose caches for a
// sample of characters (nothing is kept or computed without --report).
//
// The switch measure, per representation (high mesh, low mesh, impostor):
//  - The picture of a character is the world positions of its vertices (up to kMeterVertices of the
//    representation's mesh parts, evenly spaced) in the pose it shows: a mesh, the pose frame it
//    draws; an impostor, the high-mesh poses of the two baked frames it blends, mixed by its frame
//    weight (the nearest baked frame alone when frames are not blended). Both pictures of a step are
//    placed at the character's current feet and heading, so walking along a path is not motion.
//  - motion(P, Q) = the RMS over those vertices of the distance in pixels between their projections
//    in P and in Q (the run's camera and viewport).
//  - A switch is a displayed frame at which the character is in another range (clip or transition)
//    than at the frame before, in the same representation and on screen at both. Its jump is
//    motion(picture before, picture now).
//  - Its reference is the median per-frame motion inside the clips the transition joins (the larger
//    of its two clips, so a transition out of a nearly still idle is held to the motion it leads
//    into): per clip, the median over its loop frames k of motion(picture at k, picture at k + n),
//    where n is the number of pose frames the switch stepped (1 when every frame is shown); same
//    character, place and representation; steps that change nothing left out.
//  - ratio = jump / reference; reported: the largest ratio (with its jump and reference in pixels),
//    the median ratio and the number of switches measured. A pop-free switch moves about as much as
//    a frame inside its clip: ratio near 1. The target is <= 1.5.
//  - A clip's own steps vary round its loop (a run's fastest frame moves twice its median), so a
//    switch at a fast phase can pass 1.5 with no pop at all. largest_ratio_same_phase divides each jump
//    by the larger of its reference and the motion the clip beside the switch makes over the same steps
//    at that phase (on from the frame before entering a transition; up to the frame after leaving
//    one): 1 is a switch indistinguishable from playing the clip on.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bundle.h"
#include "crowd.h"

namespace crowdview {

// Vertices per representation the meter projects (evenly spaced over its mesh parts): enough for
// an RMS within a few per cent, few enough that a switch costs microseconds.
constexpr uint32_t kMeterVertices = 2048;
// Characters sampled per representation and archetype.
constexpr uint32_t kMeterCharacters = 32;

// Counts of the drawn characters per range (clips, then transitions) and LOD in one frame, and the
// switches so far: the report's "clips" object for one archetype.
nlohmann::json clip_counts(const Crowd& crowd, const CharacterModel& model, const FrameState& state, const Camera& camera,
                           float aspect, float time_s);

class SwitchMeter {
public:
    // `meshes` and `infos`: the archetype's pose caches (Bundle::meshes, Manifest::meshes); the
    // meters of archetypes drawn from one bundle share its pose caches.
    SwitchMeter(std::shared_ptr<const std::vector<PoseCache>> meshes, const std::vector<MeshInfo>& infos);

    // After build_frame of this archetype's frame at `time_s` (`blend_frames`: impostors blend two
    // baked frames). The first call picks the sample.
    void observe(const Crowd& crowd, const CharacterModel& model, const FrameState& state, const Camera& camera, int width,
                 int height, float time_s, bool blend_frames);

    // {"high": {...}, "low": {...}, "impostor": {...}}: per representation switches_measured,
    // largest_ratio, jump_px, reference_px, median_ratio, largest_ratio_same_phase and `worst`, the
    // switch of the largest ratio: its ranges and their frames before and after it (null figures
    // where none was measured).
    nlohmann::json report() const;

    // The largest ratio of `lod` (0 where no switch was measured), for the log line.
    double largest_ratio(Lod lod) const;

private:
    struct Tracked {
        uint32_t character = 0;
        bool seen = false, visible = false;
        Lod lod = Lod::high;
        ClipState clip;
        uint32_t pose_frame = 0;
        FrameWeights weights;
    };
    struct Event {
        double jump_px, reference_px;
        double continued_px;  // the clip beside the switch over the same steps, had it not switched
        uint32_t range_before, range_after;        // clips 0..C-1, then transitions
        uint32_t frame_before, frame_after;        // frames within those ranges
    };
    std::vector<std::string> range_names_;  // for the report's worst switch
    // What a character shows: pose frames a and b mixed by weight (a mesh: a == b, weight 0).
    struct Shown {
        uint32_t a = 0, b = 0;
        float weight = 0;
    };
    // The vertices of mesh LOD `mesh_lod` (0, 1) in pose `shown`, through `to_screen` (view-projection
    // times placement) to pixels of a width x height viewport.
    void picture(int mesh_lod, const Shown& shown, const glm::mat4& to_screen, int width, int height,
                 std::vector<glm::vec2>* pixels) const;
    // The median motion between loop frames k and k + steps of clip `clip` (steps that change nothing
    // left out); 0 when every step is still.
    double clip_reference(const CharacterModel& model, const FrameState& state, uint32_t clip, uint32_t steps, Lod lod,
                          bool blend_frames, const glm::mat4& to_screen, int width, int height) const;
    // Up to kMeterCharacters on screen per representation, spread over the crowd: tracked_ and sampled_.
    void pick_characters(const Crowd& crowd, const CharacterModel& model, const FrameState& state, const Frustum& frustum, size_t n,
                         float time_s);
    // A change of range a tracked character made between two observed frames (defined in switch_report.cpp).
    struct Switch;
    // The switch's jump on screen against its clips' own motion: an event of its LOD, or one more unmeasured.
    void measure_switch(const Switch& s, const CharacterModel& model, const FrameState& state, bool blend_frames, int width, int height);

    std::shared_ptr<const std::vector<PoseCache>> meshes_;
    std::vector<uint32_t> parts_[2];       // mesh indices by LOD (0 high, 1 low; low falls back to high)
    std::vector<uint32_t> vertices_[2];    // per LOD: (part, vertex) pairs flattened, evenly spaced
    std::vector<Tracked> tracked_;
    bool picked_ = false;
    std::vector<Event> events_[3];
    uint32_t unmeasured_[3] = {0, 0, 0};
    uint32_t sampled_[3] = {0, 0, 0};
};

}  // namespace crowdview
