// The paper's figure 3 on this machine: for each representation, the largest crowd that
// holds 30 fps and 60 fps (runtime/README.md, "Benchmark"). Needs a current context and an
// uploaded bundle; writes a JSON report.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bundle.h"
#include "crowd.h"
#include "renderer.h"

namespace crowdview {

// One representation under test: how build_frame chooses LODs and which impostor maps draw.
enum class BenchmarkMode { high_mesh, low_mesh, uv_impostor, detail_impostor, hybrid };
constexpr BenchmarkMode kAllBenchmarkModes[] = {BenchmarkMode::high_mesh, BenchmarkMode::low_mesh, BenchmarkMode::uv_impostor,
                                                BenchmarkMode::detail_impostor, BenchmarkMode::hybrid};

// "high_mesh", ...; and back (false for an unknown name).
const char* benchmark_mode_name(BenchmarkMode mode);
bool parse_benchmark_mode(const std::string& name, BenchmarkMode* mode);
// "off", "views", "frames", "full".
const char* impostor_blend_name(ImpostorBlend blend);

struct BenchmarkDesc {
    uint64_t seed = 1;
    double max_seconds = 300;  // the whole run from `started`: shared evenly by the modes and the blend-cost phase
    // When max_seconds began counting (crowdview: the process's start, so that loading the bundle
    // and making the context count too); zero: when run_benchmark starts.
    std::chrono::steady_clock::time_point started{};
    std::vector<BenchmarkMode> modes{std::begin(kAllBenchmarkModes), std::end(kAllBenchmarkModes)};
    // How impostors blend views and frames in uv_impostor, detail_impostor and hybrid. The
    // report also times UV impostors with blending off and on at one crowd size.
    ImpostorBlend blend = ImpostorBlend::warp;
    std::string device;        // GlContext::describe(), for the report
    nlohmann::json gl;         // gl_report(GlContext::info()), for the report
    std::function<void(const std::string&)> log;  // one progress line per measurement; may be empty
    // Called with the report so far after each phase (the caller writes it, so a run stopped from
    // outside still leaves one); may be empty.
    std::function<void(const nlohmann::json&)> checkpoint;
};

// Runs every mode of `desc` and returns the report (README.md lists its fields).
nlohmann::json run_benchmark(Renderer& renderer, const Bundle& bundle, const BenchmarkDesc& desc);

}  // namespace crowdview
