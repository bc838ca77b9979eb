// crowdview_frame_bench: the CPU side of a frame for a large mixed crowd, without GL: culling,
// LOD choice, clip state (cycle frame, impostor view and frame blend) and the instance-buffer
// fill, for every character of every archetype, as crowdview's frame loop runs build_frame.
//
//   crowdview_frame_bench [--count N] [--archetypes K] [--frames F] [--threads T] [--clips C] [--report JSON]
// (--threads: default crowdview's, one per archetype up to the hardware's; --clips: clips per
// archetype, default 3, joined in a ring by transitions both ways; 1 is a v1 bundle's one cycle)
//
// The archetypes are shaped like real bundles (impostor radius, tile size, views, baked frames of
// the sample walker, CesiumMan and the 4 m robot); the crowd is laid out as a --crowd spot layout.
// Characters switch clips every 4 to 10 s (crowdview's default); the timed frames start 30 s in,
// so the crowd is spread over clips and transitions as in a long run.
// Prints one line per camera and writes the figures as JSON.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <string>
#include <thread>

#include <time.h>
#include <vector>

#include <nlohmann/json.hpp>

#include "crowd.h"
#include "crowd_layout.h"

using namespace crowdview;

namespace {

struct Shape {
    const char* name;
    float radius, center_y;
    uint32_t tile, frames, baked, azimuths;
    float fps;
};

// Impostor radius and centre height (m), tile (texels), cycle frames, baked frames, azimuths and
// frame rate of the demo's four bundles (scripts/demo.sh, the bake's defaults; elevations 0, 20, 40).
const Shape kShapes[] = {{"sample-loose", 1.054f, 0.876f, 128, 40, 10, 20, 24},
                         {"sample-tight", 1.053f, 0.876f, 128, 40, 10, 20, 24},
                         {"cesiumman", 1.119f, 0.747f, 128, 48, 10, 16, 24},
                         {"robot", 3.227f, 2.174f, 128, 23, 10, 16, 24}};

// Transition length in frames: about the half second a change of gait takes.
constexpr uint32_t kTransitionFrames = 12;

// `clips` clips of s.frames frames each (s.baked baked), and for clips > 1 a transition each way
// between neighbours (baked at both ends and halfway), as a bake of a timeline writes them.
CharacterModel model_of(const Shape& s, uint32_t clips) {
    CharacterModel m;
    m.center = glm::vec3(0, s.center_y, 0);
    m.radius = s.radius;
    m.frames_per_second = s.fps;
    m.tile_size = s.tile;
    for (uint32_t a = 0; a < s.azimuths; ++a) m.azimuths_deg.push_back(360.0f * float(a) / float(s.azimuths));
    m.elevations_deg = {0, 20, 40};
    m.has_low = true;
    uint32_t first = 0;
    for (uint32_t c = 0; c < clips; ++c, first += s.frames) {
        m.clips.push_back({"clip" + std::to_string(c), first, s.frames});
        for (uint32_t f = 0; f < s.baked; ++f) m.frame_indices.push_back(first + f * s.frames / s.baked);
    }
    for (uint32_t c = 0; c + 1 < clips; ++c)
        for (uint32_t to : {c + 1, c}) {
            const uint32_t from = to == c ? c + 1 : c;
            m.transitions.push_back({from, to, (3 * c + 1) % s.frames, (5 * c + 2) % s.frames, first, kTransitionFrames});
            for (uint32_t f : {0u, kTransitionFrames / 2, kTransitionFrames - 1}) m.frame_indices.push_back(first + f);
            first += kTransitionFrames;
        }
    m.frame_count = first;
    return m;
}

double median(std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 0 : v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
    uint64_t count = 100000;
    int archetypes = 4, frames = 60, threads = 0, clips = 3;  // threads 0: as crowdview (archetype_threads)
    std::string report_path;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        auto next = [&]() -> const char* {
            if (i + 1 >= argc) {
                std::fprintf(stderr, "crowdview_frame_bench: %s needs a value\n", a.c_str());
                std::exit(2);
            }
            return argv[++i];
        };
        if (a == "--count") count = std::strtoull(next(), nullptr, 10);
        else if (a == "--archetypes") archetypes = std::atoi(next());
        else if (a == "--frames") frames = std::atoi(next());
        else if (a == "--threads") threads = std::atoi(next());
        else if (a == "--clips") clips = std::atoi(next());
        else if (a == "--report") report_path = next();
        else {
            std::fprintf(stderr, "crowdview_frame_bench: unknown argument '%s'\n", a.c_str());
            return 2;
        }
    }
    if (count < 1 || archetypes < 1 || archetypes > 4 || frames < 1 || threads < 0 || threads > 64 || clips < 1 || clips > 64) {
        std::fprintf(stderr, "crowdview_frame_bench: --count >= 1, --archetypes 1..4, --frames >= 1, --threads 1..64, --clips 1..64\n");
        return 2;
    }
    if (threads == 0) threads = int(archetype_threads(size_t(archetypes)));
    const float aspect = 1280.0f / 720.0f, height_px = 720.0f;
    std::vector<CharacterModel> models;
    std::vector<ArchetypeTraits> traits;
    CrowdFile file;
    file.seed = 1;
    for (int k = 0; k < archetypes; ++k) {
        models.push_back(model_of(kShapes[k], uint32_t(clips)));
        ArchetypeTraits t;
        t.count = count / archetypes + (uint64_t(k) < count % archetypes ? 1 : 0);
        t.spacing = crowd_spacing(models[k].radius);
        t.cycle_seconds = float(kShapes[k].frames) / models[k].frames_per_second;
        for (const ClipRange& c : models[k].clips) t.clip_seconds.push_back(float(c.frames) / models[k].frames_per_second);
        t.variations = 8, t.outfits = 8;
        t.play_rate[0] = 0.9f, t.play_rate[1] = 1.1f;
        traits.push_back(t);
    }
    const auto layout_start = std::chrono::steady_clock::now();
    const std::vector<Crowd> crowds = lay_out_crowd(file, traits, nullptr);
    const double layout_ms = 1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now() - layout_start).count();
    Crowd extent;
    extent.half_extent = crowds_half_extent(crowds);
    const float character_height = 4.2f;

    nlohmann::json results = nlohmann::json::array();
    struct View {
        const char* name;
        Camera camera;
    };
    // Overview: the whole crowd on screen, nearly all impostors. Eye level: a person standing 2 m in
    // from the crowd's front edge looking across it, so meshes near, impostors far, most culled.
    Camera eye_level = look_at(glm::vec3(0, 1.7f, extent.half_extent - 2.0f), glm::vec3(0, 1.2f, 0));
    const View views[] = {{"overview", camera_for_crowd(extent, character_height, aspect, 0.35f)}, {"eye-level", eye_level}};
    for (const View& view : views) {
        for (ImpostorBlend blend : {ImpostorBlend::warp, ImpostorBlend::off}) {  // crowdview's default and the paper's
            Camera camera = view.camera;
            camera.near_m = 0.1f, camera.far_m = std::max(camera.far_m * 4.0f, 200.0f);
            std::vector<LodRule> rules;
            for (const CharacterModel& m : models) rules.push_back(lod_rule_for(m, camera, height_px));
            std::vector<FrameState> state(models.size());
            std::vector<FrameInstances> out(models.size());
            std::vector<double> ms, cpu_ms;
            uint64_t lods[3] = {0, 0, 0}, culled = 0;
            for (int f = -2; f < frames; ++f) {  // two warm-up frames size the vectors
                const float time_s = 30.0f + float(std::max(f, 0)) * kFixedTimeStep;
                const auto start = std::chrono::steady_clock::now();
                timespec cpu_start, cpu_end;  // this process's CPU time: what the frame cost, without other programs' share of the cores
                clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &cpu_start);
                // Archetypes split over `threads` threads, as crowdview's frame loop does (for_each_archetype).
                for_each_archetype(models.size(), unsigned(threads), [&](size_t a) {
                    build_frame(crowds[a], models[a], camera, aspect, LodMode::automatic, rules[a], time_s, &state[a], &out[a], blend);
                });
                const double elapsed = 1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
                clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &cpu_end);
                const double cpu = 1e3 * double(cpu_end.tv_sec - cpu_start.tv_sec) + 1e-6 * double(cpu_end.tv_nsec - cpu_start.tv_nsec);
                if (f >= 0) ms.push_back(elapsed), cpu_ms.push_back(cpu);
            }
            for (const FrameInstances& o : out) {
                for (int l = 0; l < 3; ++l) lods[l] += o.by_lod[l].size();
                culled += o.culled;
            }
            const double med = median(ms), mean = [&] {
                double s = 0;
                for (double v : ms) s += v;
                return s / double(ms.size());
            }();
            std::printf("%s camera, impostor blend %s: %.2f ms a frame (median of %d; mean %.2f; CPU time %.2f ms) for %llu characters of %d archetypes: "
                        "%llu high, %llu low, %llu impostor, %llu culled\n",
                        view.name, blend == ImpostorBlend::off ? "off" : "warp", med, frames, mean, median(cpu_ms), (unsigned long long)count, archetypes,
                        (unsigned long long)lods[0], (unsigned long long)lods[1], (unsigned long long)lods[2], (unsigned long long)culled);
            results.push_back({{"camera", view.name},
                               {"impostor_blend", blend == ImpostorBlend::off ? "off" : "warp"},
                               {"median_ms", med},
                               {"mean_ms", mean},
                               {"median_cpu_ms", median(cpu_ms)},
                               {"lod_counts", {{"high", lods[0]}, {"low", lods[1]}, {"impostor", lods[2]}, {"culled", culled}}}});
        }
    }
    const nlohmann::json report = {{"what", "CPU ms per frame: culling, LOD choice, clip state and instance-buffer fill (build_frame)"},
                                   {"characters", count},
                                   {"clips_per_archetype", clips},
                                   {"archetypes", archetypes},
                                   {"threads", threads},
                                   {"frames", frames},
                                   {"hardware_threads", std::thread::hardware_concurrency()},
                                   {"layout_ms", layout_ms},
                                   {"results", results}};
    if (!report_path.empty()) {
        std::ofstream out(report_path);
        if (!(out << report.dump(2) << "\n")) {
            std::fprintf(stderr, "crowdview_frame_bench: cannot write %s\n", report_path.c_str());
            return 1;
        }
    }
    return 0;
}
