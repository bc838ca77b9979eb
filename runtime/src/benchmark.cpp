// The figure 3 benchmark (benchmark.h): per representation, a doubling-then-bisection search
// for the largest crowd that holds a frame rate, on a fixed camera over a crowd in view.
#include "benchmark.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <thread>

#include "benchmark_search.h"

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

using Clock = std::chrono::steady_clock;

// After the last probe: the report is written, the GL context and the bundle freed. Kept back
// from --max-seconds so that the process ends inside it.
constexpr double kExitReserveSeconds = 0.3;

Clock::duration seconds(double s) { return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s)); }
double seconds_since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }
double rounded(double value, double scale) { return std::round(value * scale) / scale; }

// One progress line through desc.log (none where it is empty).
__attribute__((format(printf, 2, 3))) void log_line(const BenchmarkDesc& desc, const char* format, ...) {
    if (!desc.log) return;
    char line[512];
    va_list args;
    va_start(args, format);
    std::vsnprintf(line, sizeof line, format, args);
    va_end(args);
    desc.log(line);
}

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

// n characters in view from half the switch distance on: no character is over twice its 1:1
// size on screen, so the impostor-only runs are not a test of magnified fill.
Crowd benchmark_crowd(const Renderer& renderer, const Bundle& bundle, uint64_t seed, uint32_t n, const Camera& cam, const LodRule& rule) {
    const CharacterModel& model = renderer.model();
    CrowdDesc desc;
    desc.count = n;
    desc.seed = seed;
    desc.spacing = crowd_spacing(model.radius);
    return make_crowd_in_view(desc, cam, renderer.aspect(), model.center.y, model.radius, 0.5f * rule.impostor_distance,
                              max_variations(bundle), bundle.manifest.outfit_count, float(model.frame_count) / model.frames_per_second);
}

// Frame rate of a crowd of n in view, drawn as `draw`: two warm-up frames (shader variants,
// buffer growth), then up to fifteen timed ones; three after half a second of rendering are
// enough for a slow crowd. The fastest frame counts: on a machine shared with other work the
// median measures the other work too (both are reported). Where the next frame, as long as the
// longest so far, would end past `deadline`, it stops after its first timed frame (one warm-up,
// one timed: the least that says anything).
Sample measure(Renderer& renderer, const Bundle& bundle, uint64_t seed, uint32_t n, const ModeDraw& draw, Clock::time_point deadline) {
    const auto entered = Clock::now();
    const Camera cam = benchmark_camera();
    const LodRule rule = lod_rule_for(renderer.model(), cam, float(renderer.height()));
    const Crowd crowd = benchmark_crowd(renderer, bundle, seed, n, cam, rule);
    const glm::vec3 light = scene_light_dir();
    FrameState state;
    FrameInstances frame;
    std::vector<double> frame_s, cpu_s;
    bool cut_short = false;
    double longest = 0;
    const auto first = Clock::now();
    for (int i = 0; i < 17; ++i) {
        const auto start = Clock::now();
        const double cpu_start = process_cpu_seconds();
        build_frame(crowd, renderer.model(), cam, renderer.aspect(), draw.lod, rule, float(i) * kFixedTimeStep, &state, &frame, draw.blend);
        renderer.draw(frame, cam, draw.kind, light);
        renderer.finish();
        const double s = seconds_since(start);
        longest = std::max(longest, s);
        const bool out_of_time = i >= 1 && Clock::now() + seconds(longest) > deadline;
        if (i >= 2 || out_of_time) frame_s.push_back(s), cpu_s.push_back(process_cpu_seconds() - cpu_start);  // frame 1 timed, not warm-up
        if (out_of_time) {
            cut_short = frame_s.size() < 3;
            break;
        }
        if (frame_s.size() >= 3 && Clock::now() - first > std::chrono::milliseconds(500)) break;
    }
    std::sort(frame_s.begin(), frame_s.end());
    std::sort(cpu_s.begin(), cpu_s.end());
    Sample sample;
    sample.n = uint32_t(crowd.characters.size());
    sample.fps = 1.0 / std::max(frame_s.front(), 1e-6);
    sample.fps_median = 1.0 / std::max(frame_s[frame_s.size() / 2], 1e-6);
    sample.cpu_ms = 1000.0 * cpu_s[cpu_s.size() / 2];
    sample.cut_short = cut_short;
    sample.seconds = seconds_since(entered);
    for (int l = 0; l < 3; ++l) sample.by_lod[l] = frame.shown[l];
    return sample;
}

// Other work on the machine shows up in the timings; the load average says how much.
double load_average_1min() {
    std::ifstream in("/proc/loadavg");
    double one_minute = -1;
    in >> one_minute;
    return one_minute;
}

// The crowd size of the blend-cost phase: uv_impostor's 30 fps answer; without one (uv_impostor
// not run), the largest 30 fps answer of the modes that ran, at most 256 (a software rasteriser
// blends 256 impostors in seconds a frame: that phase once ran 485 s of a 10 s budget), at least 8.
uint32_t blend_cost_count(const nlohmann::json& results) {
    if (results.contains("uv_impostor") && results["uv_impostor"].value("n_at_30fps", 0u) > 0)
        return results["uv_impostor"]["n_at_30fps"].get<uint32_t>();
    uint32_t n = 0;
    for (const auto& [name, entry] : results.items()) n = std::max(n, entry.value("n_at_30fps", 0u));
    return std::clamp(n, 8u, 256u);
}

// UV impostors with blending off and on (desc.blend, or full when that is off) at one crowd size
// (blend_cost_count, fewer where the time left cannot measure that many). Three alternating rounds,
// the best of each, so both see the same background load. A round starts where it is predicted to
// end before `end`: as long as the last one, or for the first, a measurement per blend as
// `on_cost` predicts (uv_impostor's, drawn with desc.blend; nothing measured: no prediction).
nlohmann::json blend_cost(Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc, const nlohmann::json& results,
                          Clock::time_point end, const MeasureCost& on_cost) {
    const ImpostorBlend on = renderer.effective_blend(desc.blend == ImpostorBlend::off ? ImpostorBlend::full : desc.blend);
    // With reprojection, the plain blend is measured too: what the surface map costs on its own.
    const bool warped = on == ImpostorBlend::warp;
    const int blends = warped ? 3 : 2;
    uint32_t n = blend_cost_count(results);
    const double left_s = std::chrono::duration<double>(end - Clock::now()).count();
    if (on_cost.seconds > 0 && blends * on_cost.predict(n) >= left_s)  // MeasureCost: in proportion above on_cost.n
        n = std::max(1u, std::min(n, uint32_t(left_s / (blends * on_cost.seconds) * on_cost.n)));
    double round_s = blends * on_cost.predict(n);
    Sample best_off, best_on, best_full;
    int rounds = 0;
    for (auto round_start = Clock::now(); rounds < 3 && round_start + seconds(round_s) < end; ++rounds, round_start = Clock::now()) {
        const Sample off = measure(renderer, bundle, desc.seed, n, {LodMode::impostor, ImpostorKind::uv, ImpostorBlend::off}, end);
        const Sample blended = measure(renderer, bundle, desc.seed, n, {LodMode::impostor, ImpostorKind::uv, on}, end);
        if (off.fps > best_off.fps) best_off = off;
        if (blended.fps > best_on.fps) best_on = blended;
        if (warped) {
            const Sample full = measure(renderer, bundle, desc.seed, n, {LodMode::impostor, ImpostorKind::uv, ImpostorBlend::full}, end);
            if (full.fps > best_full.fps) best_full = full;
        }
        round_s = seconds_since(round_start);
    }
    const bool cut_short = rounds < 3 || best_off.cut_short || best_on.cut_short;
    nlohmann::json cost = {{"mode", "uv_impostor"}, {"rounds", rounds}, {"cut_short", cut_short}, {"n", n}, {"blend", impostor_blend_name(on)}};
    if (rounds == 0) {
        log_line(desc, "benchmark: uv_impostor blending cost not measured: no time left (--max-seconds)");
        return cost;
    }
    log_line(desc, "benchmark: uv_impostor N=%u blending off %.1f fps (CPU %.1f ms/frame), %s %.1f fps (CPU %.1f ms/frame)%s", n,
             best_off.fps, best_off.cpu_ms, impostor_blend_name(on), best_on.fps, best_on.cpu_ms, cut_short ? " (cut short by --max-seconds)" : "");
    cost["fps_off"] = rounded(best_off.fps, 10);
    cost["fps_blended"] = rounded(best_on.fps, 10);
    cost["cpu_ms_per_frame_off"] = rounded(best_off.cpu_ms, 100);
    cost["cpu_ms_per_frame_blended"] = rounded(best_on.cpu_ms, 100);
    cost["fps_ratio_blended_to_off"] = rounded(best_on.fps / std::max(best_off.fps, 1e-9), 100);
    if (warped) {
        log_line(desc, "benchmark: uv_impostor N=%u full blending without reprojection %.1f fps (CPU %.1f ms/frame)", n, best_full.fps,
                 best_full.cpu_ms);
        cost["fps_full_unwarped"] = rounded(best_full.fps, 10);
        cost["fps_ratio_warped_to_full"] = rounded(best_on.fps / std::max(best_full.fps, 1e-9), 100);
    }
    return cost;
}

// On a software rasteriser fragments are shaded on the CPU, where an impostor's dependent,
// filtered lookups cost about as much as a mesh's triangles or more: the paper's ranking (a GPU's
// impostors far cheaper than its meshes) turns over there, and figures measured on it say so.
std::string software_rasteriser_note(const nlohmann::json& gl) {
    if (!gl.is_object() || !gl.value("software_rasteriser", false)) return "";
    return "GL_RENDERER " + gl.value("renderer", std::string("?")) +
           " is a software rasteriser: it shades fragments on the CPU, where impostors cost as much as meshes or more, "
           "which inverts the paper's ranking (impostors far cheaper than meshes on a GPU); compare ratios with the paper on a GPU";
}

// What the run is: the machine, the bundle, the blend, the method (results come later).
nlohmann::json report_header(const Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc, double setup_s) {
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
    report["setup_seconds"] = rounded(setup_s, 100);
    report["impostor_blend"] = impostor_blend_name(renderer.effective_blend(desc.blend));
    const std::string note = software_rasteriser_note(desc.gl);
    if (!note.empty()) report["software_rasteriser_note"] = note;
    report["compressed_textures"] = renderer.compressed_textures();
    report["triangles_per_character"] = {{"high", renderer.triangles_per_character(Lod::high)},
                                         {"low", renderer.triangles_per_character(Lod::low)},
                                         {"impostor", 2}};
    report["impostor_switch_distance_m"] = impostor_switch_distance(Camera().fov_y, float(renderer.height()),
                                                                    renderer.model().radius, renderer.model().tile_size);
    report["method"] = "per N: characters walking on the spot in staggered rows 1.6 m apart filling the view "
                       "nearest first from half the impostor switch distance (camera 6 m up, 17 degrees down, fov 45), "
                       "all on screen; hybrid = --lod auto (high, low, UV impostor by distance); 2 warm-up frames, "
                       "then up to 15 frames, each timed from build_frame (cull, LOD, views) to glFinish; a run's fps from "
                       "its fastest frame (fps_median from the median one); a size below or within 25 % above the target "
                       "is run up to 3 times and the median run decides (fps_min, fps_max: the spread); "
                       "N doubles from 8, then bisects to 5 %";
    return report;
}

// One mode's searches for 30 and 60 fps, inside `deadline` (its first probe: inside `end`).
// last_cost: what its last measurement took.
nlohmann::json run_mode(Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc, BenchmarkMode mode, Clock::time_point deadline,
                        Clock::time_point end, MeasureCost* last_cost) {
    const char* name = benchmark_mode_name(mode);
    ModeDraw draw = mode_draw(mode);
    draw.blend = desc.blend;
    ProbeSearch search(
        [&](uint32_t n) {
            const Sample s = measure(renderer, bundle, desc.seed, n, draw, deadline);
            log_line(desc, "benchmark: %-15s N=%-7u %7.1f fps (median frame %6.1f fps, CPU %7.1f ms/frame)  high %u, low %u, impostor %u%s", name,
                     n, s.fps, s.fps_median, s.cpu_ms, s.by_lod[0], s.by_lod[1], s.by_lod[2], s.cut_short ? " (cut short)" : "");
            return s;
        },
        deadline, end);
    bool converged30 = false, converged60 = false;
    const uint32_t n30 = search.largest_holding(30.0, &converged30);
    const uint32_t n60 = search.largest_holding(60.0, &converged60);
    nlohmann::json entry = {{"n_at_30fps", n30}, {"n_at_60fps", n60}, {"converged_30", converged30}, {"converged_60", converged60}};
    if (search.probes().count(n30)) {
        const Sample& s = search.probes().at(n30).runs.front();  // every run of a size draws the same crowd
        entry["lod_split_at_30fps"] = {{"high", s.by_lod[0]}, {"low", s.by_lod[1]}, {"impostor", s.by_lod[2]}};
    }
    entry["samples"] = search.probes_json();
    entry["cut_short"] = !(converged30 && converged60) || search.cut_short();
    *last_cost = search.last_cost();
    return entry;
}

// Each representation's n_at_30fps over the high mesh's.
nlohmann::json ratios_to_high_mesh(const nlohmann::json& results) {
    const double high = results.contains("high_mesh") ? results["high_mesh"].value("n_at_30fps", 0u) : 0.0;
    nlohmann::json ratios = nlohmann::json::object();
    if (high <= 0) return ratios;
    for (const auto& [name, entry] : results.items())
        if (entry.contains("n_at_30fps")) ratios[name] = rounded(entry["n_at_30fps"].get<double>() / high, 100);
    return ratios;
}

}  // namespace

nlohmann::json run_benchmark(Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc) {
    const auto start = Clock::now();
    const auto started = desc.started == Clock::time_point() ? start : desc.started;
    // --max-seconds bounds the whole run from `started`: what is left is shared evenly by the phases
    // still to run (the modes, then the blend cost), each share recomputed as a phase starts.
    const auto end = started + seconds(desc.max_seconds - kExitReserveSeconds);
    nlohmann::json report = report_header(renderer, bundle, desc, std::chrono::duration<double>(start - started).count());
    if (report.contains("software_rasteriser_note")) log_line(desc, "benchmark: %s", report["software_rasteriser_note"].get<std::string>().c_str());
    nlohmann::json results = nlohmann::json::object(), phases = nlohmann::json::array();
    MeasureCost uv_cost;  // uv_impostor's last measurement, to predict the blend-cost phase
    auto finish_phase = [&](const char* name, Clock::time_point phase_start, bool cut_short) {
        phases.push_back({{"name", name}, {"seconds", rounded(seconds_since(phase_start), 100)}, {"cut_short", cut_short}});
        report["results"] = results;
        report["phases"] = phases;
        report["seconds"] = seconds_since(start);
        if (desc.checkpoint) desc.checkpoint(report);  // the report so far, should the run be stopped from outside
    };
    for (size_t m = 0; m < desc.modes.size(); ++m) {
        const char* name = benchmark_mode_name(desc.modes[m]);
        if (mode_draw(desc.modes[m]).lod == LodMode::low && !renderer.model().has_low) {
            log_line(desc, "benchmark: %s skipped: the bundle has no lod 1 mesh", name);
            results[name] = {{"skipped", "no lod 1 mesh"}};
            continue;
        }
        const auto phase_start = Clock::now();
        const auto deadline = phase_start + (end - phase_start) / int64_t(desc.modes.size() - m + 1);
        MeasureCost cost;
        results[name] = run_mode(renderer, bundle, desc, desc.modes[m], deadline, end, &cost);
        if (desc.modes[m] == BenchmarkMode::uv_impostor) uv_cost = cost;
        const bool cut_short = results[name]["cut_short"];
        log_line(desc, "benchmark: %-15s %u at 30 fps, %u at 60 fps, %.1f s%s", name, results[name]["n_at_30fps"].get<uint32_t>(),
                 results[name]["n_at_60fps"].get<uint32_t>(), seconds_since(phase_start), cut_short ? " (cut short by --max-seconds: lower bounds)" : "");
        finish_phase(name, phase_start, cut_short);
    }
    const auto blend_start = Clock::now();
    report["impostor_blend_cost"] = blend_cost(renderer, bundle, desc, results, end, uv_cost);
    log_line(desc, "benchmark: impostor_blend_cost %.1f s", seconds_since(blend_start));
    finish_phase("impostor_blend_cost", blend_start, report["impostor_blend_cost"]["cut_short"]);
    const nlohmann::json ratios = ratios_to_high_mesh(results);
    if (!ratios.empty()) report["ratio_to_high_mesh_at_30fps"] = ratios;
    report["load_average_1min_end"] = load_average_1min();
    report["seconds"] = seconds_since(start);
    return report;
}

}  // namespace crowdview
