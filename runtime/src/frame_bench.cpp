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
#include <utility>

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

// The command line: counts, threads and the upload kind; bad values exit 2 with one line.
struct BenchArgs {
    uint64_t count = 100000;
    int archetypes = 4, frames = 60, threads = 0, clips = 3;  // threads 0: as crowdview (frame_threads)
    std::string report_path, upload_name = "map";
    GlDeviceChoice gl_device;
    bool require_gpu = false;
    // --gl-device or --require-gpu given: that context or none, never the staging copy instead.
    bool context_chosen() const { return require_gpu || gl_device.kind != GlDeviceChoice::automatic; }
};

[[noreturn]] void bench_usage_error(const std::string& message) {
    std::fprintf(stderr, "crowdview_frame_bench: %s\n", message.c_str());
    std::exit(2);
}

BenchArgs parse_bench_args(int argc, char** argv) {
    BenchArgs b;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        auto next = [&]() -> const char* {
            if (i + 1 >= argc) bench_usage_error(a + " needs a value");
            return argv[++i];
        };
        if (a == "--count") b.count = std::strtoull(next(), nullptr, 10);
        else if (a == "--archetypes") b.archetypes = std::atoi(next());
        else if (a == "--frames") b.frames = std::atoi(next());
        else if (a == "--threads") b.threads = std::atoi(next());
        else if (a == "--clips") b.clips = std::atoi(next());
        else if (a == "--report") b.report_path = next();
        else if (a == "--upload") b.upload_name = next();
        else if (a == "--require-gpu") b.require_gpu = true;
        else if (a == "--gl-device") {
            const std::string v = next();
            if (!parse_gl_device(v, &b.gl_device)) bench_usage_error("--gl-device is auto, software or an EGL device number, not '" + v + "'");
        } else {
            bench_usage_error("unknown argument '" + a + "'");
        }
    }
    if (b.count < 1 || b.archetypes < 1 || b.archetypes > 4 || b.frames < 1 || b.threads < 0 || b.threads > 64 || b.clips < 1 ||
        b.clips > 64)
        bench_usage_error("--count >= 1, --archetypes 1..4, --frames >= 1, --threads 1..64, --clips 1..64");
    if (b.upload_name != "map" && b.upload_name != "gl" && b.upload_name != "copy" && b.upload_name != "none")
        bench_usage_error("--upload takes map, gl, copy or none, not '" + b.upload_name + "'");
    if (b.context_chosen() && b.upload_name != "map" && b.upload_name != "gl")
        bench_usage_error("--gl-device and --require-gpu need --upload map or gl");
    if (b.threads == 0) b.threads = int(frame_threads());
    return b;
}

const char* upload_name(Upload kind) {
    return kind == Upload::map ? "map" : kind == Upload::gl ? "gl" : kind == Upload::copy ? "copy" : "none";
}

// The upload: GL buffers in a headless context as crowdview --headless makes one (gl_context.h),
// a staging copy where none can be made (unless the context was chosen: then exit 3). Returns the
// report's label of the upload.
std::string open_uploader(const BenchArgs& b, Uploader* uploader, std::unique_ptr<GlContext>* context) {
    uploader->kind = b.upload_name == "map"    ? Upload::map
                     : b.upload_name == "gl"   ? Upload::gl
                     : b.upload_name == "copy" ? Upload::copy
                                               : Upload::none;
    if (uploader->kind != Upload::map && uploader->kind != Upload::gl) return b.upload_name;
    GlContextDesc desc;
    desc.width = 64, desc.height = 64;
    desc.device = b.gl_device;
    desc.require_gpu = b.require_gpu;
    std::string error;
    *context = GlContext::create(desc, &error);
    if (!*context && b.context_chosen()) {
        std::fprintf(stderr, "crowdview_frame_bench: %s\n", error.c_str());
        std::exit(3);
    }
    if (!*context) {
        std::printf("crowdview_frame_bench: no OpenGL context (%s): timing a copy of the same bytes into a staging buffer instead\n",
                    error.c_str());
        uploader->kind = Upload::copy;
        return "copy (no OpenGL context: " + error + ")";
    }
    std::printf("crowdview_frame_bench: %s\n", gl_context_line((*context)->info()).c_str());
    uploader->buffers.resize(size_t(b.archetypes));
    for (InstanceBuffers& buffers : uploader->buffers) {
        glGenBuffers(3, buffers.by_lod);
        glGenBuffers(1, &buffers.impostor_samples);
    }
    uploader->mapped.buffers = uploader->buffers;
    return b.upload_name + ": " + (*context)->describe();
}

// The first `archetypes` shapes as models and layout traits, `count` characters shared out evenly.
void make_archetypes(const BenchArgs& b, std::vector<CharacterModel>* models, std::vector<ArchetypeTraits>* traits) {
    for (int k = 0; k < b.archetypes; ++k) {
        models->push_back(model_of(kShapes[k], uint32_t(b.clips)));
        const CharacterModel& m = models->back();
        ArchetypeTraits t;
        t.count = b.count / b.archetypes + (uint64_t(k) < b.count % b.archetypes ? 1 : 0);
        t.spacing = crowd_spacing(m.radius);
        t.cycle_seconds = float(kShapes[k].frames) / m.frames_per_second;
        for (const ClipRange& c : m.clips) t.clip_seconds.push_back(float(c.frames) / m.frames_per_second);
        t.variations = 8, t.outfits = 8;
        t.play_rate[0] = 0.9f, t.play_rate[1] = 1.1f;
        traits->push_back(t);
    }
}

// Per timed frame: build and upload, wall and CPU ms, the mapping counted as upload.
struct FrameTimes {
    std::vector<double> ms, cpu_ms, upload_ms, upload_cpu_ms, total_ms, total_cpu_ms;
    uint64_t upload_bytes = 0;  // the last frame's
};

// `frames` frames (after two warm-up frames that size the vectors and buffers) from 30 s in.
FrameTimes time_frames(const std::vector<ArchetypeFrame>& builds, const Camera& camera, float aspect, ImpostorBlend blend,
                       const BenchArgs& b, Uploader* uploader, const std::vector<FrameInstances>& out) {
    FrameTimes t;
    for (int f = -2; f < b.frames; ++f) {
        const float time_s = 30.0f + float(std::max(f, 0)) * kFixedTimeStep;
        const double wall0 = wall_now_ms(), cpu0 = cpu_now_ms();
        const double map_wall0 = uploader->mapped.wall_ms(), map_cpu0 = uploader->mapped.cpu_ms();
        // Chunks of every archetype over `threads` threads, as crowdview's frame loop does (build_frames).
        build_frames(builds, camera, aspect, LodMode::automatic, time_s, blend, unsigned(b.threads),
                     uploader->kind == Upload::map ? &uploader->mapped : nullptr);
        const double wall1 = wall_now_ms(), cpu1 = cpu_now_ms();
        // Mapping: the map and unmap inside build_frames count as upload, not build.
        const double map_wall = uploader->mapped.wall_ms() - map_wall0, map_cpu = uploader->mapped.cpu_ms() - map_cpu0;
        t.upload_bytes = uploader->run(out);
        const double wall2 = wall_now_ms(), cpu2 = cpu_now_ms();
        if (f < 0) continue;
        t.ms.push_back(wall1 - wall0 - map_wall), t.cpu_ms.push_back(cpu1 - cpu0 - map_cpu);
        t.upload_ms.push_back(wall2 - wall1 + map_wall), t.upload_cpu_ms.push_back(cpu2 - cpu1 + map_cpu);
        t.total_ms.push_back(wall2 - wall0), t.total_cpu_ms.push_back(cpu2 - cpu0);
    }
    return t;
}

// One camera and blend: the frames timed, one line printed, the figures as the report's entry.
nlohmann::json bench_view(const char* view_name, Camera camera, ImpostorBlend blend, const std::vector<CharacterModel>& models,
                          const std::vector<Crowd>& crowds, const BenchArgs& b, Uploader* uploader) {
    const float aspect = 1280.0f / 720.0f, height_px = 720.0f;
    camera.near_m = 0.1f, camera.far_m = std::max(camera.far_m * 4.0f, 200.0f);
    std::vector<LodRule> rules;
    for (const CharacterModel& m : models) rules.push_back(lod_rule_for(m, camera, height_px));
    std::vector<FrameState> state(models.size());
    std::vector<FrameInstances> out(models.size());
    std::vector<ArchetypeFrame> builds;
    for (size_t a = 0; a < models.size(); ++a) builds.push_back({&crowds[a], &models[a], &rules[a], &state[a], &out[a]});
    const FrameTimes t = time_frames(builds, camera, aspect, blend, b, uploader, out);
    uint64_t lods[3] = {0, 0, 0}, culled = 0;
    for (const FrameInstances& o : out) {
        for (int l = 0; l < 3; ++l) lods[l] += o.shown[l];
        culled += o.culled;
    }
    double sum = 0;
    for (double v : t.ms) sum += v;
    const double med = median(t.ms), mean = sum / double(t.ms.size());
    const char* blend_name = blend == ImpostorBlend::off ? "off" : "warp";
    std::printf("%s camera, impostor blend %s: %.2f ms CPU a frame (build %.2f + upload %.2f [%s]; wall %.2f + %.2f; medians of %d, "
                "build mean %.2f) for %llu characters of %d archetypes: %llu high, %llu low, %llu impostor, %llu culled; %.1f MB uploaded\n",
                view_name, blend_name, median(t.total_cpu_ms), median(t.cpu_ms), median(t.upload_cpu_ms), upload_name(uploader->kind), med,
                median(t.upload_ms), b.frames, mean, (unsigned long long)b.count, b.archetypes, (unsigned long long)lods[0],
                (unsigned long long)lods[1], (unsigned long long)lods[2], (unsigned long long)culled, 1e-6 * double(t.upload_bytes));
    return {{"camera", view_name},
            {"impostor_blend", blend_name},
            {"median_ms", med},
            {"mean_ms", mean},
            {"median_cpu_ms", median(t.cpu_ms)},
            {"upload_median_ms", median(t.upload_ms)},
            {"upload_median_cpu_ms", median(t.upload_cpu_ms)},
            {"upload_bytes", t.upload_bytes},
            {"total_median_ms", median(t.total_ms)},
            {"total_median_cpu_ms", median(t.total_cpu_ms)},
            {"lod_counts", {{"high", lods[0]}, {"low", lods[1]}, {"impostor", lods[2]}, {"culled", culled}}}};
}

}  // namespace

int main(int argc, char** argv) {
    const BenchArgs b = parse_bench_args(argc, argv);
    Uploader uploader;
    std::unique_ptr<GlContext> context;
    const std::string upload_label = open_uploader(b, &uploader, &context);
    std::vector<CharacterModel> models;
    std::vector<ArchetypeTraits> traits;
    make_archetypes(b, &models, &traits);
    CrowdFile file;
    file.seed = 1;
    const auto layout_start = std::chrono::steady_clock::now();
    const std::vector<Crowd> crowds = lay_out_crowd(file, traits, nullptr);
    const double layout_ms = 1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now() - layout_start).count();
    Crowd extent;
    extent.half_extent = crowds_half_extent(crowds);
    const float aspect = 1280.0f / 720.0f, character_height = 4.2f;

    // Overview: the whole crowd on screen, nearly all impostors. Eye level: a person standing 2 m in
    // from the crowd's front edge looking across it, so meshes near, impostors far, most culled.
    const Camera eye_level = look_at(glm::vec3(0, 1.7f, extent.half_extent - 2.0f), glm::vec3(0, 1.2f, 0));
    const std::pair<const char*, Camera> views[] = {{"overview", camera_for_crowd(extent, character_height, aspect, 0.35f)},
                                                    {"eye-level", eye_level}};
    nlohmann::json results = nlohmann::json::array();
    for (const auto& [name, camera] : views)
        for (ImpostorBlend blend : {ImpostorBlend::warp, ImpostorBlend::off})  // crowdview's default and the paper's
            results.push_back(bench_view(name, camera, blend, models, crowds, b, &uploader));
    const nlohmann::json report = {{"what", "ms per frame: culling, LOD choice, clip state and instance-buffer fill (build_frames), "
                                            "and the instance upload (instance_upload.h: map, the mapping and unmapping of the "
                                            "buffers the fill writes; gl, the copy after it); total = both"},
                                   {"upload", upload_label},
                                   {"gl", context ? gl_report(context->info()) : nlohmann::json(nullptr)},
                                   {"failed_maps", uploader.mapped.failed_maps()},  // map: lists built aside and copied
                                   {"lost_unmaps", uploader.mapped.lost_unmaps()},
                                   {"characters", b.count},
                                   {"clips_per_archetype", b.clips},
                                   {"archetypes", b.archetypes},
                                   {"threads", b.threads},
                                   {"frames", b.frames},
                                   {"hardware_threads", std::thread::hardware_concurrency()},
                                   {"layout_ms", layout_ms},
                                   {"results", results}};
    if (!b.report_path.empty()) {
        std::ofstream out(b.report_path);
        if (!(out << report.dump(2) << "\n")) {
            std::fprintf(stderr, "crowdview_frame_bench: cannot write %s\n", b.report_path.c_str());
            return 1;
        }
    }
    return 0;
}
