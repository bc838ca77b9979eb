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
        loaded.push_back(std::move(a));
    }
    return loaded;
}

std::string resolve_clip_mix(const std::vector<ClipWeight>& mix, const std::vector<ClipInfo>& clips, std::vector<float>* weights) {
    weights->assign(clips.size(), mix.empty() ? 1.0f : 0.0f);
    for (const ClipWeight& w : mix) {
        const auto it = std::find_if(clips.begin(), clips.end(), [&](const ClipInfo& c) { return c.name == w.clip; });
        if (it == clips.end()) {
            std::string names;
            for (const ClipInfo& c : clips) names += (names.empty() ? "" : ", ") + printable(c.name);
            return "clip '" + printable(w.clip) + "' is not in the bundle (its clips: " + names + ")";
        }
        (*weights)[size_t(it - clips.begin())] += w.weight;
    }
    return "";
}

ArchetypeTraits archetype_traits(const ArchetypeDesc& desc, uint64_t count, const Bundle& bundle, const CharacterModel& model,
                                 const float switch_after_s[2]) {
    ArchetypeTraits t;
    t.count = count;
    t.spacing = crowd_spacing(model.radius);
    const float fps = model.frames_per_second > 0 ? model.frames_per_second : 24.0f;
    // Phases span the first clip, or the whole cycle of a bundle without clips.
    t.cycle_seconds = bundle.manifest.clips.empty() ? float(model.frame_count) / fps : float(bundle.manifest.clips[0].frames) / fps;
    for (const ClipInfo& c : bundle.manifest.clips) t.clip_seconds.push_back(float(c.frames) / fps);
    resolve_clip_mix(desc.clips, bundle.manifest.clips, &t.clip_plan.weights);  // checked when loaded: no unknown names
    const float* dwell = desc.has_switch_after ? desc.switch_after_s : switch_after_s;
    t.clip_plan.switch_after_s[0] = dwell[0], t.clip_plan.switch_after_s[1] = dwell[1];
    t.variations = 1;
    for (const MaterialInfo& m : bundle.manifest.materials) t.variations = std::max(t.variations, m.variations);
    t.outfits = std::max(bundle.manifest.outfit_count, 1u);
    t.play_rate[0] = desc.play_rate[0], t.play_rate[1] = desc.play_rate[1];
    return t;
}

void ArchetypeCounts::add(const FrameInstances& frame) {
    for (int lod = 0; lod < 3; ++lod) {
        last[lod] = frame.shown[lod];
        if (last[lod] > 0) ++frames_with[lod];
    }
    last_culled = frame.culled;
}

std::string lod_summary(const ArchetypeCounts& c) {
    return "high " + std::to_string(c.last[0]) + " | low " + std::to_string(c.last[1]) + " | impostor " + std::to_string(c.last[2]) +
           " | culled " + std::to_string(c.last_culled);
}

// Counts per archetype and LOD, GPU memory per archetype, and the CPU cost of a frame: the
// --report of a headless run.
nlohmann::json view_report(const std::string& device, const Renderer& renderer, const CrowdScene& scene,
                           const std::vector<ArchetypeCounts>& counts, const std::vector<LodRule>& rules, int frames,
                           double build_ms, const DrawStats& stats) {
    nlohmann::json archetypes = nlohmann::json::array();
    const char* lods[] = {"high", "low", "impostor"};
    for (size_t a = 0; a < renderer.archetype_count(); ++a) {
        const CharacterModel& m = renderer.model(a);
        const ArchetypeMemory mem = renderer.memory(a);
        nlohmann::json counts_json, frames_with;
        for (int l = 0; l < 3; ++l) counts_json[lods[l]] = counts[a].last[l], frames_with[lods[l]] = counts[a].frames_with[l];
        counts_json["culled"] = counts[a].last_culled;
        archetypes.push_back({{"name", scene.names[a]},
                              {"characters", scene.traits[a].count},
                              {"radius_m", m.radius},
                              {"tile_size", m.tile_size},
                              {"spacing_m", scene.traits[a].spacing},
                              {"low_switch_m", rules[a].has_low ? rules[a].impostor_distance * rules[a].low_fraction : 0.0f},
                              {"impostor_switch_m", rules[a].impostor_distance},
                              {"lod_counts", counts_json},
                              {"frames_with_lod", frames_with},
                              {"gpu_memory_bytes", {{"meshes", mem.meshes()}, {"bodies", mem.bodies}, {"garments", mem.garments},
                                                    {"textures", mem.textures}, {"impostors", mem.impostors},
                                                    {"total", mem.total()}}}});
    }
    nlohmann::json refused = nlohmann::json::array();
    for (const RefusedArchetype& r : scene.refused) refused.push_back({{"name", r.name}, {"error", r.error}});
    return {{"device", device},
            {"width", renderer.width()},
            {"height", renderer.height()},
            {"frames", frames},
            {"archetypes", archetypes},
            {"refused", refused},
            {"draw_calls", stats.draw_calls},
            {"triangles", stats.triangles},
            {"cpu_build_ms_per_frame", build_ms}};
}


bool upload_archetypes(Renderer* renderer, const std::vector<LoadedArchetype>& loaded, CrowdScene* scene,
                       const std::function<void(const std::string&)>& log, std::string* error) {
    const std::vector<uint64_t> counts = archetype_counts(scene->file);
    for (const LoadedArchetype& a : loaded) {
        std::string refusal;
        if (!renderer->add_archetype(a.bundle, &refusal)) {
            if (!log) {
                *error = refusal;
                return false;
            }
            log("archetype '" + a.name + "': " + refusal);
            scene->refused.push_back({a.name, refusal});
            continue;
        }
        scene->desc_index.push_back(a.desc_index);
        scene->names.push_back(a.name);
        scene->traits.push_back(archetype_traits(scene->file.archetypes[a.desc_index], counts[a.desc_index], a.bundle,
                                                 renderer->model(renderer->archetype_count() - 1), scene->switch_after_s));
    }
    return true;
}

}  // namespace crowdview
