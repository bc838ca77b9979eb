// Where the characters of several archetypes stand (crowd_file.h's layouts), without GL:
// one Crowd per archetype, all on one ground, none closer to another than their sizes allow.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "crowd.h"
#include "crowd_file.h"

namespace crowdview {

// What the layout needs to know of one archetype (from its bundle, and its description).
struct ArchetypeTraits {
    uint64_t count = 0;        // characters; 0 leaves the archetype out (e.g. its bundle was refused)
    float spacing = 1.6f;      // crowd_spacing(impostor radius): metres between neighbours of this size
    float cycle_seconds = 1;   // for random phases
    uint32_t variations = 1, outfits = 1;
    float play_rate[2] = {1, 1};
    ClipPlan clip_plan;                // the clip mix (per clip of the bundle) and the dwell range
    std::vector<float> clip_seconds;   // per clip, its loop's length: first clips and phases are drawn from these
};

// Closest two characters of spacings `a` and `b` may stand (metres): 0.6 of their mean spacing,
// the nearest make_crowd's quarter-spacing jitter lets two grid neighbours come, plus a margin.
inline float min_separation(float spacing_a, float spacing_b) { return 0.3f * (spacing_a + spacing_b); }

// One Crowd per entry of `traits` (empty for count 0), on a common ground: every Crowd has
// the same layout, half_extent and walk_speed.
//  spot, paths: one archetype is make_crowd's jittered grid (as --bundle draws it); several are
//    scattered without overlap (min_separation) in a square centred on the origin that grows
//    until everyone fits, largest archetypes first, so big characters are not crowded out;
//  scatter: the same in the description's area; characters that do not fit are left out and
//    `note` says how many;
//  positions: the description's list, with each archetype's random phase, variation and outfit.
// Then each character gets its first clip by the archetype's clip mix (crowd.h assign_clips), and
// each Crowd the archetype's clip plan and a schedule seed.
// Deterministic for a seed. `note` (may be null) gets "" or one line for the log.
std::vector<Crowd> lay_out_crowd(const CrowdFile& file, const std::vector<ArchetypeTraits>& traits, std::string* note);

// The half size of the square that holds every character of `crowds` (metres, XZ).
float crowds_half_extent(const std::vector<Crowd>& crowds);

}  // namespace crowdview
