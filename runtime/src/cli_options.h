// crowdview's command line, parsed and checked once (parse_args), and its exit codes.
// Exit codes, one rule for every input:
//   0  drawn (with --crowd --allow-missing, archetypes whose bundles were refused are left out)
//   1  a file was refused: a bundle that cannot be loaded, verified or uploaded (with --crowd, any
//      archetype's, unless --allow-missing; always when none is left), a crowd description that
//      cannot be read, does not parse or breaks its rules (a clip its bundle lacks included), or
//      an output that cannot be written
//   2  the command line is wrong (a flag, a value, a combination, a --clips name the bundle lacks,
//      --lod detail on a bundle without detail maps): one line, before anything is drawn
//   3  no OpenGL context could be created here (--require-gpu: none on a GPU)
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "benchmark.h"
#include "crowd.h"
#include "crowd_file.h"
#include "gl_context.h"
#include "renderer.h"

namespace crowdview {

constexpr int kExitRefused = 1, kExitUsage = 2, kExitNoGl = 3;

// --lod: a LOD rule for everyone, or one representation for everyone.
enum class LodChoice { automatic, high, low, impostor, detail };
enum class CameraView { overview, street };

struct Options {
    std::string source;        // a bundle folder or URL (--bundle, --url or --verify)
    std::string crowd_file;    // --crowd: a crowd description (crowd_file.h) instead of one bundle
    bool crowd_flags = false;  // --count, --seed or --layout given: they belong in the description
    bool allow_missing = false;  // --allow-missing: a --crowd archetype whose bundle is refused is left out
    bool source_is_url = false;  // holds "://": fetched through the cache
    bool verify_only = false;  // --verify
    std::string cache_dir, files_prefix = "files/", shader_dir;
    std::string api_key;       // --key, else $CROWDVIEW_API_KEY; never printed
    uint64_t cache_budget_mib = 4096;
    double min_rate = 0, timeout_s = 0, manifest_timeout_s = 0;  // 0: FetchOptions' defaults
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
    double progress_every_s = 2;    // headless: a "frame k of N" line at most this often, first and last frame aside
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

// The options of `argv`, with $CROWDVIEW_API_KEY and $CROWDVIEW_SHADERS (else `default_shader_dir`)
// filled in. --help prints the usage and exits 0; a bad command line prints one line and exits
// kExitUsage.
Options parse_args(int argc, char** argv, const std::string& default_shader_dir);

}  // namespace crowdview
