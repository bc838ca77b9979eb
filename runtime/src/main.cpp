// crowdview: shows a crowdbake bundle as a crowd, in a window, headless, or as a benchmark.
//
//   crowdview (--bundle DIR | --url URL | --crowd FILE) [--cache DIR] [--count N] [--seed S] [--layout spot|paths]
//             [--headless --frames N --screenshot out.png] [--benchmark --report out.json] [--gl-device auto|software|N] [--require-gpu]
//             [--width W --height H] [--lod auto|high|low|impostor|detail] [--impostor-blend off|views|frames|full|warp]
//             [--key KEY] [--cache-budget-mib N] [--min-rate B] [--timeout S] [--clips NAME=W,...] [--switch-after LO,HI]
//   crowdview --verify DIR|URL
//
// Exit status: 0 success, 1 a bundle or file was refused or a run failed, 2 bad arguments,
// 3 no OpenGL context could be created here (--require-gpu: none on a GPU).
#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "archetypes.h"
#include "benchmark.h"
#include "cli_parse.h"
#include "bundle.h"
#include "crowd.h"
#include "fetch.h"
#include "fly_controls.h"
#include "gl_context.h"
#include "renderer.h"
#include "switch_report.h"

#ifndef CROWDVIEW_SHADER_DIR
#define CROWDVIEW_SHADER_DIR "shaders"
#endif

using namespace crowdview;

namespace {

constexpr int kExitRefused = 1, kExitUsage = 2, kExitNoGl = 3;
// Set before main runs: --max-seconds counts from here, loading and context creation included.
const std::chrono::steady_clock::time_point kProcessStart = std::chrono::steady_clock::now();

// --lod: a LOD rule for everyone, or one representation for everyone.
enum class LodChoice { automatic, high, low, impostor, detail };
enum class CameraView { overview, street };

// The command line, parsed and checked once.
struct Options {
    std::string source;        // a bundle folder or URL (--bundle, --url or --verify)
    std::string crowd_file;    // --crowd: a crowd description (crowd_file.h) instead of one bundle
    bool crowd_flags = false;  // --count, --seed or --layout given: they belong in the description
    bool source_is_url = false;  // holds "://": fetched through the cache
    bool verify_only = false;  // --verify
    std::string cache_dir, files_prefix = "files/", shader_dir;
    std::string api_key;       // --key, else $CROWDVIEW_API_KEY; never printed
    uint64_t cache_budget_mib = 4096;
    double min_rate = 0, timeout_s = 0;  // 0: FetchOptions' defaults
    uint32_t count = 100;
    uint64_t seed = 1;
    Layout layout = Layout::on_the_spot;
    bool headless = false, benchmark = false;
    GlDeviceChoice gl_device;  // --gl-device: headless only
    bool require_gpu = false;
    int frames = -1;  // -1: until the window closes (headless: 1)
    std::string screenshot, report;
    int width = 1280, height = 720;
    LodChoice lod = LodChoice::automatic;
    CameraView camera = CameraView::overview;
    ImpostorKind impostors = ImpostorKind::uv;  // what LodChoice::automatic draws far away
    ImpostorBlend blend = ImpostorBlend::warp;
    bool blend_chosen = false;      // --impostor-blend given: no note about its cost
    double progress_every_s = 2;    // headless: a "frame k of N" line at most this often
    double max_seconds = 300;
    std::vector<BenchmarkMode> modes{std::begin(kAllBenchmarkModes), std::end(kAllBenchmarkModes)};
    bool cpu_decode = false;
    // --switch-view: one character at the origin seen from (azimuth, elevation) degrees at the impostor
    // switch distance, at cycle frame `frame` (the bake's fidelity cameras, for comparing pictures).
    bool switch_view = false;
    float switch_azimuth_deg = 0, switch_elevation_deg = 0;
    int switch_frame = 0;
    std::vector<ClipWeight> clips;  // --clips: the clip mix of a lone bundle
    float switch_after_s[2] = {kDefaultSwitchAfterS[0], kDefaultSwitchAfterS[1]};
};

const char* kUsage =
    "usage: crowdview (--bundle DIR | --url URL | --crowd FILE) [options]\n"
    "       crowdview --verify DIR|URL [--cache DIR] [--files-prefix P]\n"
    "  --bundle DIR          a bundle folder (manifest.json and its files)\n"
    "  --url URL             a published bundle: URL/manifest.json and URL/<files-prefix><path>\n"
    "  --crowd FILE          a crowd description (JSON, shared_formats/crowd.schema.json): several archetypes\n"
    "  --cache DIR           content-addressed download cache (default ~/.cache/crowdview)\n"
    "  --files-prefix P      where files sit below the bundle URL (default files/)\n"
    "  --key KEY             API key sent as a bearer token (default: $CROWDVIEW_API_KEY)\n"
    "  --cache-budget-mib N  refuse bundles listing more than N MiB (default 4096)\n"
    "  --min-rate B          each file must arrive at B bytes/s or faster (default 65536)\n"
    "  --timeout S           give up a whole fetch after S seconds (default: 60 + size / min rate)\n"
    "  --count N             characters (default 100)\n"
    "  --seed S              crowd seed (default 1)\n"
    "  --layout spot|paths   walk on the spot (default, the paper's test) or along paths\n"
    "  --lod MODE            auto (default) | high | low | impostor | detail\n"
    "  --camera VIEW         overview (default: the whole crowd) | street (eye level at the crowd's edge)\n"
    "  --impostors uv|detail impostor maps used by --lod auto (default uv)\n"
    "  --clips NAME=W,...    clip mix: which clips characters play, by weight (default: every clip alike)\n"
    "  --switch-after LO,HI  seconds a character dwells in a clip before switching (default 4,10)\n"
    "  --impostor-blend B    off (the paper: nearest view and frame) | views | frames | full |\n"
    "                        warp (default: full, reprojected by the bundle's surface map; full without one)\n"
    "  --width W --height H  framebuffer size (default 1280x720)\n"
    "  --switch-view A,E,F   one character (heading 0, variation 0, outfit 0) seen from azimuth A, elevation E\n"
    "                        (degrees) at the impostor switch distance, at cycle frame F\n"
    "  --headless            no window: a GPU's EGL device, else EGL surfaceless, else a hidden GLFW window\n"
    "  --gl-device D         headless: auto (default, as above) | software (Mesa's software EGL device) | N (EGL device N)\n"
    "  --require-gpu         exit 3 where the context renders on a software rasteriser (llvmpipe, softpipe, swrast)\n"
    "  --frames N            frames to draw, then exit (headless default 1)\n"
    "  --progress-every S    headless: print \"frame k of N\" every S seconds of wall time (default 2)\n"
    "  --screenshot PNG      write the last frame\n"
    "  --benchmark           largest crowd at 30 and 60 fps per representation (headless)\n"
    "  --report JSON         benchmark figures; headless: counts per archetype and LOD, GPU memory per archetype\n"
    "  --max-seconds S       benchmark time budget in seconds, every phase included (default 300)\n"
    "  --modes LIST          benchmark these of high_mesh,low_mesh,uv_impostor,detail_impostor,hybrid\n"
    "  --shaders DIR         shader folder (default: the source tree's src/shaders)\n"
    "  --cpu-decode          upload BC textures decoded to RGBA8 even where S3TC exists\n";

[[noreturn]] void usage_error(const std::string& message) {
    std::fprintf(stderr, "crowdview: %s (see --help)\n", message.c_str());
    std::exit(kExitUsage);
}

bool is_url(const std::string& s) { return s.find("://") != std::string::npos; }

Options parse_args(int argc, char** argv) {
    Options o;
    auto value = [&](int& i) -> const char* {
        if (i + 1 >= argc) usage_error(std::string(argv[i]) + " needs a value");
        return argv[++i];
    };
    int sources = 0;
    std::string modes;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--help" || a == "-h") {
            std::fputs(kUsage, stdout);
            std::exit(0);
        } else if (a == "--bundle" || a == "--url" || a == "--verify") {
            o.source = value(i);
            o.source_is_url = is_url(o.source);
            o.verify_only = a == "--verify";
            ++sources;
        } else if (a == "--crowd") {
            o.crowd_file = value(i);
            ++sources;
        } else if (a == "--cache") o.cache_dir = value(i);
        else if (a == "--key") o.api_key = value(i);
        else if (a == "--cache-budget-mib") o.cache_budget_mib = parse_number<uint64_t>(a, value(i), 1, 1ull << 30);
        else if (a == "--min-rate") o.min_rate = parse_number<double>(a, value(i), 1, 1e12);
        else if (a == "--timeout") o.timeout_s = parse_number<double>(a, value(i), 0.1, 1e7);
        else if (a == "--files-prefix") o.files_prefix = value(i);
        else if (a == "--shaders") o.shader_dir = value(i);
        else if (a == "--count") o.count = parse_number<uint32_t>(a, value(i), 1, 10000000), o.crowd_flags = true;
        else if (a == "--seed") o.seed = parse_number<uint64_t>(a, value(i), 0, 1ull << 53), o.crowd_flags = true;
        else if (a == "--frames") o.frames = parse_number<int>(a, value(i), 1, 100000000);
        else if (a == "--width") o.width = parse_number<int>(a, value(i), 16, 16384);
        else if (a == "--height") o.height = parse_number<int>(a, value(i), 16, 16384);
        else if (a == "--max-seconds") o.max_seconds = parse_number<double>(a, value(i), 1, 86400);
        else if (a == "--screenshot") o.screenshot = value(i);
        else if (a == "--modes") modes = value(i);
        else if (a == "--report") o.report = value(i);
        else if (a == "--headless") o.headless = true;
        else if (a == "--benchmark") o.benchmark = true;
        else if (a == "--cpu-decode") o.cpu_decode = true;
        else if (a == "--require-gpu") o.require_gpu = true;
        else if (a == "--gl-device") {
            const std::string v = value(i);
            if (!parse_gl_device(v, &o.gl_device)) usage_error("--gl-device is auto, software or an EGL device number; got '" + v + "'");
        }
        else if (a == "--layout")
            o.crowd_flags = true, o.layout = parse_choice<Layout>(a, value(i), {{"spot", Layout::on_the_spot}, {"paths", Layout::paths}});
        else if (a == "--camera")
            o.camera = parse_choice<CameraView>(a, value(i), {{"overview", CameraView::overview}, {"street", CameraView::street}});
        else if (a == "--lod")
            o.lod = parse_choice<LodChoice>(a, value(i), {{"auto", LodChoice::automatic}, {"high", LodChoice::high}, {"low", LodChoice::low},
                                                          {"impostor", LodChoice::impostor}, {"detail", LodChoice::detail}});
        else if (a == "--progress-every") o.progress_every_s = parse_number<double>(a, value(i), 1e-6, 86400);
        else if (a == "--impostor-blend")
            o.blend_chosen = true, o.blend = parse_choice<ImpostorBlend>(a, value(i), {{"off", ImpostorBlend::off}, {"views", ImpostorBlend::views},
                                                                {"frames", ImpostorBlend::frames}, {"full", ImpostorBlend::full},
                                                                {"warp", ImpostorBlend::warp}});
        else if (a == "--switch-view") {
            const std::string v = value(i);
            char rest = 0;
            if (std::sscanf(v.c_str(), "%f,%f,%d%c", &o.switch_azimuth_deg, &o.switch_elevation_deg, &o.switch_frame, &rest) != 3 ||
                o.switch_frame < 0 || std::fabs(o.switch_elevation_deg) > 90.0f)
                usage_error("--switch-view takes AZIMUTH,ELEVATION,FRAME (degrees, elevation within +-90, frame >= 0); got '" + v + "'");
            o.switch_view = true;
        } else if (a == "--clips") {
            const std::string v = value(i);
            for (size_t start = 0; start <= v.size();) {
                const size_t end = std::min(v.find(',', start), v.size()), eq = v.find('=', start);
                ClipWeight w;
                w.clip = v.substr(start, std::min(eq, end) - start);
                if (eq < end) w.weight = parse_number<float>("--clips weight of '" + w.clip + "'", v.substr(eq + 1, end - eq - 1).c_str(), 0, 1e6f);
                if (w.clip.empty() || !(w.weight > 0)) usage_error("--clips takes NAME=WEIGHT,NAME=WEIGHT,...; got '" + v + "'");
                o.clips.push_back(w);
                start = end + 1;
            }
        } else if (a == "--switch-after") {
            const std::string v = value(i);
            char rest = 0;
            float* s = o.switch_after_s;
            if (std::sscanf(v.c_str(), "%f,%f%c", &s[0], &s[1], &rest) != 2 || !(s[0] >= 0 && s[0] <= s[1] && s[1] <= 86400))
                usage_error("--switch-after takes LO,HI seconds (0 <= LO <= HI <= 86400); got '" + v + "'");
        } else if (a == "--impostors")
            o.impostors = parse_choice<ImpostorKind>(a, value(i), {{"uv", ImpostorKind::uv}, {"detail", ImpostorKind::detail}});
        else usage_error("unknown argument '" + a + "'");
    }
    if (sources == 0) usage_error("give --bundle DIR, --url URL, --crowd FILE or --verify DIR|URL");
    if (sources > 1) usage_error("give only one of --bundle, --url, --crowd and --verify");
    if (o.benchmark && !o.screenshot.empty()) usage_error("--screenshot does not go with --benchmark");
    if (!o.report.empty() && !o.benchmark && !o.headless) usage_error("--report needs --benchmark or --headless");
    if (o.gl_device.kind != GlDeviceChoice::automatic && !o.benchmark && !o.headless) usage_error("--gl-device needs --benchmark or --headless");
    if (!o.crowd_file.empty() && o.crowd_flags) usage_error("--count, --seed and --layout go in the --crowd description");
    if (!o.crowd_file.empty() && !o.clips.empty()) usage_error("--clips goes in the --crowd description's archetypes (\"clips\")");
    if (!o.crowd_file.empty() && (o.benchmark || o.switch_view)) usage_error("--benchmark and --switch-view take --bundle or --url");
    if (!modes.empty()) {
        o.modes.clear();
        for (size_t start = 0; start <= modes.size();) {
            const size_t end = std::min(modes.find(',', start), modes.size());
            const std::string name = modes.substr(start, end - start);
            BenchmarkMode mode;
            if (!parse_benchmark_mode(name, &mode))
                usage_error("--modes takes high_mesh, low_mesh, uv_impostor, detail_impostor, hybrid; got '" + name + "'");
            if (std::find(o.modes.begin(), o.modes.end(), mode) == o.modes.end()) o.modes.push_back(mode);
            start = end + 1;
        }
    }
    if (o.api_key.empty()) {
        const char* env = std::getenv("CROWDVIEW_API_KEY");
        o.api_key = env ? env : "";
    }
    if (o.shader_dir.empty()) {
        const char* env = std::getenv("CROWDVIEW_SHADERS");
        o.shader_dir = env && *env ? env : CROWDVIEW_SHADER_DIR;
    }
    return o;
}

FetchOptions fetch_options(const Options& o) {
    FetchOptions fetch;
    fetch.cache_dir = o.cache_dir;
    fetch.files_prefix = o.files_prefix;
    fetch.api_key = o.api_key;
    fetch.cache_budget_bytes = o.cache_budget_mib << 20;
    if (o.min_rate > 0) fetch.min_rate_bytes_per_s = o.min_rate;
    fetch.total_timeout_s = o.timeout_s;
    fetch.log = [](const std::string& line) { std::fprintf(stderr, "%s\n", line.c_str()); };
    return fetch;
}

void log_line(const std::string& line) { std::fprintf(stderr, "crowdview: %s\n", line.c_str()); }

// How build_frame chooses LODs and which impostor maps draw, for a --lod choice.
struct DrawChoice {
    LodMode lod;
    ImpostorKind kind;
};

DrawChoice draw_choice(LodChoice lod, ImpostorKind automatic_impostors) {
    switch (lod) {
    case LodChoice::high: return {LodMode::high, ImpostorKind::uv};
    case LodChoice::low: return {LodMode::low, ImpostorKind::uv};
    case LodChoice::impostor: return {LodMode::impostor, ImpostorKind::uv};
    case LodChoice::detail: return {LodMode::impostor, ImpostorKind::detail};
    case LodChoice::automatic: break;
    }
    return {LodMode::automatic, automatic_impostors};
}

float character_height(const CharacterModel& m) { return m.center.y + m.radius; }

int run_benchmark_mode(const GlContext& context, Renderer& renderer, const Bundle& bundle, const Options& o) {
    BenchmarkDesc desc;
    desc.seed = o.seed;
    desc.max_seconds = o.max_seconds;
    desc.started = kProcessStart;
    desc.modes = o.modes;
    if (bundle.manifest.impostor.detail_map.empty()) {
        const auto detail = std::find(desc.modes.begin(), desc.modes.end(), BenchmarkMode::detail_impostor);
        if (detail != desc.modes.end()) {
            desc.modes.erase(detail);
            std::fprintf(stderr, "crowdview: benchmark: detail_impostor left out: the bundle has no detail maps (bake it with --detail-map)\n");
            if (desc.modes.empty()) return kExitUsage;
        }
    }
    desc.blend = o.blend;
    desc.device = context.describe();
    desc.gl = gl_report(context.info());
    desc.log = [](const std::string& line) { std::fprintf(stderr, "%s\n", line.c_str()); };
    // The report so far after every phase, so a run stopped from outside still leaves one.
    if (!o.report.empty())
        desc.checkpoint = [&](const nlohmann::json& partial) {
            std::ofstream out(o.report);
            out << partial.dump(2) << "\n";
        };
    const std::string text = run_benchmark(renderer, bundle, desc).dump(2) + "\n";
    std::fputs(text.c_str(), stdout);
    if (!o.report.empty()) {
        std::ofstream out(o.report);
        if (!(out << text)) {
            std::fprintf(stderr, "crowdview: cannot write %s\n", o.report.c_str());
            return kExitRefused;
        }
    }
    return 0;
}

// `meters`: one per archetype with --report (the switch measure, switch_report.h), else empty.
int run_view(GlContext& context, Renderer& renderer, const CrowdScene& scene, const Options& o, std::vector<SwitchMeter>& meters) {
    const size_t archetype_count = renderer.archetype_count();
    std::string note;
    std::vector<Crowd> crowds = lay_out_crowd(scene.file, scene.traits, &note);
    if (!note.empty()) log_line(note);
    const CharacterModel& model = renderer.model(0);  // --switch-view: one archetype
    float height = 0;
    for (size_t a = 0; a < archetype_count; ++a) height = std::max(height, character_height(renderer.model(a)));
    Crowd extent;  // the whole crowd's square, for the cameras
    extent.half_extent = crowds_half_extent(crowds);
    const CameraView view = scene.file.camera.kind == CrowdCameraKind::street ? CameraView::street : o.camera;
    Camera camera = view == CameraView::street ? street_camera(extent, height) : camera_for_crowd(extent, height, renderer.aspect(), 0.35f);
    camera.near_m = 0.1f;
    camera.far_m = std::max(camera.far_m * 4.0f, 200.0f);
    if (scene.file.camera.kind == CrowdCameraKind::look_at) {
        camera = look_at(scene.file.camera.eye, scene.file.camera.target);
        camera.far_m = std::max(camera.far_m, 4.0f * (extent.half_extent + glm::length(scene.file.camera.eye)));
    }
    camera.fov_y = glm::radians(scene.file.camera.fov_deg);
    if (o.switch_view) {  // the bake's view (SPEC.md "Impostor maps"): the camera in direction (sin A cos E, sin E, cos A cos E)
        crowds[0].characters.assign(1, Character{glm::vec3(0), 0.0f, 0.0f, 0, 0});
        const float a = glm::radians(o.switch_azimuth_deg), e = glm::radians(o.switch_elevation_deg);
        const float d = impostor_switch_distance(Camera().fov_y, float(renderer.height()), model.radius, model.tile_size);
        camera = look_at(model.center + glm::vec3(std::sin(a) * std::cos(e), std::sin(e), std::cos(a) * std::cos(e)) * d, model.center);
    }
    DrawChoice choice = draw_choice(o.lod, o.impostors);
    // Each archetype's own LOD distances: its impostor radius and tile size set the 1:1 distance.
    std::vector<LodRule> rules(archetype_count);
    for (size_t a = 0; a < archetype_count; ++a) rules[a] = lod_rule_for(renderer.model(a), camera, float(renderer.height()));
    const glm::vec3 light = scene_light_dir();
    std::vector<FrameState> state(archetype_count);
    std::vector<FrameInstances> frame(archetype_count);
    std::vector<ArchetypeFrame> builds(archetype_count);  // every archetype's frame in one build, on every core
    for (size_t a = 0; a < archetype_count; ++a) builds[a] = {&crowds[a], &renderer.model(a), &rules[a], &state[a], &frame[a]};
    const unsigned build_threads = frame_threads();
    std::vector<ArchetypeCounts> counts(archetype_count);
    FlyControls controls;
    const bool windowed = context.visible();
    const int frames = o.frames > 0 ? o.frames : (windowed ? -1 : 1);
    const auto start = std::chrono::steady_clock::now();
    auto last = start, last_progress = start;
    double fps_smoothed = 0, build_seconds = 0;
    std::vector<double> frame_ms;
    float time_s = 0;
    int drawn = 0;
    DrawStats stats;
    for (int i = 0; frames < 0 || i < frames; ++i) {
        if (context.should_close()) break;
        const auto now = std::chrono::steady_clock::now();
        const float dt = windowed ? std::chrono::duration<float>(now - last).count() : kFixedTimeStep;
        last = now;
        time_s = windowed ? time_s + dt : float(i) * kFixedTimeStep;
        // Half a frame in, so floor(t * fps) is the frame asked for.
        if (o.switch_view) time_s = (float(o.switch_frame % std::max(model.frame_count, 1u)) + 0.5f) / model.frames_per_second;
        if (windowed) {
            GLFWwindow* w = context.window();
            controls.update(w, &camera, dt);
            const LodChoice keys[] = {LodChoice::automatic, LodChoice::high, LodChoice::low, LodChoice::impostor, LodChoice::detail};
            for (int k = 0; k < 5; ++k)
                if (glfwGetKey(w, GLFW_KEY_1 + k) == GLFW_PRESS) choice = draw_choice(keys[k], ImpostorKind::uv);
            if (glfwGetKey(w, GLFW_KEY_ESCAPE) == GLFW_PRESS) break;
        }
        // The frame: cull and choose LODs on the CPU for every archetype, then a few instanced
        // draws per archetype.
        const auto build_start = std::chrono::steady_clock::now();
        // Straight into the renderer's mapped instance buffers: draw() then copies nothing.
        build_frames(builds, camera, renderer.aspect(), choice.lod, time_s, o.blend, build_threads, renderer.instance_storage());
        build_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();
        // The switch measure (--report): a few sampled characters, after the timed part.
        const bool blend_frames = o.blend == ImpostorBlend::frames || o.blend == ImpostorBlend::full || o.blend == ImpostorBlend::warp;
        for (size_t a = 0; a < meters.size() && a < archetype_count; ++a)
            meters[a].observe(crowds[a], renderer.model(a), state[a], camera, renderer.width(), renderer.height(), time_s, blend_frames);
        for (size_t a = 0; a < archetype_count; ++a) counts[a].add(frame[a]);
        ++drawn;
        stats = renderer.draw(frame, camera, choice.kind, light);
        if (!o.report.empty() && !windowed) {  // the report times whole frames: wait for the GPU (or llvmpipe)
            renderer.finish();
            frame_ms.push_back(1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count());
        }
        if (windowed) {
            int w = 0, h = 0;
            glfwGetFramebufferSize(context.window(), &w, &h);
            renderer.present(w, h);
            fps_smoothed = fps_smoothed == 0 ? 1.0 / std::max(dt, 1e-4f) : 0.9 * fps_smoothed + 0.1 / std::max(dt, 1e-4f);
            std::string title = "crowdview - " + std::to_string(int(fps_smoothed + 0.5)) + " fps";
            for (size_t a = 0; a < archetype_count; ++a)
                title += (archetype_count > 1 ? " - " + scene.names[a] + ": " : " - ") + lod_summary(counts[a]);
            context.set_title(title.c_str());
            context.swap_and_poll();
        } else if (std::chrono::duration<double>(std::chrono::steady_clock::now() - last_progress).count() >= o.progress_every_s) {
            // Headless runs can take minutes on a software rasteriser: say they are alive.
            renderer.finish();
            last_progress = std::chrono::steady_clock::now();
            std::fprintf(stderr, "crowdview: frame %d of %d, %.1f s elapsed\n", i + 1, frames,
                         std::chrono::duration<double>(last_progress - start).count());
        }
    }
    uint64_t lod_total[3] = {0, 0, 0}, culled = 0;
    for (size_t a = 0; a < archetype_count; ++a) {
        for (int l = 0; l < 3; ++l) lod_total[l] += counts[a].last[l];
        culled += counts[a].last_culled;
        if (archetype_count > 1) log_line("archetype '" + scene.names[a] + "': " + lod_summary(counts[a]));
    }
    std::fprintf(stderr, "crowdview: %s; %llu high, %llu low, %llu impostor, %llu culled; %u draws, %llu triangles\n",
                 context.describe().c_str(), (unsigned long long)lod_total[0], (unsigned long long)lod_total[1],
                 (unsigned long long)lod_total[2], (unsigned long long)culled, stats.draw_calls, (unsigned long long)stats.triangles);
    if (!o.report.empty()) {
        nlohmann::json report = view_report(context.describe(), renderer, scene, counts, rules, drawn, drawn ? 1e3 * build_seconds / drawn : 0, stats);
        report["gl"] = gl_report(context.info());
        // Whole frames, cull to glFinish; the first two warm up (uploads, shader compilation on first use).
        std::vector<double> timed(frame_ms.begin() + std::min<size_t>(2, frame_ms.size() > 2 ? 2 : 0), frame_ms.end());
        std::sort(timed.begin(), timed.end());
        report["frame_ms_median"] = timed.empty() ? 0.0 : timed[timed.size() / 2];
        // Per archetype: characters per clip (and transition) and LOD in the last frame, and the switches' jumps.
        for (size_t a = 0; a < archetype_count; ++a) {
            report["archetypes"][a]["clips"] = clip_counts(crowds[a], renderer.model(a), state[a], camera, renderer.aspect(), time_s);
            report["archetypes"][a]["impostor_blend"] = impostor_blend_name(renderer.effective_blend(o.blend, a));  // warp needs a surface map
            if (a < meters.size()) {
                report["archetypes"][a]["switch_jumps"] = meters[a].report();
                std::string line = "archetype '" + scene.names[a] + "': switches, largest jump / median motion in the clip:";
                for (Lod lod : {Lod::high, Lod::low, Lod::impostor}) {
                    const nlohmann::json& r = report["archetypes"][a]["switch_jumps"][lod == Lod::high ? "high" : lod == Lod::low ? "low" : "impostor"];
                    char figure[96];
                    std::snprintf(figure, sizeof figure, " %s %s (%d measured)", lod == Lod::high ? "high" : lod == Lod::low ? "low" : "impostor",
                                  r["largest_ratio"].is_null() ? "-" : std::to_string(r["largest_ratio"].get<double>()).substr(0, 4).c_str(),
                                  r["switches_measured"].get<int>());
                    line += figure;
                }
                log_line(line);
            }
        }
        std::ofstream out(o.report);
        if (!(out << report.dump(2) << "\n")) {
            std::fprintf(stderr, "crowdview: cannot write %s\n", o.report.c_str());
            return kExitRefused;
        }
    }
    if (!o.screenshot.empty()) {
        if (!write_png(o.screenshot, renderer.width(), renderer.height(), renderer.read_rgba())) {
            std::fprintf(stderr, "crowdview: cannot write %s\n", o.screenshot.c_str());
            return kExitRefused;
        }
        std::fprintf(stderr, "crowdview: wrote %s\n", o.screenshot.c_str());
    }
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    const Options o = parse_args(argc, argv);

    // 1. Bundles: from folders, or fetched through the one cache; verified either way.
    if (o.verify_only) {
        Bundle bundle;
        const Status status = o.source_is_url ? fetch_bundle(o.source, fetch_options(o), &bundle) : load_bundle_dir(o.source, &bundle);
        if (status) std::printf("OK %s %s (%zu files)\n", bundle.manifest.name.c_str(), bundle.manifest.version.c_str(),
                                bundle.manifest.files.size());
        else std::printf("%s %s\n", error_code_name(status.code), status.file.c_str());
        if (!status) std::fprintf(stderr, "crowdview: %s\n", status.message.c_str());
        return status ? 0 : kExitRefused;
    }
    CrowdScene scene;
    if (!o.crowd_file.empty()) {
        const std::string error = load_crowd_description(o.crowd_file, &scene.file);
        if (!error.empty()) {
            log_line(error);
            return kExitRefused;
        }
    } else {
        ArchetypeSource source;
        (o.source_is_url ? source.url : source.folder) = o.source;
        scene.file = single_archetype_crowd(source, o.count, o.seed, o.layout == Layout::paths);
    }
    const bool one_bundle = o.crowd_file.empty();
    if (one_bundle) scene.file.archetypes[0].clips = o.clips;
    scene.switch_after_s[0] = o.switch_after_s[0], scene.switch_after_s[1] = o.switch_after_s[1];
    std::vector<LoadedArchetype> loaded =
        load_archetypes(scene.file, fetch_options(o), one_bundle ? std::function<void(const std::string&)>() : log_line, &scene.refused);
    if (one_bundle && !scene.refused.empty()) {
        log_line("bundle refused: " + scene.refused[0].error);
        return kExitRefused;
    }
    if (loaded.empty()) {
        log_line("no archetype of " + o.crowd_file + " could be loaded");
        return kExitRefused;
    }
    // A clip mix naming a clip the bundle lacks is a mistake in the arguments or the description.
    for (const LoadedArchetype& a : loaded) {
        std::vector<float> weights;
        const std::string error = resolve_clip_mix(scene.file.archetypes[a.desc_index].clips, a.bundle.manifest.clips, &weights);
        if (!error.empty()) return log_line((one_bundle ? "--clips: " : "archetype '" + a.name + "': ") + error), kExitUsage;
    }

    // Detail-mapped impostors need the detail maps, which a bake stores only when asked (--detail-map).
    const bool wants_detail = o.lod == LodChoice::detail || (o.lod == LodChoice::automatic && o.impostors == ImpostorKind::detail);
    for (const LoadedArchetype& a : loaded)
        if (wants_detail && !o.benchmark && a.bundle.manifest.impostor.detail_map.empty())
            return log_line(a.bundle.manifest.name + " " + a.bundle.manifest.version + " has no detail maps (bake it with --detail-map); "
                            "--lod detail and --impostors detail need them, --lod impostor draws the UV-mapped impostor"), kExitUsage;

    // 2. GL context and the uploaded bundles, one renderer archetype each.
    GlContextDesc context_desc;
    context_desc.width = o.width;
    context_desc.height = o.height;
    context_desc.window = !(o.headless || o.benchmark);
    context_desc.device = o.gl_device;
    context_desc.require_gpu = o.require_gpu;
    std::string error;
    std::unique_ptr<GlContext> context = GlContext::create(context_desc, &error);
    if (!context) {
        std::fprintf(stderr, "crowdview: %s\n", error.c_str());
        return kExitNoGl;
    }
    const std::string gl_renderer = context->renderer_name();
    std::fprintf(stderr, "crowdview: %s (%s)\n", gl_context_line(context->info()).c_str(), context_desc.window ? "window" : "headless");
    const bool draws_impostors = o.benchmark || !(o.lod == LodChoice::high || o.lod == LodChoice::low);
    if (is_software_renderer(gl_renderer) && !o.blend_chosen && draws_impostors)
        std::fprintf(stderr, "crowdview: note: %s is a software rasteriser, where the default --impostor-blend warp costs about 6x "
                             "(3 frames: 14.5 s against 2.4 s); --impostor-blend off draws the nearest view and frame instead\n",
                     gl_renderer.c_str());
    RendererDesc renderer_desc;
    renderer_desc.width = o.width;
    renderer_desc.height = o.height;
    renderer_desc.shader_dir = o.shader_dir;
    renderer_desc.force_cpu_texture_decode = o.cpu_decode;
    std::unique_ptr<Renderer> renderer = Renderer::create(renderer_desc, &error);
    if (!renderer) {
        std::fprintf(stderr, "crowdview: %s\n", error.c_str());
        return kExitRefused;
    }
    if (!upload_archetypes(renderer.get(), loaded, &scene, one_bundle ? std::function<void(const std::string&)>() : log_line, &error)) {
        std::fprintf(stderr, "crowdview: %s\n", error.c_str());
        return kExitRefused;
    }
    if (renderer->archetype_count() == 0) {
        log_line("no archetype of " + o.crowd_file + " could be drawn");
        return kExitRefused;
    }
    // The layout indexes archetypes as the renderer does; a positions layout names description indices.
    if (scene.file.layout.kind == CrowdLayoutKind::positions) {
        for (PlacedCharacter& p : scene.file.layout.positions) {
            const auto it = std::find(scene.desc_index.begin(), scene.desc_index.end(), size_t(p.archetype));
            p.archetype = it == scene.desc_index.end() ? UINT32_MAX : uint32_t(it - scene.desc_index.begin());
        }
    }

    // 3. Run.
    if (o.benchmark) return run_benchmark_mode(*context, *renderer, loaded[0].bundle, o);
    // The switch measure reads the pose caches on the CPU: kept only for --report.
    std::vector<SwitchMeter> meters;
    if (!o.report.empty())
        for (size_t a = 0; a < renderer->archetype_count(); ++a)
            for (LoadedArchetype& l : loaded)
                if (l.desc_index == scene.desc_index[a]) meters.emplace_back(std::move(l.bundle.meshes), l.bundle.manifest.meshes);
    for (LoadedArchetype& a : loaded) a.bundle = Bundle();  // on the GPU now
    return run_view(*context, *renderer, scene, o, meters);
}
