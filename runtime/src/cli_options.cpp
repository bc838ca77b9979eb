// crowdview's command line (see cli_options.h).
#include "cli_options.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>

#include "cli_parse.h"

namespace {

const char* kUsage =
    "usage: crowdview (--bundle DIR | --url URL | --crowd FILE) [options]\n"
    "       crowdview --verify DIR|URL [--cache DIR] [--files-prefix P]\n"
    "  --bundle DIR          a bundle folder (manifest.json and its files)\n"
    "  --url URL             a published bundle: URL/manifest.json and URL/<files-prefix><path>\n"
    "  --crowd FILE          a crowd description (JSON, shared_formats/crowd.schema.json): several archetypes\n"
    "  --allow-missing       --crowd: draw without the archetypes whose bundles are refused (default: exit 1)\n"
    "  --cache DIR           content-addressed download cache (default ~/.cache/crowdview)\n"
    "  --files-prefix P      where files sit below the bundle URL (default files/)\n"
    "  --key KEY             API key sent as a bearer token (default: $CROWDVIEW_API_KEY)\n"
    "  --cache-budget-mib N  refuse bundles listing more than N MiB (default 4096)\n"
    "  --min-rate B          each file must arrive at B bytes/s or faster (default 65536)\n"
    "  --timeout S           give up a whole fetch after S seconds (default: 60 + size / min rate);\n"
    "                        a --crowd's fetches share one such deadline\n"
    "  --manifest-timeout S  each manifest must arrive within S seconds (default 60)\n"
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
    "  --progress-every S    headless: print \"frame k of N\" as frames finish: the first, the last, every S s between (default 2)\n"
    "  --screenshot PNG      write the last frame\n"
    "  --benchmark           largest crowd at 30 and 60 fps per representation (headless)\n"
    "  --report JSON         benchmark figures; headless: counts per archetype and LOD, GPU memory per archetype\n"
    "  --max-seconds S       benchmark time budget in seconds, every phase included (default 300)\n"
    "  --modes LIST          benchmark these of high_mesh,low_mesh,uv_impostor,detail_impostor,hybrid\n"
    "  --shaders DIR         shader folder (default: the source tree's src/shaders)\n"
    "  --cpu-decode          upload BC textures decoded to RGBA8 even where S3TC exists\n"
    "exit status:\n"
    "  0  drawn (with --allow-missing, maybe without some archetypes: each is logged and in --report's \"refused\")\n"
    "  1  a file was refused: a bundle (any --crowd archetype's, unless --allow-missing; always when none is\n"
    "     left), the --crowd description (unreadable, not JSON, against its rules, a clip its bundle lacks),\n"
    "     or an output that cannot be written\n"
    "  2  bad arguments (a --clips name the bundle lacks, --lod detail without detail maps included)\n"
    "  3  no OpenGL context (--require-gpu: none on a GPU)\n";

[[noreturn]] void usage_error(const std::string& message) {
    std::fprintf(stderr, "crowdview: %s (see --help)\n", message.c_str());
    std::exit(crowdview::kExitUsage);
}

}  // namespace

namespace crowdview {

namespace {

bool is_url(const std::string& s) { return s.find("://") != std::string::npos; }

void parse_switch_view(const std::string& v, Options* o) {
    char rest = 0;
    if (std::sscanf(v.c_str(), "%f,%f,%d%c", &o->switch_azimuth_deg, &o->switch_elevation_deg, &o->switch_frame, &rest) != 3 ||
        o->switch_frame < 0 || std::fabs(o->switch_elevation_deg) > 90.0f)
        usage_error("--switch-view takes AZIMUTH,ELEVATION,FRAME (degrees, elevation within +-90, frame >= 0); got '" + v + "'");
    o->switch_view = true;
}

std::vector<ClipWeight> parse_clip_mix(const std::string& v) {
    std::vector<ClipWeight> clips;
    for (size_t start = 0; start <= v.size();) {
        const size_t end = std::min(v.find(',', start), v.size()), eq = v.find('=', start);
        ClipWeight w;
        w.clip = v.substr(start, std::min(eq, end) - start);
        if (eq < end) w.weight = parse_number<float>("--clips weight of '" + w.clip + "'", v.substr(eq + 1, end - eq - 1).c_str(), 0, 1e6f);
        if (w.clip.empty() || !(w.weight > 0)) usage_error("--clips takes NAME=WEIGHT,NAME=WEIGHT,...; got '" + v + "'");
        clips.push_back(w);
        start = end + 1;
    }
    return clips;
}

void parse_gl_device_flag(const std::string& v, GlDeviceChoice* device) {
    if (!parse_gl_device(v, device)) usage_error("--gl-device is auto, software or an EGL device number; got '" + v + "'");
}

void parse_switch_after(const std::string& v, float s[2]) {
    char rest = 0;
    if (std::sscanf(v.c_str(), "%f,%f%c", &s[0], &s[1], &rest) != 2 || !(s[0] >= 0 && s[0] <= s[1] && s[1] <= 86400))
        usage_error("--switch-after takes LO,HI seconds (0 <= LO <= HI <= 86400); got '" + v + "'");
}

// --modes' list, each mode once, in the order given.
std::vector<BenchmarkMode> parse_modes(const std::string& modes) {
    std::vector<BenchmarkMode> parsed;
    for (size_t start = 0; start <= modes.size();) {
        const size_t end = std::min(modes.find(',', start), modes.size());
        const std::string name = modes.substr(start, end - start);
        BenchmarkMode mode;
        if (!parse_benchmark_mode(name, &mode))
            usage_error("--modes takes high_mesh, low_mesh, uv_impostor, detail_impostor, hybrid; got '" + name + "'");
        if (std::find(parsed.begin(), parsed.end(), mode) == parsed.end()) parsed.push_back(mode);
        start = end + 1;
    }
    return parsed;
}

// A flag that takes no value or a number: true when `a` was one. `value` reads the flag's value.
template <typename Value>
bool parse_plain_flag(const std::string& a, Value value, Options& o) {
    if (a == "--cache") o.cache_dir = value();
    else if (a == "--key") o.api_key = value();
    else if (a == "--cache-budget-mib") o.cache_budget_mib = parse_number<uint64_t>(a, value(), 1, 1ull << 30);
    else if (a == "--min-rate") o.min_rate = parse_number<double>(a, value(), 1, 1e12);
    else if (a == "--timeout") o.timeout_s = parse_number<double>(a, value(), 0.1, 1e7);
    else if (a == "--manifest-timeout") o.manifest_timeout_s = parse_number<double>(a, value(), 0.1, 1e7);
    else if (a == "--files-prefix") o.files_prefix = value();
    else if (a == "--shaders") o.shader_dir = value();
    else if (a == "--count") o.count = parse_number<uint32_t>(a, value(), 1, 10000000), o.crowd_flags = true;
    else if (a == "--seed") o.seed = parse_number<uint64_t>(a, value(), 0, 1ull << 53), o.crowd_flags = true;
    else if (a == "--frames") o.frames = parse_number<int>(a, value(), 1, 100000000);
    else if (a == "--width") o.width = parse_number<int>(a, value(), 16, 16384);
    else if (a == "--height") o.height = parse_number<int>(a, value(), 16, 16384);
    else if (a == "--max-seconds") o.max_seconds = parse_number<double>(a, value(), 1, 86400);
    else if (a == "--progress-every") o.progress_every_s = parse_number<double>(a, value(), 1e-6, 86400);
    else if (a == "--screenshot") o.screenshot = value();
    else if (a == "--report") o.report = value();
    else if (a == "--headless") o.headless = true;
    else if (a == "--benchmark") o.benchmark = true;
    else if (a == "--cpu-decode") o.cpu_decode = true;
    else if (a == "--allow-missing") o.allow_missing = true;
    else if (a == "--require-gpu") o.require_gpu = true;
    else return false;
    return true;
}

// A flag that takes a named choice or a list: true when `a` was one.
template <typename Value>
bool parse_choice_flag(const std::string& a, Value value, Options& o) {
    if (a == "--layout")
        o.crowd_flags = true, o.layout = parse_choice<Layout>(a, value(), {{"spot", Layout::on_the_spot}, {"paths", Layout::paths}});
    else if (a == "--camera")
        o.camera = parse_choice<CameraView>(a, value(), {{"overview", CameraView::overview}, {"street", CameraView::street}});
    else if (a == "--lod")
        o.lod = parse_choice<LodChoice>(a, value(), {{"auto", LodChoice::automatic}, {"high", LodChoice::high}, {"low", LodChoice::low},
                                                     {"impostor", LodChoice::impostor}, {"detail", LodChoice::detail}});
    else if (a == "--impostor-blend")
        o.blend_chosen = true, o.blend = parse_choice<ImpostorBlend>(a, value(), {{"off", ImpostorBlend::off}, {"views", ImpostorBlend::views},
                                                                                  {"frames", ImpostorBlend::frames}, {"full", ImpostorBlend::full},
                                                                                  {"warp", ImpostorBlend::warp}});
    else if (a == "--impostors")
        o.impostors = parse_choice<ImpostorKind>(a, value(), {{"uv", ImpostorKind::uv}, {"detail", ImpostorKind::detail}});
    else if (a == "--switch-view") parse_switch_view(value(), &o);
    else if (a == "--gl-device") parse_gl_device_flag(value(), &o.gl_device);
    else if (a == "--switch-after") parse_switch_after(value(), o.switch_after_s);
    else if (a == "--clips") {
        const std::vector<ClipWeight> mix = parse_clip_mix(value());
        o.clips.insert(o.clips.end(), mix.begin(), mix.end());
    } else if (a == "--modes") {
        const std::string list = value();
        if (!list.empty()) o.modes = parse_modes(list);
    } else {
        return false;
    }
    return true;
}

// Flags that do not go together, or need another.
void check_combinations(const Options& o, int sources) {
    if (sources == 0) usage_error("give --bundle DIR, --url URL, --crowd FILE or --verify DIR|URL");
    if (sources > 1) usage_error("give only one of --bundle, --url, --crowd and --verify");
    if (o.benchmark && !o.screenshot.empty()) usage_error("--screenshot does not go with --benchmark");
    if (!o.report.empty() && !o.benchmark && !o.headless) usage_error("--report needs --benchmark or --headless");
    if (o.gl_device.kind != GlDeviceChoice::automatic && !o.benchmark && !o.headless) usage_error("--gl-device needs --benchmark or --headless");
    if (!o.crowd_file.empty() && o.crowd_flags) usage_error("--count, --seed and --layout go in the --crowd description");
    if (!o.crowd_file.empty() && !o.clips.empty()) usage_error("--clips goes in the --crowd description's archetypes (\"clips\")");
    if (!o.crowd_file.empty() && (o.benchmark || o.switch_view)) usage_error("--benchmark and --switch-view take --bundle or --url");
    if (o.crowd_file.empty() && o.allow_missing) usage_error("--allow-missing goes with --crowd (a lone bundle cannot be left out)");
}

}  // namespace

Options parse_args(int argc, char** argv, const std::string& default_shader_dir) {
    Options o;
    int sources = 0;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        const auto value = [&]() -> const char* {
            if (i + 1 >= argc) usage_error(a + " needs a value");
            return argv[++i];
        };
        if (a == "--help" || a == "-h") {
            std::fputs(kUsage, stdout);
            std::exit(0);
        } else if (a == "--bundle" || a == "--url" || a == "--verify") {
            o.source = value();
            o.source_is_url = is_url(o.source);
            o.verify_only = a == "--verify";
            ++sources;
        } else if (a == "--crowd") {
            o.crowd_file = value();
            ++sources;
        } else if (!parse_plain_flag(a, value, o) && !parse_choice_flag(a, value, o)) {
            usage_error("unknown argument '" + a + "'");
        }
    }
    check_combinations(o, sources);
    if (o.api_key.empty()) {
        const char* env = std::getenv("CROWDVIEW_API_KEY");
        o.api_key = env ? env : "";
    }
    if (o.shader_dir.empty()) {
        const char* env = std::getenv("CROWDVIEW_SHADERS");
        o.shader_dir = env && *env ? env : default_shader_dir;
    }
    return o;
}

}  // namespace crowdview
