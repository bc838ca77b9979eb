// Loading a crowd description's archetypes (archetypes.h).
#include "archetypes.h"

#include <algorithm>

namespace crowdview {

std::vector<LoadedArchetype> load_archetypes(const CrowdFile& crowd, const FetchOptions& fetch,
                                             const std::function<void(const std::string&)>& log,
                                             std::vector<RefusedArchetype>* refused) {
    std::vector<LoadedArchetype> loaded;
    const std::vector<uint64_t> counts = archetype_counts(crowd);
    for (size_t k = 0; k < crowd.archetypes.size(); ++k) {
        const ArchetypeDesc& desc = crowd.archetypes[k];
        if (counts[k] == 0) {  // a share too small to round to one character, or no positions
            if (log) log("archetype '" + desc.name + "': no characters, not loaded");
            continue;
        }
        LoadedArchetype a;
        a.desc_index = k;
        a.name = desc.name;
        const Status status = desc.source.is_url() ? fetch_bundle(desc.source.url, fetch, &a.bundle)
                                                   : load_bundle_dir(desc.source.folder, &a.bundle);
        if (!status) {
            refused->push_back({desc.name, status.message});
            if (log) log("archetype '" + desc.name + "': bundle refused: " + status.message);
            continue;
        }
        // Bundles hold one clip today (SPEC.md): the mix is reserved for bundles with several.
        if (desc.clips.size() > 1 && log)
            log("archetype '" + desc.name + "': the bundle has one clip; the clip mix of " + std::to_string(desc.clips.size()) +
                " clips is ignored");
        loaded.push_back(std::move(a));
    }
    return loaded;
}

ArchetypeTraits archetype_traits(const ArchetypeDesc& desc, uint64_t count, const Bundle& bundle, const CharacterModel& model) {
    ArchetypeTraits t;
    t.count = count;
    t.spacing = crowd_spacing(model.radius);
    t.cycle_seconds = model.frames_per_second > 0 ? float(model.frame_count) / model.frames_per_second : 1.0f;
    t.variations = 1;
    for (const MaterialInfo& m : bundle.manifest.materials) t.variations = std::max(t.variations, m.variations);
    t.outfits = std::max(bundle.manifest.outfit_count, 1u);
    t.play_rate[0] = desc.play_rate[0], t.play_rate[1] = desc.play_rate[1];
    return t;
}

void ArchetypeCounts::add(const FrameInstances& frame) {
    for (int lod = 0; lod < 3; ++lod) {
        last[lod] = frame.by_lod[lod].size();
        if (last[lod] > 0) ++frames_with[lod];
    }
    last_culled = frame.culled;
}

std::string lod_summary(const ArchetypeCounts& c) {
    return "high " + std::to_string(c.last[0]) + " | low " + std::to_string(c.last[1]) + " | impostor " + std::to_string(c.last[2]) +
           " | culled " + std::to_string(c.last_culled);
}

}  // namespace crowdview
