// The archetypes of a crowd description, loaded: each bundle read from its folder or fetched
// through the one download cache (fetch.h), verified, and later uploaded as one of the
// renderer's archetypes. A bundle that is refused stops its archetype, not the crowd. A bundle
// several archetypes name (the same folder or URL, or the same name, version and files) is loaded
// and uploaded once for all of them; each keeps its own count, clips and play rate.
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bundle.h"
#include "crowd.h"
#include "crowd_file.h"
#include "crowd_layout.h"
#include "fetch.h"
#include "renderer.h"

namespace crowdview {

struct LoadedArchetype {
    size_t desc_index = 0;  // into CrowdFile::archetypes
    std::string name;
    std::shared_ptr<Bundle> bundle;  // one per bundle, shared by the archetypes naming it; released once uploaded
};

struct RefusedArchetype {
    std::string name, error;  // error: one line, the loader's or the renderer's message
};

// Loads every archetype of `crowd` in order; refusals go to `refused` and are logged as
// "archetype '<name>': bundle refused: <message>". `fetch` serves every URL archetype, so the
// cache (content-addressed) is shared: a file two bundles hold is downloaded once. The URL
// archetypes' fetches share one total deadline (fetch.h FetchDeadline). Each folder or URL is
// loaded once; archetypes naming one bundle share it (logged once per shared bundle).
std::vector<LoadedArchetype> load_archetypes(const CrowdFile& crowd, const FetchOptions& fetch,
                                             const std::function<void(const std::string&)>& log,
                                             std::vector<RefusedArchetype>* refused);

// What the layout needs of a loaded archetype: its count, spacing from its impostor radius,
// clips (their lengths, the mix, the dwell range: the description's switch_after_s, else
// `switch_after_s`), variations, outfits and play rate.
ArchetypeTraits archetype_traits(const ArchetypeDesc& desc, uint64_t count, const Bundle& bundle, const CharacterModel& model,
                                 const float switch_after_s[2]);

// The clip mix `mix` as a weight per clip of `clips` (empty mix: all 1); "" or one line naming
// the first clip the bundle lacks and the clips it has.
std::string resolve_clip_mix(const std::vector<ClipWeight>& mix, const std::vector<ClipInfo>& clips, std::vector<float>* weights);

// Per-frame counts of one archetype (FrameInstances sizes), accumulated over a run.
struct ArchetypeCounts {
    uint64_t last[3] = {0, 0, 0};        // by Lod, in the last frame
    uint32_t last_culled = 0;
    uint64_t frames_with[3] = {0, 0, 0};  // frames in which at least one character drew at that Lod
    void add(const FrameInstances& frame);
};

// "high 12 | low 3 | impostor 40 | culled 2" for the title and the log.
std::string lod_summary(const ArchetypeCounts& counts);

// The crowd as loaded: the description, and per renderer archetype its description index and name.
struct CrowdScene {
    CrowdFile file;
    float switch_after_s[2] = {kDefaultSwitchAfterS[0], kDefaultSwitchAfterS[1]};  // --switch-after
    std::vector<size_t> desc_index;  // renderer archetype -> CrowdFile::archetypes
    std::vector<std::string> names;
    std::vector<ArchetypeTraits> traits;
    std::vector<RefusedArchetype> refused;
};

// Counts per archetype and LOD, GPU memory per archetype, and the CPU cost of a frame: the
// --report of a headless run.
nlohmann::json view_report(const std::string& device, const Renderer& renderer, const CrowdScene& scene,
                           const std::vector<ArchetypeCounts>& counts, const std::vector<LodRule>& rules, int frames,
                           double build_ms, const DrawStats& stats);

// Uploads each loaded archetype as the renderer's next one and fills scene's per-archetype
// lists (desc_index, names, traits); archetypes sharing a bundle share its uploads. A bundle the renderer refuses is logged and left out;
// without `log` (a lone --bundle) the first refusal is returned as false and `error` instead.
bool upload_archetypes(Renderer* renderer, const std::vector<LoadedArchetype>& loaded, CrowdScene* scene,
                       const std::function<void(const std::string&)>& log, std::string* error);

}  // namespace crowdview
