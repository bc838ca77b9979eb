// The figure 3 benchmark (benchmark.h): per representation, a doubling-then-bisection search
// for the largest crowd that holds a frame rate, on a fixed camera over a crowd in view.
#include "benchmark.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <map>
#include <thread>

namespace crowdview {

const char* benchmark_mode_name(BenchmarkMode mode) {
    switch (mode) {
    case BenchmarkMode::high_mesh: return "high_mesh";
    case BenchmarkMode::low_mesh: return "low_mesh";
    case BenchmarkMode::uv_impostor: return "uv_impostor";
    case BenchmarkMode::detail_impostor: return "detail_impostor";
    case BenchmarkMode::hybrid: return "hybrid";
    }
    return "unknown";
}

bool parse_benchmark_mode(const std::string& name, BenchmarkMode* mode) {
    for (BenchmarkMode m : kAllBenchmarkModes)
        if (name == benchmark_mode_name(m)) {
            *mode = m;
            return true;
        }
    return false;
}

const char* impostor_blend_name(ImpostorBlend blend) {
    switch (blend) {
    case ImpostorBlend::off: return "off";
    case ImpostorBlend::views: return "views";
    case ImpostorBlend::frames: return "frames";
    case ImpostorBlend::full: return "full";
    case ImpostorBlend::warp: return "warp";
    }
    return "unknown";
}

namespace {

struct Sample {
    uint32_t n = 0;
    double fps = 0;         // from the fastest timed frame: what the machine does undisturbed
    double fps_median = 0;  // from the median frame: includes whatever else the machine ran
    double cpu_ms = 0;      // median CPU time of this process per frame, all threads (llvmpipe
                            // renders on the CPU): the cost, whatever else the machine ran
    uint32_t by_lod[3] = {0, 0, 0};
    bool cut_short = false;  // the deadline ended it before its usual frame count (fewer timed frames)
};

using Clock = std::chrono::steady_clock;

// How a mode draws: build_frame's LOD choice and the impostor maps.
struct ModeDraw {
    LodMode lod;
    ImpostorKind kind;
    ImpostorBlend blend = ImpostorBlend::full;
};

ModeDraw mode_draw(BenchmarkMode mode) {
    switch (mode) {
    case BenchmarkMode::high_mesh: return {LodMode::high, ImpostorKind::uv};
    case BenchmarkMode::low_mesh: return {LodMode::low, ImpostorKind::uv};
    case BenchmarkMode::uv_impostor: return {LodMode::impostor, ImpostorKind::uv};
    case BenchmarkMode::detail_impostor: return {LodMode::impostor, ImpostorKind::detail};
    case BenchmarkMode::hybrid: break;
    }
    return {LodMode::automatic, ImpostorKind::uv};
}

// The benchmark's fixed camera: 6 m up, looking 17 degrees down over the crowd.
Camera benchmark_camera() {
    Camera c;
    c.position = glm::vec3(0, 6, 0);
    c.pitch = -0.3f;
    c.far_m = 5000;
    return c;
}

uint32_t max_variations(const Bundle& bundle) {
    uint32_t v = 1;
    for (const MaterialInfo& m : bundle.manifest.materials) v = std::max(v, m.variations);
    return v;
}

double process_cpu_seconds() {
    timespec t;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
    return double(t.tv_sec) + 1e-9 * double(t.tv_nsec);
}

// Frame rate of a crowd of n in view, drawn as `draw`, after a warm-up. Past `deadline` it stops
// after its first timed frame (one warm-up, one timed: the least that says anything), so a
// crowd that draws slowly on a software rasteriser cannot run the benchmark past --max-seconds.
Sample measure(Renderer& renderer, const Bundle& bundle, uint64_t seed, uint32_t n, const ModeDraw& draw, Clock::time_point deadline) {
    const CharacterModel& model = renderer.model();
    CrowdDesc desc;
    desc.count = n;
    desc.seed = seed;
    desc.spacing = crowd_spacing(model.radius);
    const Camera cam = benchmark_camera();
    const LodRule rule = lod_rule_for(model, cam, float(renderer.height()));
    // From half the switch distance on: no character is over twice its 1:1 size on screen,
    // so the impostor-only runs are not a test of magnified fill.
    const float near_m = 0.5f * rule.impostor_distance;
    const Crowd crowd = make_crowd_in_view(desc, cam, renderer.aspect(), model.center.y, model.radius, near_m,
                                           max_variations(bundle), bundle.manifest.outfit_count,
                                           float(model.frame_count) / model.frames_per_second);
    const glm::vec3 light = scene_light_dir();
    FrameState state;
    FrameInstances frame;
    std::vector<double> seconds, cpu_seconds;
    bool cut_short = false;
    // Two warm-up frames (shader variants, buffer growth), then fifteen timed ones. The
    // search uses the fastest: on a machine shared with other work the median measures
    // the other work too (both are reported).
    const auto first = std::chrono::steady_clock::now();
    for (int i = 0; i < 17; ++i) {
        const auto start = std::chrono::steady_clock::now();
        const double cpu_start = process_cpu_seconds();
        build_frame(crowd, model, cam, renderer.aspect(), draw.lod, rule, float(i) * kFixedTimeStep, &state, &frame, draw.blend);
        renderer.draw(frame, cam, draw.kind, light);
        renderer.finish();
        const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
        if (i >= 2) seconds.push_back(s), cpu_seconds.push_back(process_cpu_seconds() - cpu_start);
        if (Clock::now() > deadline && (i >= 2 || i == 1)) {
            if (i == 1) seconds.push_back(s), cpu_seconds.push_back(process_cpu_seconds() - cpu_start);  // timed, not warm-up
            cut_short = seconds.size() < 3;
            break;
        }
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
    sample.cut_short = cut_short;
    for (int l = 0; l < 3; ++l) sample.by_lod[l] = frame.shown[l];
    return sample;
}

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

// Other work on the machine shows up in the timings; the load average says how much.
double load_average_1min() {
    std::ifstream in("/proc/loadavg");
    double one_minute = -1;
    in >> one_minute;
    return one_minute;
}

// UV impostors with blending off and on (desc.blend, or full when that is off) at one crowd
// size: uv_impostor's 30 fps answer, else 256. Three alternating rounds, the best of each, so
// both see the same background load.
template <typename Log>
nlohmann::json blend_cost(Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc, const nlohmann::json& results,
                          Clock::time_point deadline, const Log& log) {
    const ImpostorBlend on = renderer.effective_blend(desc.blend == ImpostorBlend::off ? ImpostorBlend::full : desc.blend);
    // With reprojection, the plain blend is measured too: what the surface map costs on its own.
    const bool warped = on == ImpostorBlend::warp;
    // The crowd size: uv_impostor's 30 fps answer; without one (uv_impostor not run), the largest
    // 30 fps answer of the modes that ran, at most 256 (a software rasteriser blends 256 impostors in
    // seconds a frame: that phase once ran 485 s of a 10 s budget), at least 8.
    uint32_t n = 0;
    if (results.contains("uv_impostor") && results["uv_impostor"].value("n_at_30fps", 0u) > 0)
        n = results["uv_impostor"]["n_at_30fps"].get<uint32_t>();
    else {
        for (const auto& [name, entry] : results.items()) n = std::max(n, entry.value("n_at_30fps", 0u));
        n = std::clamp(n, 8u, 256u);
    }
    Sample best_off, best_on, best_full;
    int rounds = 0;
    for (int round = 0; round < 3 && (round == 0 || Clock::now() < deadline); ++round) {
        const Sample off = measure(renderer, bundle, desc.seed, n, {LodMode::impostor, ImpostorKind::uv, ImpostorBlend::off}, deadline);
        const Sample blended = measure(renderer, bundle, desc.seed, n, {LodMode::impostor, ImpostorKind::uv, on}, deadline);
        if (off.fps > best_off.fps) best_off = off;
        if (blended.fps > best_on.fps) best_on = blended;
        if (warped) {
            const Sample full = measure(renderer, bundle, desc.seed, n, {LodMode::impostor, ImpostorKind::uv, ImpostorBlend::full}, deadline);
            if (full.fps > best_full.fps) best_full = full;
        }
        ++rounds;
    }
    const bool cut_short = rounds < 3 || best_off.cut_short || best_on.cut_short;
    log("benchmark: uv_impostor N=%u blending off %.1f fps (CPU %.1f ms/frame), %s %.1f fps (CPU %.1f ms/frame)%s", best_off.n,
        best_off.fps, best_off.cpu_ms, impostor_blend_name(on), best_on.fps, best_on.cpu_ms,
        cut_short ? " (cut short by --max-seconds)" : "");
    nlohmann::json cost = {{"mode", "uv_impostor"},
                           {"rounds", rounds},
                           {"cut_short", cut_short},
                           {"n", best_off.n},
                           {"blend", impostor_blend_name(on)},
                           {"fps_off", std::round(best_off.fps * 10) / 10},
                           {"fps_blended", std::round(best_on.fps * 10) / 10},
                           {"cpu_ms_per_frame_off", std::round(best_off.cpu_ms * 100) / 100},
                           {"cpu_ms_per_frame_blended", std::round(best_on.cpu_ms * 100) / 100},
                           {"fps_ratio_blended_to_off", std::round(best_on.fps / std::max(best_off.fps, 1e-9) * 100) / 100}};
    if (warped) {
        log("benchmark: uv_impostor N=%u full blending without reprojection %.1f fps (CPU %.1f ms/frame)", best_full.n, best_full.fps,
            best_full.cpu_ms);
        cost["fps_full_unwarped"] = std::round(best_full.fps * 10) / 10;
        cost["fps_ratio_warped_to_full"] = std::round(best_on.fps / std::max(best_full.fps, 1e-9) * 100) / 100;
    }
    return cost;
}

// What the report says before any figure: the machine, the bundle, the budget and the method.
nlohmann::json report_header(const Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc) {
    nlohmann::json report;
    report["device"] = desc.device;
    report["gl"] = desc.gl;
    report["width"] = renderer.width();
    report["height"] = renderer.height();
    report["bundle"] = bundle.manifest.name + "/" + bundle.manifest.version;
    report["seed"] = desc.seed;
    report["load_average_1min_start"] = load_average_1min();
    report["cpu_threads"] = std::thread::hardware_concurrency();
    report["max_seconds"] = desc.max_seconds;
    report["compressed_textures"] = renderer.compressed_textures();
    report["triangles_per_character"] = {{"high", renderer.triangles_per_character(Lod::high)},
                                         {"low", renderer.triangles_per_character(Lod::low)},
                                         {"impostor", 2}};
    report["impostor_switch_distance_m"] = impostor_switch_distance(Camera().fov_y, float(renderer.height()),
                                                                    renderer.model().radius, renderer.model().tile_size);
    report["method"] = "per N: characters walking on the spot in staggered rows 1.6 m apart filling the view "
                       "nearest first from half the impostor switch distance (camera 6 m up, 17 degrees down, fov 45), "
                       "all on screen; hybrid = --lod auto (high, low, UV impostor by distance); 2 warm-up frames, "
                       "then 15 frames, each timed from build_frame (cull, LOD, views) to glFinish; fps from the "
                       "fastest frame (fps_median from the median one); N doubles from 8, then bisects to 5 %";
    return report;
}

// One mode's largest crowds at 30 and 60 fps, searched until `deadline`, every sample logged:
// the report's results entry, "cut_short" where the search did not converge in time.
template <typename Log>
nlohmann::json measure_mode(Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc, const char* name, const ModeDraw& draw,
                            Clock::time_point deadline, const Log& log) {
    std::map<uint32_t, Sample> samples;
    bool sample_cut = false;
    auto measure_n = [&](uint32_t n) {
        const Sample s = measure(renderer, bundle, desc.seed, n, draw, deadline);
        sample_cut |= s.cut_short;
        log("benchmark: %-15s N=%-7u %7.1f fps (median frame %6.1f fps, CPU %7.1f ms/frame)  high %u, low %u, impostor %u%s", name, n,
            s.fps, s.fps_median, s.cpu_ms, s.by_lod[0], s.by_lod[1], s.by_lod[2], s.cut_short ? " (cut short)" : "");
        return s;
    };
    bool converged30 = false, converged60 = false;
    const uint32_t n30 = search(measure_n, &samples, 30.0, deadline, &converged30);
    const uint32_t n60 = search(measure_n, &samples, 60.0, deadline, &converged60);
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
    entry["cut_short"] = !(converged30 && converged60) || sample_cut;
    return entry;
}

// Each mode's crowd at 30 fps against high_mesh's; null without a high_mesh answer.
nlohmann::json ratios_to_high_mesh(const nlohmann::json& results) {
    const double high = results.contains("high_mesh") ? results["high_mesh"].value("n_at_30fps", 0u) : 0.0;
    if (high <= 0) return nullptr;
    nlohmann::json ratios;
    for (const auto& [name, entry] : results.items())
        if (entry.contains("n_at_30fps")) ratios[name] = std::round(entry["n_at_30fps"].get<double>() / high * 100) / 100;
    return ratios;
}

double seconds_since(Clock::time_point start) { return std::chrono::duration<double>(Clock::now() - start).count(); }

}  // namespace

nlohmann::json run_benchmark(Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc) {
    auto log = [&](const char* format, auto... args) {
        if (!desc.log) return;
        char line[512];
        std::snprintf(line, sizeof line, format, args...);
        desc.log(line);
    };
    const auto start = Clock::now();
    nlohmann::json report = report_header(renderer, bundle, desc);
    nlohmann::json results = nlohmann::json::object();
    nlohmann::json phases = nlohmann::json::array();  // every phase: name, seconds, cut_short
    // --max-seconds bounds the whole run: the modes and the blend-cost phase each get an even share,
    // and none runs past the run's end (measure() stops at its deadline after one timed frame).
    const auto end = start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(desc.max_seconds));
    const double share = desc.max_seconds / double(desc.modes.size() + 1);
    for (size_t m = 0; m < desc.modes.size(); ++m) {
        const char* name = benchmark_mode_name(desc.modes[m]);
        ModeDraw draw = mode_draw(desc.modes[m]);
        draw.blend = desc.blend;
        if (draw.lod == LodMode::low && !renderer.model().has_low) {
            log("benchmark: %s skipped: the bundle has no lod 1 mesh", name);
            results[name] = {{"skipped", "no lod 1 mesh"}};
            continue;
        }
        const auto phase_start = Clock::now();
        const auto deadline = std::min(end, start + std::chrono::duration_cast<Clock::duration>(
                                                        std::chrono::duration<double>(share * double(m + 1))));
        const nlohmann::json entry = results[name] = measure_mode(renderer, bundle, desc, name, draw, deadline, log);
        const double phase_s = seconds_since(phase_start);
        const bool cut_short = entry["cut_short"];
        phases.push_back({{"name", name}, {"seconds", std::round(phase_s * 100) / 100}, {"cut_short", cut_short}});
        log("benchmark: %-15s %u at 30 fps, %u at 60 fps, %.1f s%s", name, entry["n_at_30fps"].get<uint32_t>(),
            entry["n_at_60fps"].get<uint32_t>(), phase_s, cut_short ? " (cut short by --max-seconds: lower bounds)" : "");
        // The report so far, so a run stopped from outside still leaves one.
        report["results"] = results;
        report["phases"] = phases;
        report["seconds"] = seconds_since(start);
        if (desc.checkpoint) desc.checkpoint(report);
    }
    report["impostor_blend"] = impostor_blend_name(renderer.effective_blend(desc.blend));
    const auto blend_start = Clock::now();
    report["impostor_blend_cost"] = blend_cost(renderer, bundle, desc, results, end, log);
    const double blend_s = seconds_since(blend_start);
    phases.push_back({{"name", "impostor_blend_cost"}, {"seconds", std::round(blend_s * 100) / 100},
                      {"cut_short", report["impostor_blend_cost"]["cut_short"]}});
    log("benchmark: impostor_blend_cost %.1f s", blend_s);
    report["results"] = results;
    report["phases"] = phases;
    if (nlohmann::json ratios = ratios_to_high_mesh(results); !ratios.is_null()) report["ratio_to_high_mesh_at_30fps"] = ratios;
    report["load_average_1min_end"] = load_average_1min();
    report["seconds"] = seconds_since(start);
    return report;
}

}  // namespace crowdview
