// crowdview: shows a crowdbake bundle as a crowd, in a window, headless, or as a benchmark.
//
//   crowdview (--bundle DIR | --url URL | --crowd FILE [--allow-missing]) [--cache DIR] [--count N] [--seed S]
//             [--layout spot|paths] [--headless --frames N --screenshot out.png] [--benchmark --report out.json]
//             [--gl-device auto|software|N] [--require-gpu]
//             [--width W --height H] [--lod auto|high|low|impostor|detail] [--impostor-blend off|views|frames|full|warp]
//             [--key KEY] [--cache-budget-mib N] [--min-rate B] [--timeout S] [--manifest-timeout S]
//             [--clips NAME=W,...] [--switch-after LO,HI]
//   crowdview --verify DIR|URL
//
// The run, in order: the command line (cli_options.h), the bundles (archetypes.h), the GL context
// and the renderer with every bundle uploaded, then the view's frame loop or the benchmark.
// Exit status (cli_options.h): 0 drawn, 1 a file was refused, 2 bad arguments, 3 no OpenGL context
// (--require-gpu: none on a GPU).
#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "archetypes.h"
#include "benchmark.h"
#include "bundle.h"
#include "cli_options.h"
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

// Set before main runs: --max-seconds counts from here, loading and context creation included.
const std::chrono::steady_clock::time_point kProcessStart = std::chrono::steady_clock::now();

FetchOptions fetch_options(const Options& o) {
    FetchOptions fetch;
    fetch.cache_dir = o.cache_dir;
    fetch.files_prefix = o.files_prefix;
    fetch.api_key = o.api_key;
    fetch.cache_budget_bytes = o.cache_budget_mib << 20;
    if (o.min_rate > 0) fetch.min_rate_bytes_per_s = o.min_rate;
    fetch.total_timeout_s = o.timeout_s;
    if (o.manifest_timeout_s > 0) fetch.manifest_timeout_s = o.manifest_timeout_s;
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

// ---------------------------------------------------------------------------------------
// The view: a frame loop over the crowd, in a window or headless

// What a view keeps across frames, and what its log and report read at the end. `builds` points
// into the other lists: fill it once they have their final size (prepare_view).
struct ViewRun {
    std::vector<Crowd> crowds;
    Camera camera;
    std::vector<LodRule> rules;  // each archetype's own LOD distances
    std::vector<FrameState> state;
    std::vector<FrameInstances> frame;
    std::vector<ArchetypeFrame> builds;  // every archetype's frame in one build, on every core
    unsigned build_threads = 1;
    std::vector<ArchetypeCounts> counts;
    std::vector<double> frame_ms;  // whole frames, build to glFinish: headless with --report
    std::vector<double> gpu_ms;    // the same frames' draws on the GPU (Renderer::time_draws)
    double build_seconds = 0;
    float time_s = 0;
    int drawn = 0;
    DrawStats stats;  // the last frame's
};

// The description's camera, else --camera's view of the whole crowd; --switch-view replaces the
// crowd by one character at the origin and looks at it as the bake's view did (SPEC.md "Impostor
// maps": the camera in direction (sin A cos E, sin E, cos A cos E)).
Camera view_camera(const Renderer& renderer, const CrowdFile& file, const Options& o, std::vector<Crowd>* crowds) {
    float height = 0;
    for (size_t a = 0; a < renderer.archetype_count(); ++a) height = std::max(height, character_height(renderer.model(a)));
    Crowd extent;  // the whole crowd's square, for the cameras
    extent.half_extent = crowds_half_extent(*crowds);
    const CameraView view = file.camera.kind == CrowdCameraKind::street ? CameraView::street : o.camera;
    Camera camera = view == CameraView::street ? street_camera(extent, height) : camera_for_crowd(extent, height, renderer.aspect(), 0.35f);
    camera.near_m = 0.1f;
    camera.far_m = std::max(camera.far_m * 4.0f, 200.0f);
    if (file.camera.kind == CrowdCameraKind::look_at) {
        camera = look_at(file.camera.eye, file.camera.target);
        camera.far_m = std::max(camera.far_m, 4.0f * (extent.half_extent + glm::length(file.camera.eye)));
    }
    camera.fov_y = glm::radians(file.camera.fov_deg);
    if (o.switch_view) {
        const CharacterModel& model = renderer.model(0);
        (*crowds)[0].characters.assign(1, Character{glm::vec3(0), 0.0f, 0.0f, 0, 0});
        const float a = glm::radians(o.switch_azimuth_deg), e = glm::radians(o.switch_elevation_deg);
        const float d = impostor_switch_distance(Camera().fov_y, float(renderer.height()), model.radius, model.tile_size);
        camera = look_at(model.center + glm::vec3(std::sin(a) * std::cos(e), std::sin(e), std::cos(a) * std::cos(e)) * d, model.center);
    }
    return camera;
}

void prepare_view(const Renderer& renderer, const CrowdScene& scene, const Options& o, ViewRun* run) {
    const size_t archetype_count = renderer.archetype_count();
    std::string note;
    run->crowds = lay_out_crowd(scene.file, scene.traits, &note);
    if (!note.empty()) log_line(note);
    run->camera = view_camera(renderer, scene.file, o, &run->crowds);
    // Each archetype's own LOD distances: its impostor radius and tile size set the 1:1 distance.
    run->rules.resize(archetype_count);
    for (size_t a = 0; a < archetype_count; ++a) run->rules[a] = lod_rule_for(renderer.model(a), run->camera, float(renderer.height()));
    run->state.resize(archetype_count);
    run->frame.resize(archetype_count);
    run->builds.resize(archetype_count);
    for (size_t a = 0; a < archetype_count; ++a)
        run->builds[a] = {&run->crowds[a], &renderer.model(a), &run->rules[a], &run->state[a], &run->frame[a]};
    run->build_threads = frame_threads();
    run->counts.resize(archetype_count);
}

// The number keys pick a --lod choice (1 auto ... 5 detail); false once Escape is pressed.
bool read_keys(GLFWwindow* window, DrawChoice* choice) {
    const LodChoice keys[] = {LodChoice::automatic, LodChoice::high, LodChoice::low, LodChoice::impostor, LodChoice::detail};
    for (int k = 0; k < 5; ++k)
        if (glfwGetKey(window, GLFW_KEY_1 + k) == GLFW_PRESS) *choice = draw_choice(keys[k], ImpostorKind::uv);
    return glfwGetKey(window, GLFW_KEY_ESCAPE) != GLFW_PRESS;
}

// The frame: cull and choose LODs on the CPU for every archetype, then a few instanced draws per
// archetype. `timed`: wait for the GPU (or llvmpipe) and record the whole frame's time.
void draw_frame(Renderer& renderer, const Options& o, const DrawChoice& choice, std::vector<SwitchMeter>& meters, bool timed,
                ViewRun* run) {
    const size_t archetype_count = renderer.archetype_count();
    const auto build_start = std::chrono::steady_clock::now();
    // Straight into the renderer's mapped instance buffers: draw() then copies nothing.
    build_frames(run->builds, run->camera, renderer.aspect(), choice.lod, run->time_s, o.blend, run->build_threads,
                 renderer.instance_storage());
    run->build_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();
    // The switch measure (--report): a few sampled characters, after the timed part.
    const bool blend_frames = o.blend == ImpostorBlend::frames || o.blend == ImpostorBlend::full || o.blend == ImpostorBlend::warp;
    for (size_t a = 0; a < meters.size() && a < archetype_count; ++a)
        meters[a].observe(run->crowds[a], renderer.model(a), run->state[a], run->camera, renderer.width(), renderer.height(), run->time_s,
                          blend_frames);
    for (size_t a = 0; a < archetype_count; ++a) run->counts[a].add(run->frame[a]);
    ++run->drawn;
    run->stats = renderer.draw(run->frame, run->camera, choice.kind, scene_light_dir());
    if (timed) {
        renderer.finish();
        run->frame_ms.push_back(1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count());
        run->gpu_ms.push_back(renderer.last_draw_gpu_ms());
    }
}

// The frame into the window, its title the frame rate and each archetype's counts.
void present_frame(GlContext& context, const Renderer& renderer, const CrowdScene& scene, const ViewRun& run, double fps) {
    int w = 0, h = 0;
    glfwGetFramebufferSize(context.window(), &w, &h);
    renderer.present(w, h);
    const size_t archetype_count = renderer.archetype_count();
    std::string title = "crowdview - " + std::to_string(int(fps + 0.5)) + " fps";
    for (size_t a = 0; a < archetype_count; ++a)
        title += (archetype_count > 1 ? " - " + scene.names[a] + ": " : " - ") + lod_summary(run.counts[a]);
    context.set_title(title.c_str());
    context.swap_and_poll();
}

// The last frame's counts: per archetype where there are several, then the crowd's.
void log_totals(const GlContext& context, const CrowdScene& scene, const ViewRun& run) {
    uint64_t lod_total[3] = {0, 0, 0}, culled = 0;
    for (size_t a = 0; a < run.counts.size(); ++a) {
        for (int l = 0; l < 3; ++l) lod_total[l] += run.counts[a].last[l];
        culled += run.counts[a].last_culled;
        if (run.counts.size() > 1) log_line("archetype '" + scene.names[a] + "': " + lod_summary(run.counts[a]));
    }
    std::fprintf(stderr, "crowdview: %s; %llu high, %llu low, %llu impostor, %llu culled; %u draws, %llu triangles\n",
                 context.describe().c_str(), (unsigned long long)lod_total[0], (unsigned long long)lod_total[1],
                 (unsigned long long)lod_total[2], (unsigned long long)culled, run.stats.draw_calls,
                 (unsigned long long)run.stats.triangles);
}

// "archetype 'NAME': switches, largest jump / median motion in the clip: high 1.02 (12 measured) ...".
std::string switch_jump_line(const std::string& name, const nlohmann::json& jumps) {
    std::string line = "archetype '" + name + "': switches, largest jump / median motion in the clip:";
    for (const char* lod : {"high", "low", "impostor"}) {
        const nlohmann::json& r = jumps[lod];
        char figure[96];
        std::snprintf(figure, sizeof figure, " %s %s (%d measured)", lod,
                      r["largest_ratio"].is_null() ? "-" : std::to_string(r["largest_ratio"].get<double>()).substr(0, 4).c_str(),
                      r["switches_measured"].get<int>());
        line += figure;
    }
    return line;
}

// The median of per-frame times less the first two frames (where there are more); 0 for none.
double warm_median(const std::vector<double>& per_frame) {
    std::vector<double> timed(per_frame.begin() + (per_frame.size() > 2 ? 2 : 0), per_frame.end());
    std::sort(timed.begin(), timed.end());
    return timed.empty() ? 0.0 : timed[timed.size() / 2];
}

// --report of a headless view: view_report's counts and memory, the median frame time, and per
// archetype its characters per clip, the impostor blend it drew with (`blend` where it can: warp
// needs a surface map) and the switches' jumps. False after one line when it cannot be written.
bool write_view_report(const GlContext& context, const Renderer& renderer, const CrowdScene& scene, const ViewRun& run,
                       std::vector<SwitchMeter>& meters, ImpostorBlend blend, const std::string& path) {
    const double build_ms = run.drawn ? 1e3 * run.build_seconds / run.drawn : 0;
    nlohmann::json report = view_report(context.describe(), renderer, scene, run.counts, run.rules, run.drawn, build_ms, run.stats);
    report["gl"] = gl_report(context.info());
    // Whole frames, cull to glFinish, and their draws on the GPU; the first two warm up (uploads, shader
    // compilation on first use).
    report["frame_ms_median"] = warm_median(run.frame_ms);
    report["gpu_draw_ms_median"] = warm_median(run.gpu_ms);
    for (size_t a = 0; a < renderer.archetype_count(); ++a) {
        report["archetypes"][a]["clips"] =
            clip_counts(run.crowds[a], renderer.model(a), run.state[a], run.camera, renderer.aspect(), run.time_s);
        report["archetypes"][a]["impostor_blend"] = impostor_blend_name(renderer.effective_blend(blend, a));
        if (a < meters.size()) {
            report["archetypes"][a]["switch_jumps"] = meters[a].report();
            log_line(switch_jump_line(scene.names[a], report["archetypes"][a]["switch_jumps"]));
        }
    }
    std::ofstream out(path);
    if (!(out << report.dump(2) << "\n")) return log_line("cannot write " + path), false;
    return true;
}

bool write_screenshot(const Renderer& renderer, const std::string& path) {
    if (!write_png(path, renderer.width(), renderer.height(), renderer.read_rgba())) return log_line("cannot write " + path), false;
    log_line("wrote " + path);
    return true;
}

// Headless runs can take minutes on a software rasteriser: say they are alive. Waits for frame `i`
// to finish first, since the driver queues commands and a line after the queueing alone would
// count frames not yet drawn. A line after the first frame, the last, and at most every
// `every_s` seconds between.
void log_progress(const Renderer& renderer, double every_s, int i, int frames, std::chrono::steady_clock::time_point start,
                  std::chrono::steady_clock::time_point* last_line) {
    renderer.finish();
    const auto now = std::chrono::steady_clock::now();
    const bool due = std::chrono::duration<double>(now - *last_line).count() >= every_s;
    if (i != 0 && i + 1 != frames && !due) return;
    *last_line = now;
    std::fprintf(stderr, "crowdview: frame %d of %d, %.1f s elapsed\n", i + 1, frames, std::chrono::duration<double>(now - start).count());
}

// `meters`: one per archetype with --report (the switch measure, switch_report.h), else empty.
int run_view(GlContext& context, Renderer& renderer, const CrowdScene& scene, const Options& o, std::vector<SwitchMeter>& meters) {
    ViewRun run;
    prepare_view(renderer, scene, o, &run);
    const CharacterModel& model = renderer.model(0);  // --switch-view: one archetype
    DrawChoice choice = draw_choice(o.lod, o.impostors);
    FlyControls controls;
    const bool windowed = context.visible();
    const int frames = o.frames > 0 ? o.frames : (windowed ? -1 : 1);
    const bool timed = !o.report.empty() && !windowed;
    renderer.time_draws(timed);
    const auto start = std::chrono::steady_clock::now();
    auto last = start, last_progress = start;
    double fps_smoothed = 0;
    for (int i = 0; frames < 0 || i < frames; ++i) {
        if (context.should_close()) break;
        const auto now = std::chrono::steady_clock::now();
        const float dt = windowed ? std::chrono::duration<float>(now - last).count() : kFixedTimeStep;
        last = now;
        run.time_s = windowed ? run.time_s + dt : float(i) * kFixedTimeStep;
        // Half a frame in, so floor(t * fps) is the frame asked for.
        if (o.switch_view) run.time_s = (float(o.switch_frame % std::max(model.frame_count, 1u)) + 0.5f) / model.frames_per_second;
        if (windowed) {
            controls.update(context.window(), &run.camera, dt);
            if (!read_keys(context.window(), &choice)) break;
        }
        draw_frame(renderer, o, choice, meters, timed, &run);
        if (windowed) {
            fps_smoothed = fps_smoothed == 0 ? 1.0 / std::max(dt, 1e-4f) : 0.9 * fps_smoothed + 0.1 / std::max(dt, 1e-4f);
            present_frame(context, renderer, scene, run, fps_smoothed);
        } else {
            log_progress(renderer, o.progress_every_s, i, frames, start, &last_progress);
        }
    }
    log_totals(context, scene, run);
    if (!o.report.empty() && !write_view_report(context, renderer, scene, run, meters, o.blend, o.report)) return kExitRefused;
    if (!o.screenshot.empty() && !write_screenshot(renderer, o.screenshot)) return kExitRefused;
    return 0;
}

// ---------------------------------------------------------------------------------------
// Before the view: bundles, context, renderer

// --verify: one bundle loaded and verified; "OK NAME VERSION (N files)" or "CODE FILE" on stdout.
int verify_bundle(const Options& o) {
    Bundle bundle;
    const Status status = o.source_is_url ? fetch_bundle(o.source, fetch_options(o), &bundle) : load_bundle_dir(o.source, &bundle);
    if (status) std::printf("OK %s %s (%zu files)\n", bundle.manifest.name.c_str(), bundle.manifest.version.c_str(),
                            bundle.manifest.files.size());
    else std::printf("%s %s\n", error_code_name(status.code), status.file.c_str());
    if (!status) std::fprintf(stderr, "crowdview: %s\n", status.message.c_str());
    return status ? 0 : kExitRefused;
}

// The exit status after the refusals so far (cli_options.h): a lone bundle's stops the run; a
// crowd's stop it unless --allow-missing, and always when no archetype is `left`. 0: go on.
int refusal_status(const Options& o, const CrowdScene& scene, size_t left, const std::string& stage) {
    if (o.crowd_file.empty() && !scene.refused.empty()) return log_line("bundle refused: " + scene.refused[0].error), kExitRefused;
    if (left == 0) return log_line("no archetype of " + o.crowd_file + " could be " + stage), kExitRefused;
    if (!scene.refused.empty() && !o.allow_missing)
        return log_line(std::to_string(scene.refused.size()) + " of " + std::to_string(scene.file.archetypes.size()) + " archetypes of " +
                        o.crowd_file + " refused; --allow-missing draws the crowd without them"),
               kExitRefused;
    return 0;
}

// What the options ask of the loaded bundles: every clip of a clip mix, and the detail maps that
// detail-mapped impostors need (a bake stores them only when asked: --detail-map). 0, or the exit
// status after one line: --clips and --lod are arguments (exit 2); a description's clip mix is the file's (exit 1).
int check_bundles_against_options(const Options& o, const CrowdFile& file, const std::vector<LoadedArchetype>& loaded) {
    const bool one_bundle = o.crowd_file.empty();
    for (const LoadedArchetype& a : loaded) {
        std::vector<float> weights;
        const std::string error = resolve_clip_mix(file.archetypes[a.desc_index].clips, a.bundle->manifest.clips, &weights);
        if (!error.empty()) return log_line((one_bundle ? "--clips: " : "archetype '" + a.name + "': ") + error), one_bundle ? kExitUsage : kExitRefused;
    }
    const bool wants_detail = o.lod == LodChoice::detail || (o.lod == LodChoice::automatic && o.impostors == ImpostorKind::detail);
    for (const LoadedArchetype& a : loaded)
        if (wants_detail && !o.benchmark && a.bundle->manifest.impostor.detail_map.empty())
            return log_line(a.bundle->manifest.name + " " + a.bundle->manifest.version + " has no detail maps (bake it with --detail-map); "
                            "--lod detail and --impostors detail need them, --lod impostor draws the UV-mapped impostor"), kExitUsage;
    return 0;
}

// The crowd: the --crowd description, or a one-archetype crowd of --bundle or --url; every bundle
// from its folder or fetched through the one cache, verified either way. 0, or the exit status after one line.
int load_scene(const Options& o, CrowdScene* scene, std::vector<LoadedArchetype>* loaded) {
    const bool one_bundle = o.crowd_file.empty();
    if (!one_bundle) {
        const std::string error = load_crowd_description(o.crowd_file, &scene->file);
        if (!error.empty()) return log_line(error), kExitRefused;
    } else {
        ArchetypeSource source;
        (o.source_is_url ? source.url : source.folder) = o.source;
        scene->file = single_archetype_crowd(source, o.count, o.seed, o.layout == Layout::paths);
        scene->file.archetypes[0].clips = o.clips;
    }
    scene->switch_after_s[0] = o.switch_after_s[0], scene->switch_after_s[1] = o.switch_after_s[1];
    *loaded = load_archetypes(scene->file, fetch_options(o), one_bundle ? std::function<void(const std::string&)>() : log_line,
                              &scene->refused);
    if (const int status = refusal_status(o, *scene, loaded->size(), "loaded")) return status;
    return check_bundles_against_options(o, scene->file, *loaded);
}

// The GL context (a window unless --headless or --benchmark), logged; nullptr after one line.
std::unique_ptr<GlContext> open_context(const Options& o) {
    GlContextDesc desc;
    desc.width = o.width;
    desc.height = o.height;
    desc.window = !(o.headless || o.benchmark);
    desc.device = o.gl_device;
    desc.require_gpu = o.require_gpu;
    std::string error;
    std::unique_ptr<GlContext> context = GlContext::create(desc, &error);
    if (!context) return log_line(error), nullptr;
    const std::string gl_renderer = context->renderer_name();
    log_line(gl_context_line(context->info()) + " (" + (desc.window ? "window" : "headless") + ")");
    const bool draws_impostors = o.benchmark || !(o.lod == LodChoice::high || o.lod == LodChoice::low);
    if (is_software_renderer(gl_renderer) && !o.blend_chosen && draws_impostors)
        log_line("note: " + gl_renderer + " is a software rasteriser, where the default --impostor-blend warp costs about 4x "
                 "(the demo's mixed crowd, 3 frames: 5.2 s against 1.3 s); --impostor-blend off draws the nearest view and "
                 "frame instead");
    return context;
}

// The layout indexes archetypes as the renderer does; a positions layout names description indices.
void index_positions_by_renderer(CrowdScene* scene) {
    if (scene->file.layout.kind != CrowdLayoutKind::positions) return;
    for (PlacedCharacter& p : scene->file.layout.positions) {
        const auto it = std::find(scene->desc_index.begin(), scene->desc_index.end(), size_t(p.archetype));
        p.archetype = it == scene->desc_index.end() ? UINT32_MAX : uint32_t(it - scene->desc_index.begin());
    }
}

// The renderer with each loaded bundle uploaded as one archetype. 0, or the exit status after one line.
int make_renderer(const Options& o, const std::vector<LoadedArchetype>& loaded, CrowdScene* scene, std::unique_ptr<Renderer>* renderer) {
    RendererDesc desc;
    desc.width = o.width;
    desc.height = o.height;
    desc.shader_dir = o.shader_dir;
    desc.force_cpu_texture_decode = o.cpu_decode;
    std::string error;
    *renderer = Renderer::create(desc, &error);
    if (!*renderer) return log_line(error), kExitRefused;
    const bool one_bundle = o.crowd_file.empty();
    if (!upload_archetypes(renderer->get(), loaded, scene, one_bundle ? std::function<void(const std::string&)>() : log_line, &error))
        return log_line(error), kExitRefused;
    if (const int status = refusal_status(o, *scene, (*renderer)->archetype_count(), "drawn")) return status;
    index_positions_by_renderer(scene);
    return 0;
}

// The switch measure reads the pose caches on the CPU: one meter per renderer archetype, only for
// --report, each bundle's pose caches taken out of `loaded` once and shared by its archetypes' meters.
std::vector<SwitchMeter> switch_meters(const Options& o, const Renderer& renderer, const CrowdScene& scene,
                                       std::vector<LoadedArchetype>* loaded) {
    std::vector<SwitchMeter> meters;
    if (o.report.empty()) return meters;
    std::map<const Bundle*, std::shared_ptr<const std::vector<PoseCache>>> poses;
    for (size_t a = 0; a < renderer.archetype_count(); ++a)
        for (LoadedArchetype& l : *loaded) {
            if (l.desc_index != scene.desc_index[a]) continue;
            auto& shared = poses[l.bundle.get()];
            if (!shared) shared = std::make_shared<const std::vector<PoseCache>>(std::move(l.bundle->meshes));
            meters.emplace_back(shared, l.bundle->manifest.meshes);
        }
    return meters;
}

}  // namespace

int main(int argc, char** argv) {
    const Options o = parse_args(argc, argv, CROWDVIEW_SHADER_DIR);
    if (o.verify_only) return verify_bundle(o);

    // 1. Bundles: the crowd's, loaded and verified.
    CrowdScene scene;
    std::vector<LoadedArchetype> loaded;
    if (const int status = load_scene(o, &scene, &loaded)) return status;

    // 2. GL context and the uploaded bundles, one renderer archetype each.
    std::unique_ptr<GlContext> context = open_context(o);
    if (!context) return kExitNoGl;
    std::unique_ptr<Renderer> renderer;
    if (const int status = make_renderer(o, loaded, &scene, &renderer)) return status;

    // 3. Run.
    if (o.benchmark) return run_benchmark_mode(*context, *renderer, *loaded[0].bundle, o);
    std::vector<SwitchMeter> meters = switch_meters(o, *renderer, scene, &loaded);
    for (LoadedArchetype& a : loaded) a.bundle.reset();  // on the GPU now
    return run_view(*context, *renderer, scene, o, meters);
}
