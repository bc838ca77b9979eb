// crowdview: shows a crowdbake bundle as a crowd, in a window, headless, or as a benchmark.
//
//   crowdview (--bundle DIR | --url URL) [--cache DIR] [--count N] [--seed S] [--layout spot|paths]
//             [--headless --frames N --screenshot out.png] [--benchmark --report out.json]
//             [--width W --height H] [--lod auto|high|low|impostor|detail]
//   crowdview --verify DIR|URL
//
// Exit status: 0 success, 1 a bundle or file was refused or a run failed, 2 bad arguments,
// 3 no OpenGL context could be created here.
#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fstream>
#include <functional>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "bundle.h"
#include "crowd.h"
#include "fetch.h"
#include "gl_context.h"
#include "renderer.h"

#ifndef CROWDVIEW_SHADER_DIR
#define CROWDVIEW_SHADER_DIR "shaders"
#endif

using namespace crowdview;

namespace {

constexpr int kExitRefused = 1, kExitUsage = 2, kExitNoGl = 3;

struct Options {
    std::string bundle_dir, url, cache_dir, files_prefix = "files/", verify, shader_dir;
    uint32_t count = 100;
    uint64_t seed = 1;
    Layout layout = Layout::on_the_spot;
    bool headless = false, benchmark = false;
    int frames = -1;  // -1: until the window closes (headless: 1)
    std::string screenshot, report;
    int width = 1280, height = 720;
    std::string lod = "auto";
    std::string camera = "overview";
    std::string impostors = "uv";
    double max_seconds = 300;
    std::string modes = "high_mesh,low_mesh,uv_impostor,detail_impostor,hybrid";
    bool cpu_decode = false;
};

const char* kUsage =
    "usage: crowdview (--bundle DIR | --url URL) [options]\n"
    "       crowdview --verify DIR|URL [--cache DIR] [--files-prefix P]\n"
    "  --bundle DIR          a bundle folder (manifest.json and its files)\n"
    "  --url URL             a published bundle: URL/manifest.json and URL/<files-prefix><path>\n"
    "  --cache DIR           content-addressed download cache (default ~/.cache/crowdview)\n"
    "  --files-prefix P      where files sit below the bundle URL (default files/)\n"
    "  --count N             characters (default 100)\n"
    "  --seed S              crowd seed (default 1)\n"
    "  --layout spot|paths   walk on the spot (default, the paper's test) or along paths\n"
    "  --lod MODE            auto (default) | high | low | impostor | detail\n"
    "  --camera VIEW         overview (default: the whole crowd) | street (eye level at the crowd's edge)\n"
    "  --impostors uv|detail impostor maps used by --lod auto (default uv)\n"
    "  --width W --height H  framebuffer size (default 1280x720)\n"
    "  --headless            no window: EGL surfaceless, else a hidden GLFW window\n"
    "  --frames N            frames to draw, then exit (headless default 1)\n"
    "  --screenshot PNG      write the last frame\n"
    "  --benchmark           largest crowd at 30 and 60 fps per representation (headless)\n"
    "  --report JSON         benchmark figures\n"
    "  --max-seconds S       benchmark time budget (default 300)\n"
    "  --modes LIST          benchmark these of high_mesh,low_mesh,uv_impostor,detail_impostor,hybrid\n"
    "  --shaders DIR         shader folder (default: the source tree's src/shaders)\n"
    "  --cpu-decode          upload BC textures decoded to RGBA8 even where S3TC exists\n";

[[noreturn]] void usage_error(const std::string& message) {
    std::fprintf(stderr, "crowdview: %s (see --help)\n", message.c_str());
    std::exit(kExitUsage);
}

template <typename T>
T parse_number(const std::string& flag, const char* text, T lo, T hi) {
    char* end = nullptr;
    errno = 0;
    const double v = std::strtod(text, &end);
    if (errno || end == text || *end || !(v >= double(lo) && v <= double(hi)))
        usage_error(flag + " needs a number in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got '" + text + "'");
    if (std::is_integral<T>::value && std::floor(v) != v) usage_error(flag + " needs a whole number, got '" + text + "'");
    return T(v);
}

Options parse_args(int argc, char** argv) {
    Options o;
    auto value = [&](int& i) -> const char* {
        if (i + 1 >= argc) usage_error(std::string(argv[i]) + " needs a value");
        return argv[++i];
    };
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--help" || a == "-h") {
            std::fputs(kUsage, stdout);
            std::exit(0);
        } else if (a == "--bundle") o.bundle_dir = value(i);
        else if (a == "--url") o.url = value(i);
        else if (a == "--cache") o.cache_dir = value(i);
        else if (a == "--files-prefix") o.files_prefix = value(i);
        else if (a == "--verify") o.verify = value(i);
        else if (a == "--shaders") o.shader_dir = value(i);
        else if (a == "--count") o.count = parse_number<uint32_t>(a, value(i), 1, 10000000);
        else if (a == "--seed") o.seed = parse_number<uint64_t>(a, value(i), 0, 1ull << 53);
        else if (a == "--frames") o.frames = parse_number<int>(a, value(i), 1, 100000000);
        else if (a == "--width") o.width = parse_number<int>(a, value(i), 16, 16384);
        else if (a == "--height") o.height = parse_number<int>(a, value(i), 16, 16384);
        else if (a == "--max-seconds") o.max_seconds = parse_number<double>(a, value(i), 1, 86400);
        else if (a == "--screenshot") o.screenshot = value(i);
        else if (a == "--modes") o.modes = value(i);
        else if (a == "--report") o.report = value(i);
        else if (a == "--headless") o.headless = true;
        else if (a == "--benchmark") o.benchmark = true;
        else if (a == "--cpu-decode") o.cpu_decode = true;
        else if (a == "--layout") {
            const std::string v = value(i);
            if (v == "spot") o.layout = Layout::on_the_spot;
            else if (v == "paths") o.layout = Layout::paths;
            else usage_error("--layout is spot or paths, got '" + v + "'");
        } else if (a == "--camera") {
            o.camera = value(i);
            if (o.camera != "overview" && o.camera != "street")
                usage_error("--camera is overview or street, got '" + o.camera + "'");
        } else if (a == "--lod") {
            o.lod = value(i);
            if (o.lod != "auto" && o.lod != "high" && o.lod != "low" && o.lod != "impostor" && o.lod != "detail")
                usage_error("--lod is auto, high, low, impostor or detail, got '" + o.lod + "'");
        } else if (a == "--impostors") {
            o.impostors = value(i);
            if (o.impostors != "uv" && o.impostors != "detail") usage_error("--impostors is uv or detail, got '" + o.impostors + "'");
        } else {
            usage_error("unknown argument '" + a + "'");
        }
    }
    const int sources = !o.bundle_dir.empty() + !o.url.empty() + !o.verify.empty();
    if (sources == 0) usage_error("give --bundle DIR, --url URL or --verify DIR|URL");
    if (sources > 1) usage_error("give only one of --bundle, --url and --verify");
    if (o.benchmark && !o.screenshot.empty()) usage_error("--screenshot does not go with --benchmark");
    if (!o.report.empty() && !o.benchmark) usage_error("--report needs --benchmark");
    for (size_t start = 0; start <= o.modes.size();) {
        const size_t end = std::min(o.modes.find(',', start), o.modes.size());
        const std::string mode = o.modes.substr(start, end - start);
        if (std::string(",high_mesh,low_mesh,uv_impostor,detail_impostor,hybrid,").find("," + mode + ",") == std::string::npos)
            usage_error("--modes takes high_mesh, low_mesh, uv_impostor, detail_impostor, hybrid; got '" + mode + "'");
        start = end + 1;
    }
    if (o.shader_dir.empty()) {
        const char* env = std::getenv("CROWDVIEW_SHADERS");
        o.shader_dir = env && *env ? env : CROWDVIEW_SHADER_DIR;
    }
    return o;
}

bool is_url(const std::string& s) { return s.find("://") != std::string::npos; }

Status load(const std::string& where, const Options& o, Bundle* bundle) {
    if (!is_url(where)) return load_bundle_dir(where, bundle);
    FetchOptions fetch;
    fetch.cache_dir = o.cache_dir;
    fetch.files_prefix = o.files_prefix;
    fetch.log = [](const std::string& line) { std::fprintf(stderr, "%s\n", line.c_str()); };
    return fetch_bundle(where, fetch, bundle);
}

LodMode lod_mode(const std::string& lod) {
    if (lod == "high") return LodMode::high;
    if (lod == "low") return LodMode::low;
    if (lod == "impostor" || lod == "detail") return LodMode::impostor;
    return LodMode::automatic;
}

// Every character is lit dynamically, as in the paper's test: a sun up and to the side, so the
// normal maps show.
const glm::vec3 kLightDir = glm::normalize(glm::vec3(0.4f, 0.8f, 0.45f));
// Headless and benchmark runs step time at a fixed 30 Hz, so output is reproducible.
constexpr float kFixedStep = 1.0f / 30.0f;

LodRule lod_rule_for(const Renderer& r, const Camera& camera) {
    LodRule rule;
    rule.impostor_distance = impostor_switch_distance(camera.fov_y, float(r.height()), r.model().radius, r.model().tile_size);
    rule.has_low = r.model().has_low;
    return rule;
}

float character_height(const CharacterModel& m) { return m.center.y + m.radius; }

// ---------------------------------------------------------------------------------------
// Benchmark: the paper's figure 3 on this machine.

struct Sample {
    uint32_t n = 0;
    double fps = 0;         // from the fastest timed frame: what the machine does undisturbed
    double fps_median = 0;  // from the median frame: includes whatever else the machine ran
    double cpu_ms = 0;      // median CPU time of this process per frame, all threads (llvmpipe
                            // renders on the CPU): the cost, whatever else the machine ran
    uint32_t by_lod[3] = {0, 0, 0};
};

class Benchmark {
public:
    Benchmark(Renderer& r, const Bundle& b, const Options& o) : renderer_(r), bundle_(b), options_(o) {}

    // The benchmark's fixed camera: 6 m up, looking 17 degrees down over the crowd.
    static Camera camera() {
        Camera c;
        c.position = glm::vec3(0, 6, 0);
        c.pitch = -0.3f;
        c.far_m = 5000;
        return c;
    }

    // Frame rate of a crowd of n in view, drawn by `mode`, after a warm-up.
    Sample measure(uint32_t n, LodMode mode, ImpostorKind kind) {
        const CharacterModel& model = renderer_.model();
        CrowdDesc desc;
        desc.count = n;
        desc.seed = options_.seed;
        const Camera cam = camera();
        const LodRule rule = lod_rule_for(renderer_, cam);
        // From half the switch distance on: no character is over twice its 1:1 size on screen,
        // so the impostor-only runs are not a test of magnified fill.
        const float near_m = 0.5f * rule.impostor_distance;
        const Crowd crowd =
            make_crowd_in_view(desc, cam, renderer_.aspect(), model.center.y, model.radius, near_m, max_variations(),
                               bundle_.manifest.outfit_count, float(model.frame_count) / model.frames_per_second);
        std::vector<Lod> state;
        FrameInstances frame;
        std::vector<double> seconds, cpu_seconds;
        auto cpu_now = [] {
            timespec t;
            clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
            return double(t.tv_sec) + 1e-9 * double(t.tv_nsec);
        };
        // Two warm-up frames (shader variants, buffer growth), then fifteen timed ones. The
        // search uses the fastest: on a machine shared with other work the median measures
        // the other work too (both are reported).
        const auto first = std::chrono::steady_clock::now();
        for (int i = 0; i < 17; ++i) {
            const auto start = std::chrono::steady_clock::now();
            const double cpu_start = cpu_now();
            build_frame(crowd, model, cam, renderer_.aspect(), mode, rule, float(i) * kFixedStep, &state, &frame);
            renderer_.draw(frame, cam, kind, kLightDir);
            renderer_.finish();
            const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
            if (i >= 2) seconds.push_back(s), cpu_seconds.push_back(cpu_now() - cpu_start);
            // Slow crowds need fewer frames to show it: three timed frames after half a second
            // of rendering bound each measurement.
            if (seconds.size() >= 3 && std::chrono::steady_clock::now() - first > std::chrono::milliseconds(500)) break;
        }
        std::sort(seconds.begin(), seconds.end());
        std::sort(cpu_seconds.begin(), cpu_seconds.end());
        Sample sample;
        sample.n = uint32_t(crowd.characters.size());
        sample.fps = 1.0 / std::max(seconds.front(), 1e-6);
        sample.fps_median = 1.0 / std::max(seconds[seconds.size() / 2], 1e-6);
        sample.cpu_ms = 1000.0 * cpu_seconds[cpu_seconds.size() / 2];
        for (int l = 0; l < 3; ++l) sample.by_lod[l] = uint32_t(frame.by_lod[l].size());
        return sample;
    }

    uint32_t max_variations() const {
        uint32_t v = 1;
        for (const MaterialInfo& m : bundle_.manifest.materials) v = std::max(v, m.variations);
        return v;
    }

private:
    Renderer& renderer_;
    const Bundle& bundle_;
    const Options& options_;
};

// Largest n whose fps holds `target`, from the samples so far plus new ones: doubling, then
// bisection to 5 %, inside the deadline. Returns the largest passing sample (0 if none).
uint32_t search(const std::function<Sample(uint32_t)>& measure, std::map<uint32_t, Sample>* samples, double target,
                const std::chrono::steady_clock::time_point& deadline, bool* converged) {
    constexpr uint32_t kMaxCount = 1u << 20;  // a million characters bounds the doubling
    auto fps = [&](uint32_t n) {
        auto it = samples->find(n);
        if (it == samples->end()) it = samples->emplace(n, measure(n)).first;
        return it->second.fps;
    };
    auto in_time = [&] { return std::chrono::steady_clock::now() < deadline; };
    uint32_t lo = 0, hi = 0;  // lo passes (0: nothing yet), hi fails (0: none found yet)
    for (const auto& [n, s] : *samples) {
        if (s.fps >= target) lo = std::max(lo, n);
        else if (hi == 0 || n < hi) hi = n;
    }
    if (hi != 0 && lo > hi) lo = 0;  // noisy samples: trust the failing one
    if (hi == 0) {
        // The first size is measured even past the deadline, so every mode reports something.
        for (uint32_t n = std::max(lo * 2, 8u); n <= kMaxCount && (n == std::max(lo * 2, 8u) || in_time()); n *= 2) {
            if (fps(n) >= target) lo = n;
            else {
                hi = n;
                break;
            }
        }
    }
    if (hi == 0) {
        *converged = false;
        return lo;
    }
    while (hi - lo > std::max(1u, lo / 20) && in_time()) {
        const uint32_t mid = lo + (hi - lo) / 2;
        if (fps(mid) >= target) lo = mid;
        else hi = mid;
    }
    *converged = hi - lo <= std::max(1u, lo / 20);
    return lo;
}

int run_benchmark(GlContext& context, Renderer& renderer, const Bundle& bundle, const Options& o) {
    struct Mode {
        const char* name;
        LodMode lod;
        ImpostorKind kind;
    };
    const Mode modes[] = {{"high_mesh", LodMode::high, ImpostorKind::uv},
                          {"low_mesh", LodMode::low, ImpostorKind::uv},
                          {"uv_impostor", LodMode::impostor, ImpostorKind::uv},
                          {"detail_impostor", LodMode::impostor, ImpostorKind::detail},
                          {"hybrid", LodMode::automatic, ImpostorKind::uv}};
    Benchmark bench(renderer, bundle, o);
    const auto start = std::chrono::steady_clock::now();
    nlohmann::json report;
    report["device"] = context.describe();
    report["width"] = o.width;
    report["height"] = o.height;
    report["bundle"] = bundle.manifest.name + "/" + bundle.manifest.version;
    report["seed"] = o.seed;
    // Other work on the machine shows up in the timings; the load average says how much.
    auto load_average = [] {
        std::ifstream in("/proc/loadavg");
        double one_minute = -1;
        in >> one_minute;
        return one_minute;
    };
    report["load_average_1min_start"] = load_average();
    report["cpu_threads"] = std::thread::hardware_concurrency();
    report["max_seconds"] = o.max_seconds;
    report["compressed_textures"] = renderer.compressed_textures();
    report["triangles_per_character"] = {{"high", renderer.triangles_per_character(Lod::high)},
                                         {"low", renderer.triangles_per_character(Lod::low)},
                                         {"impostor", 2}};
    report["impostor_switch_distance_m"] = impostor_switch_distance(Camera().fov_y, float(o.height), renderer.model().radius,
                                                                    renderer.model().tile_size);
    report["method"] = "per N: characters walking on the spot in staggered rows 1.6 m apart filling the view "
                       "nearest first from half the impostor switch distance (camera 6 m up, 17 degrees down, fov 45), "
                       "all on screen; hybrid = --lod auto (high, low, UV impostor by distance); 2 warm-up frames, "
                       "then 15 frames, each timed from build_frame (cull, LOD, views) to glFinish; fps from the "
                       "fastest frame (fps_median from the median one); N doubles from 8, then bisects to 5 %";
    nlohmann::json results = nlohmann::json::object();
    std::vector<const Mode*> chosen;
    for (const Mode& mode : modes)
        if (("," + o.modes + ",").find(std::string(",") + mode.name + ",") != std::string::npos) chosen.push_back(&mode);
    const double per_mode = o.max_seconds / double(chosen.size());
    for (size_t m = 0; m < chosen.size(); ++m) {
        const Mode& mode = *chosen[m];
        if (mode.lod == LodMode::low && !renderer.model().has_low) {
            std::fprintf(stderr, "benchmark: %s skipped: the bundle has no lod 1 mesh\n", mode.name);
            results[mode.name] = {{"skipped", "no lod 1 mesh"}};
            continue;
        }
        const auto deadline = start + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                          std::chrono::duration<double>(per_mode * (m + 1)));
        std::map<uint32_t, Sample> samples;
        auto measure = [&](uint32_t n) {
            Sample s = bench.measure(n, mode.lod, mode.kind);
            std::fprintf(stderr,
                         "benchmark: %-15s N=%-7u %7.1f fps (median frame %6.1f, CPU %7.1f ms)  high %u, low %u, impostor %u\n",
                         mode.name, n, s.fps, s.fps_median, s.cpu_ms, s.by_lod[0], s.by_lod[1], s.by_lod[2]);
            return s;
        };
        bool converged30 = false, converged60 = false;
        const uint32_t n30 = search(measure, &samples, 30.0, deadline, &converged30);
        const uint32_t n60 = search(measure, &samples, 60.0, deadline, &converged60);
        nlohmann::json entry;
        entry["n_at_30fps"] = n30;
        entry["n_at_60fps"] = n60;
        entry["converged_30"] = converged30;
        entry["converged_60"] = converged60;
        if (samples.count(n30)) {
            const Sample& s = samples[n30];
            entry["lod_split_at_30fps"] = {{"high", s.by_lod[0]}, {"low", s.by_lod[1]}, {"impostor", s.by_lod[2]}};
        }
        nlohmann::json list = nlohmann::json::array();
        for (const auto& [n, s] : samples)
            list.push_back({{"n", n},
                            {"fps", std::round(s.fps * 10) / 10},
                            {"fps_median", std::round(s.fps_median * 10) / 10},
                            {"cpu_ms_per_frame", std::round(s.cpu_ms * 100) / 100}});
        entry["samples"] = list;
        results[mode.name] = entry;
        std::fprintf(stderr, "benchmark: %-15s %u at 30 fps, %u at 60 fps%s\n", mode.name, n30, n60,
                     converged30 && converged60 ? "" : " (time budget hit: lower bounds)");
    }
    report["results"] = results;
    const double high = results.contains("high_mesh") ? results["high_mesh"].value("n_at_30fps", 0u) : 0.0;
    if (high > 0) {
        nlohmann::json ratios;
        for (const auto& [name, entry] : results.items())
            if (entry.contains("n_at_30fps")) ratios[name] = std::round(entry["n_at_30fps"].get<double>() / high * 100) / 100;
        report["ratio_to_high_mesh_at_30fps"] = ratios;
    }
    report["load_average_1min_end"] = load_average();
    report["seconds"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    const std::string text = report.dump(2) + "\n";
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

// ---------------------------------------------------------------------------------------
// Window controls: a fly camera.

struct FlyControls {
    double last_x = 0, last_y = 0;
    bool dragging = false;
    float speed = 8.0f;  // metres per second

    void update(GLFWwindow* w, Camera* camera, float dt) {
        double x, y;
        glfwGetCursorPos(w, &x, &y);
        const bool down = glfwGetMouseButton(w, GLFW_MOUSE_BUTTON_LEFT) == GLFW_PRESS;
        if (down && dragging) {
            camera->yaw -= float(x - last_x) * 0.004f;
            camera->pitch = glm::clamp(camera->pitch - float(y - last_y) * 0.004f, -1.5f, 1.5f);
        }
        dragging = down;
        last_x = x, last_y = y;
        const glm::vec3 forward = camera->forward();
        const glm::vec3 right = glm::normalize(glm::cross(forward, glm::vec3(0, 1, 0)));
        const float step = speed * dt * (glfwGetKey(w, GLFW_KEY_LEFT_SHIFT) == GLFW_PRESS ? 4.0f : 1.0f);
        auto key = [&](int k) { return glfwGetKey(w, k) == GLFW_PRESS ? 1.0f : 0.0f; };
        camera->position += forward * step * (key(GLFW_KEY_W) - key(GLFW_KEY_S));
        camera->position += right * step * (key(GLFW_KEY_D) - key(GLFW_KEY_A));
        camera->position.y += step * (key(GLFW_KEY_E) - key(GLFW_KEY_Q));
    }
};

int run_view(GlContext& context, Renderer& renderer, const Bundle& bundle, const Options& o) {
    const CharacterModel& model = renderer.model();
    CrowdDesc desc;
    desc.count = o.count;
    desc.seed = o.seed;
    desc.layout = o.layout;
    uint32_t variations = 1;
    for (const MaterialInfo& m : bundle.manifest.materials) variations = std::max(variations, m.variations);
    const Crowd crowd = make_crowd(desc, variations, bundle.manifest.outfit_count, float(model.frame_count) / model.frames_per_second);
    Camera camera = o.camera == "street" ? street_camera(crowd, character_height(model))
                                         : camera_for_crowd(crowd, character_height(model), renderer.aspect(), 0.35f);
    camera.near_m = 0.1f;
    camera.far_m = std::max(camera.far_m * 4.0f, 200.0f);
    LodMode mode = lod_mode(o.lod);
    ImpostorKind kind = (o.lod == "detail" || o.impostors == "detail") ? ImpostorKind::detail : ImpostorKind::uv;
    const LodRule rule = lod_rule_for(renderer, camera);
    std::vector<Lod> state;
    FrameInstances frame;
    FlyControls controls;
    const bool windowed = context.visible();
    const int frames = o.frames > 0 ? o.frames : (windowed ? -1 : 1);
    auto last = std::chrono::steady_clock::now();
    double fps_smoothed = 0;
    float time_s = 0;
    DrawStats stats;
    for (int i = 0; frames < 0 || i < frames; ++i) {
        if (context.should_close()) break;
        const auto now = std::chrono::steady_clock::now();
        const float dt = windowed ? std::chrono::duration<float>(now - last).count() : kFixedStep;
        last = now;
        time_s = windowed ? time_s + dt : float(i) * kFixedStep;
        if (windowed) {
            GLFWwindow* w = context.window();
            controls.update(w, &camera, dt);
            const char* names[] = {"auto", "high", "low", "impostor", "detail"};
            for (int k = 0; k < 5; ++k)
                if (glfwGetKey(w, GLFW_KEY_1 + k) == GLFW_PRESS) {
                    mode = lod_mode(names[k]);
                    kind = k == 4 ? ImpostorKind::detail : ImpostorKind::uv;
                }
            if (glfwGetKey(w, GLFW_KEY_ESCAPE) == GLFW_PRESS) break;
        }
        // The frame: cull and choose LODs on the CPU, then a few instanced draws.
        build_frame(crowd, model, camera, renderer.aspect(), mode, rule, time_s, &state, &frame);
        stats = renderer.draw(frame, camera, kind, kLightDir);
        if (windowed) {
            int w = 0, h = 0;
            glfwGetFramebufferSize(context.window(), &w, &h);
            renderer.present(w, h);
            fps_smoothed = fps_smoothed == 0 ? 1.0 / std::max(dt, 1e-4f) : 0.9 * fps_smoothed + 0.1 / std::max(dt, 1e-4f);
            char title[256];
            std::snprintf(title, sizeof title, "crowdview - %.1f fps - high %zu | low %zu | impostor %zu | culled %u",
                          fps_smoothed, frame.by_lod[0].size(), frame.by_lod[1].size(), frame.by_lod[2].size(), frame.culled);
            context.set_title(title);
            context.swap_and_poll();
        }
    }
    std::fprintf(stderr, "crowdview: %s; %zu high, %zu low, %zu impostor, %u culled; %u draws, %llu triangles\n",
                 context.describe().c_str(), frame.by_lod[0].size(), frame.by_lod[1].size(), frame.by_lod[2].size(), frame.culled,
                 stats.draw_calls, (unsigned long long)stats.triangles);
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

    // 1. Bundle: from a folder, or fetched through the cache; verified either way.
    Bundle bundle;
    const std::string source = !o.verify.empty() ? o.verify : !o.url.empty() ? o.url : o.bundle_dir;
    const Status status = load(source, o, &bundle);
    if (!o.verify.empty()) {
        if (status) std::printf("OK %s %s (%zu files)\n", bundle.manifest.name.c_str(), bundle.manifest.version.c_str(),
                                bundle.manifest.files.size());
        else std::printf("%s %s\n", error_code_name(status.code), status.file.c_str());
        if (!status) std::fprintf(stderr, "crowdview: %s\n", status.message.c_str());
        return status ? 0 : kExitRefused;
    }
    if (!status) {
        std::fprintf(stderr, "crowdview: bundle refused: %s\n", status.message.c_str());
        return kExitRefused;
    }

    // 2. GL context and the uploaded bundle.
    GlContextDesc context_desc;
    context_desc.width = o.width;
    context_desc.height = o.height;
    context_desc.window = !(o.headless || o.benchmark);
    std::string error;
    std::unique_ptr<GlContext> context = GlContext::create(context_desc, &error);
    if (!context) {
        std::fprintf(stderr, "crowdview: %s\n", error.c_str());
        return kExitNoGl;
    }
    RendererDesc renderer_desc;
    renderer_desc.width = o.width;
    renderer_desc.height = o.height;
    renderer_desc.shader_dir = o.shader_dir;
    renderer_desc.force_cpu_texture_decode = o.cpu_decode;
    std::unique_ptr<Renderer> renderer = Renderer::create(bundle, renderer_desc, &error);
    if (!renderer) {
        std::fprintf(stderr, "crowdview: %s\n", error.c_str());
        return kExitRefused;
    }

    // 3. Run.
    return o.benchmark ? run_benchmark(*context, *renderer, bundle, o) : run_view(*context, *renderer, bundle, o);
}
