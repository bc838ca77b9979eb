// crowdview_frame_bench: the CPU side of a frame for a large mixed crowd: culling, LOD choice,
// clip state (cycle frame, impostor view and frame blend) and the instance-buffer fill, for every
// character of every archetype, as crowdview's frame loop runs build_frames, and getting the lists
// into GL buffers with the renderer's own code (instance_upload.h), timed apart.
//
//   crowdview_frame_bench [--count N] [--archetypes K] [--frames F] [--threads T] [--clips C]
//                         [--upload map|gl|copy|none] [--gl-device auto|software|N] [--require-gpu] [--report JSON]
// (--threads: default crowdview's, the hardware's; --clips: clips per
// archetype, default 3, joined in a ring by transitions both ways; 1 is a v1 bundle's one cycle;
// --upload: map (default), as crowdview: the lists built straight into mapped GL buffers of a
// headless context as crowdview --headless makes it (the upload figure is the mapping and unmapping);
// gl: built into vectors, then copied into the buffers (glBufferData); either falls back, with a
// message, to copy where no context can be made; copy: memcpy of the vectors into a staging
// buffer; none: no upload; --gl-device and --require-gpu: the context, as crowdview's, and with
// either no fallback to copy: no such context exits 3)
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
#include <memory>
#include <string>
#include <thread>

#include <time.h>
#include <vector>

#include <epoxy/gl.h>
#include <nlohmann/json.hpp>

#include "crowd.h"
#include "crowd_layout.h"
#include "gl_context.h"
#include "instance_upload.h"

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

// This process's CPU time in ms: what a step cost, without other programs' share of the cores.
double cpu_now_ms() {
    timespec t;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
    return 1e3 * double(t.tv_sec) + 1e-6 * double(t.tv_nsec);
}

double wall_now_ms() { return 1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count(); }

enum class Upload { map, gl, copy, none };

// Where the frame's instances go: GL buffers per archetype (instance_upload.h), or a staging copy.
struct Uploader {
    Upload kind = Upload::none;
    std::vector<InstanceBuffers> buffers;
    MappedInstanceStorage mapped;  // kind map: build_frames writes into the buffers
    std::vector<ImpostorSamples> nearest_samples;
    std::vector<uint8_t> staging;

    // The bytes of every list of every archetype, into the GL buffers or the staging buffer.
    uint64_t run(const std::vector<FrameInstances>& out) {
        if (kind == Upload::map) {  // build_frames wrote the lists there
            glFlush();
            return mapped.bytes();
        }
        uint64_t bytes = 0;
        for (size_t a = 0; a < out.size(); ++a) {
            if (kind == Upload::gl) {
                bytes += upload_instances(out[a], buffers[a], &nearest_samples);
                continue;
            }
            if (kind != Upload::copy) continue;
            auto copy = [&](const void* data, size_t n) {
                if (staging.size() < bytes + n) staging.resize(bytes + n);
                if (n) std::memcpy(staging.data() + bytes, data, n);
                bytes += n;
            };
            for (const std::vector<Instance>& list : out[a].by_lod) copy(list.data(), list.size() * sizeof(Instance));
            copy(out[a].impostor_samples.data(), out[a].impostor_samples.size() * sizeof(ImpostorSamples));
        }
        if (kind == Upload::gl) glFlush();  // hands the copies to the driver, as a frame's draws would
        return bytes;
    }
};

}  // namespace

int main(int argc, char** argv) {
    uint64_t count = 100000;
    int archetypes = 4, frames = 60, threads = 0, clips = 3;  // threads 0: as crowdview (frame_threads)
    std::string report_path, upload_name = "map";
    GlDeviceChoice gl_device;
    bool require_gpu = false;
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
        else if (a == "--upload") upload_name = next();
        else if (a == "--require-gpu") require_gpu = true;
        else if (a == "--gl-device") {
            const std::string v = next();
            if (!parse_gl_device(v, &gl_device)) {
                std::fprintf(stderr, "crowdview_frame_bench: --gl-device is auto, software or an EGL device number, not '%s'\n", v.c_str());
                return 2;
            }
        } else {
            std::fprintf(stderr, "crowdview_frame_bench: unknown argument '%s'\n", a.c_str());
            return 2;
        }
    }
    if (count < 1 || archetypes < 1 || archetypes > 4 || frames < 1 || threads < 0 || threads > 64 || clips < 1 || clips > 64) {
        std::fprintf(stderr, "crowdview_frame_bench: --count >= 1, --archetypes 1..4, --frames >= 1, --threads 1..64, --clips 1..64\n");
        return 2;
    }
    if (upload_name != "map" && upload_name != "gl" && upload_name != "copy" && upload_name != "none") {
        std::fprintf(stderr, "crowdview_frame_bench: --upload takes map, gl, copy or none, not '%s'\n", upload_name.c_str());
        return 2;
    }
    if (threads == 0) threads = int(frame_threads());
    // The upload: GL buffers in a headless context as crowdview --headless makes one (gl_context.h).
    Uploader uploader;
    uploader.kind = upload_name == "map"  ? Upload::map
                    : upload_name == "gl" ? Upload::gl
                    : upload_name == "copy" ? Upload::copy
                                            : Upload::none;
    std::unique_ptr<GlContext> context;
    std::string upload_label = upload_name;
    const bool context_chosen = require_gpu || gl_device.kind != GlDeviceChoice::automatic;
    if (context_chosen && (uploader.kind == Upload::copy || uploader.kind == Upload::none)) {
        std::fprintf(stderr, "crowdview_frame_bench: --gl-device and --require-gpu need --upload map or gl\n");
        return 2;
    }
    if (uploader.kind == Upload::map || uploader.kind == Upload::gl) {
        GlContextDesc desc;
        desc.width = 64, desc.height = 64;
        desc.device = gl_device;
        desc.require_gpu = require_gpu;
        std::string error;
        context = GlContext::create(desc, &error);
        if (!context && context_chosen) {
            std::fprintf(stderr, "crowdview_frame_bench: %s\n", error.c_str());
            return 3;
        }
        if (!context) {
            std::printf("crowdview_frame_bench: no OpenGL context (%s): timing a copy of the same bytes into a staging buffer instead\n",
                        error.c_str());
            uploader.kind = Upload::copy;
            upload_label = "copy (no OpenGL context: " + error + ")";
        } else {
            upload_label = upload_name + ": " + context->describe();
            std::printf("crowdview_frame_bench: %s\n", gl_context_line(context->info()).c_str());
            uploader.buffers.resize(size_t(archetypes));
            for (InstanceBuffers& b : uploader.buffers) {
                glGenBuffers(3, b.by_lod);
                glGenBuffers(1, &b.impostor_samples);
            }
            uploader.mapped.buffers = uploader.buffers;
        }
    }
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
            std::vector<ArchetypeFrame> builds;
            for (size_t a = 0; a < models.size(); ++a) builds.push_back({&crowds[a], &models[a], &rules[a], &state[a], &out[a]});
            std::vector<double> ms, cpu_ms, upload_ms, upload_cpu_ms, total_ms, total_cpu_ms;
            uint64_t lods[3] = {0, 0, 0}, culled = 0, upload_bytes = 0;
            for (int f = -2; f < frames; ++f) {  // two warm-up frames size the vectors and buffers
                const float time_s = 30.0f + float(std::max(f, 0)) * kFixedTimeStep;
                const double wall0 = wall_now_ms(), cpu0 = cpu_now_ms();
                const double map_wall0 = uploader.mapped.wall_ms(), map_cpu0 = uploader.mapped.cpu_ms();
                // Chunks of every archetype over `threads` threads, as crowdview's frame loop does (build_frames).
                build_frames(builds, camera, aspect, LodMode::automatic, time_s, blend, unsigned(threads),
                             uploader.kind == Upload::map ? &uploader.mapped : nullptr);
                const double wall1 = wall_now_ms(), cpu1 = cpu_now_ms();
                // Mapping: the map and unmap inside build_frames count as upload, not build.
                const double map_wall = uploader.mapped.wall_ms() - map_wall0, map_cpu = uploader.mapped.cpu_ms() - map_cpu0;
                upload_bytes = uploader.run(out);
                const double wall2 = wall_now_ms(), cpu2 = cpu_now_ms();
                if (f < 0) continue;
                ms.push_back(wall1 - wall0 - map_wall), cpu_ms.push_back(cpu1 - cpu0 - map_cpu);
                upload_ms.push_back(wall2 - wall1 + map_wall), upload_cpu_ms.push_back(cpu2 - cpu1 + map_cpu);
                total_ms.push_back(wall2 - wall0), total_cpu_ms.push_back(cpu2 - cpu0);
            }
            for (const FrameInstances& o : out) {
                for (int l = 0; l < 3; ++l) lods[l] += o.shown[l];
                culled += o.culled;
            }
            const double med = median(ms), mean = [&] {
                double s = 0;
                for (double v : ms) s += v;
                return s / double(ms.size());
            }();
            std::printf("%s camera, impostor blend %s: %.2f ms CPU a frame (build %.2f + upload %.2f [%s]; wall %.2f + %.2f; medians of %d, "
                        "build mean %.2f) for %llu characters of %d archetypes: %llu high, %llu low, %llu impostor, %llu culled; %.1f MB uploaded\n",
                        view.name, blend == ImpostorBlend::off ? "off" : "warp", median(total_cpu_ms), median(cpu_ms), median(upload_cpu_ms),
                        uploader.kind == Upload::map ? "map" : uploader.kind == Upload::gl ? "gl" : uploader.kind == Upload::copy ? "copy" : "none",
                        med, median(upload_ms), frames, mean, (unsigned long long)count, archetypes, (unsigned long long)lods[0],
                        (unsigned long long)lods[1], (unsigned long long)lods[2], (unsigned long long)culled, 1e-6 * double(upload_bytes));
            results.push_back({{"camera", view.name},
                               {"impostor_blend", blend == ImpostorBlend::off ? "off" : "warp"},
                               {"median_ms", med},
                               {"mean_ms", mean},
                               {"median_cpu_ms", median(cpu_ms)},
                               {"upload_median_ms", median(upload_ms)},
                               {"upload_median_cpu_ms", median(upload_cpu_ms)},
                               {"upload_bytes", upload_bytes},
                               {"total_median_ms", median(total_ms)},
                               {"total_median_cpu_ms", median(total_cpu_ms)},
                               {"lod_counts", {{"high", lods[0]}, {"low", lods[1]}, {"impostor", lods[2]}, {"culled", culled}}}});
        }
    }
    const nlohmann::json report = {{"what", "ms per frame: culling, LOD choice, clip state and instance-buffer fill (build_frames), "
                                            "and the instance upload (instance_upload.h: map, the mapping and unmapping of the "
                                            "buffers the fill writes; gl, the copy after it); total = both"},
                                   {"upload", upload_label},
                                   {"gl", context ? gl_report(context->info()) : nlohmann::json(nullptr)},
                                   {"failed_maps", uploader.mapped.failed_maps()},  // map: lists built aside and copied
                                   {"lost_unmaps", uploader.mapped.lost_unmaps()},
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
