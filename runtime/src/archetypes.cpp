// Loading a crowd description's archetypes (archetypes.h).
#include "archetypes.h"

#include <algorithm>
#include <filesystem>
#include <map>

namespace crowdview {

namespace {

// Where an archetype's bundle comes from, so that two spellings of one place compare equal: a
// folder's canonical path, a URL's bundle folder (fetch.h bundle_urls).
std::string source_key(const ArchetypeSource& source) {
    if (source.is_url()) return "url " + bundle_urls(source.url).base;
    std::error_code error;
    const std::filesystem::path canonical = std::filesystem::weakly_canonical(source.folder, error);
    return "folder " + (error ? source.folder : canonical.string());
}

// Two loads of one bundle (a `latest` URL and its version's, say): the same name, version and files.
bool same_bundle(const Manifest& a, const Manifest& b) {
    if (a.name != b.name || a.version != b.version || a.files.size() != b.files.size()) return false;
    for (size_t i = 0; i < a.files.size(); ++i)
        if (a.files[i].path != b.files[i].path || a.files[i].sha256 != b.files[i].sha256) return false;
    return true;
}

// One source's bundle, or its refusal (`error`); a bundle already among `loaded` is that one.
struct SourceLoad {
    std::shared_ptr<Bundle> bundle;
    std::string error;
};

SourceLoad load_source(const ArchetypeSource& source, const FetchOptions& fetch, FetchDeadline* deadline,
                       const std::vector<LoadedArchetype>& loaded) {
    auto bundle = std::make_shared<Bundle>();
    const Status status = source.is_url() ? fetch_bundle(source.url, fetch, bundle.get(), deadline)
                                          : load_bundle_dir(source.folder, bundle.get());
    if (!status) return {nullptr, status.message};
    for (const LoadedArchetype& a : loaded)
        if (same_bundle(a.bundle->manifest, bundle->manifest)) return {a.bundle, ""};
    return {bundle, ""};
}

// "bundle NAME VERSION: loaded once for 64 archetypes ('a', 'b', 'c' and 61 more)", per bundle
// that several archetypes share.
void log_shared_bundles(const std::vector<LoadedArchetype>& loaded, const std::function<void(const std::string&)>& log) {
    for (size_t i = 0; log && i < loaded.size(); ++i) {
        const Bundle* bundle = loaded[i].bundle.get();
        const auto same = [&](const LoadedArchetype& a) { return a.bundle.get() == bundle; };
        if (std::any_of(loaded.begin(), loaded.begin() + i, same)) continue;  // logged with its first archetype
        const size_t sharing = size_t(std::count_if(loaded.begin() + i, loaded.end(), same));
        if (sharing < 2) continue;
        std::string names;
        size_t named = 0;
        for (size_t k = i; k < loaded.size() && named < 3; ++k)
            if (same(loaded[k])) names += std::string(named++ ? ", '" : "'") + loaded[k].name + "'";
        if (sharing > named) names += " and " + std::to_string(sharing - named) + " more";
        log("bundle " + bundle->manifest.name + " " + bundle->manifest.version + ": loaded once for " + std::to_string(sharing) +
            " archetypes (" + names + ")");
    }
}

}  // namespace

std::vector<LoadedArchetype> load_archetypes(const CrowdFile& crowd, const FetchOptions& fetch,
                                             const std::function<void(const std::string&)>& log,
                                             std::vector<RefusedArchetype>* refused) {
    std::vector<LoadedArchetype> loaded;
    const std::vector<uint64_t> counts = archetype_counts(crowd);
    FetchDeadline deadline;                    // one for every URL archetype's fetch
    std::map<std::string, SourceLoad> sources;  // by source_key: each folder or URL loaded once
    for (size_t k = 0; k < crowd.archetypes.size(); ++k) {
        const ArchetypeDesc& desc = crowd.archetypes[k];
        if (counts[k] == 0) {  // a share too small to round to one character, or no positions
            if (log) log("archetype '" + desc.name + "': no characters, not loaded");
            continue;
        }
        const std::string key = source_key(desc.source);
        auto source = sources.find(key);
        if (source == sources.end()) source = sources.emplace(key, load_source(desc.source, fetch, &deadline, loaded)).first;
        if (!source->second.bundle) {
            refused->push_back({desc.name, source->second.error});
            if (log) log("archetype '" + desc.name + "': bundle refused: " + source->second.error);
            continue;
        }
        loaded.push_back({k, desc.name, source->second.bundle});
    }
    log_shared_bundles(loaded, log);
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
    uint64_t gpu_memory_total = 0;
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
        gpu_memory_total += mem.total();
        // Drawn with another archetype's uploads (the same bundle): its own memory above is zero.
        if (const size_t owner = renderer.uploaded_by(a); owner != a) archetypes.back()["shares_uploads_of"] = scene.names[owner];
    }
    nlohmann::json refused = nlohmann::json::array();
    for (const RefusedArchetype& r : scene.refused) refused.push_back({{"name", r.name}, {"error", r.error}});
    return {{"device", device},
            {"width", renderer.width()},
            {"height", renderer.height()},
            {"frames", frames},
            {"archetypes", archetypes},
            {"gpu_memory_bytes_total", gpu_memory_total},
            {"refused", refused},
            {"draw_calls", stats.draw_calls},
            {"triangles", stats.triangles},
            {"cpu_build_ms_per_frame", build_ms}};
}


bool upload_archetypes(Renderer* renderer, const std::vector<LoadedArchetype>& loaded, CrowdScene* scene,
                       const std::function<void(const std::string&)>& log, std::string* error) {
    const std::vector<uint64_t> counts = archetype_counts(scene->file);
    std::map<const Bundle*, size_t> uploaded;       // a bundle's uploads: the renderer archetype that made them
    std::map<const Bundle*, std::string> refusals;  // a bundle the renderer refused, asked once
    for (const LoadedArchetype& a : loaded) {
        const Bundle* bundle = a.bundle.get();
        if (const auto same = uploaded.find(bundle); same != uploaded.end()) {
            renderer->add_archetype_like(same->second);
        } else if (!refusals.count(bundle) && renderer->add_archetype(*bundle, &refusals[bundle])) {
            refusals.erase(bundle);
            uploaded[bundle] = renderer->archetype_count() - 1;
        } else {
            if (!log) {
                *error = refusals[bundle];
                return false;
            }
            log("archetype '" + a.name + "': " + refusals[bundle]);
            scene->refused.push_back({a.name, refusals[bundle]});
            continue;
        }
        scene->desc_index.push_back(a.desc_index);
        scene->names.push_back(a.name);
        scene->traits.push_back(archetype_traits(scene->file.archetypes[a.desc_index], counts[a.desc_index], *bundle,
                                                 renderer->model(renderer->archetype_count() - 1), scene->switch_after_s));
    }
    return true;
}

}  // namespace crowdview
