// crowdview headless on a synthetic v2 bundle (an idle and a walk, a transition each way): every
// character changes clip at least once, --report counts characters per clip and transition and
// gives the switch figure per representation; the clip mix is honoured, an unknown clip refused.
//   test_clip_render CROWDVIEW
// Exits 77 (skipped) where crowdview finds no OpenGL context.
#include <sys/wait.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>

#include <glm/gtc/constants.hpp>
#include <nlohmann/json.hpp>

#include "check.h"
#include "crowd.h"
#include "synthetic_bundle.h"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

using synthetic::Run;

Run run(const std::string& crowdview, const std::string& args) { return synthetic::run_crowdview(crowdview, args + " >/dev/null"); }

json read_json(const std::string& path) { return json::parse(synthetic::read_text(path), nullptr, false); }

// 320 x 240 keeps llvmpipe quick; the LOD distances below are for this height.
constexpr int kWidth = 320, kHeight = 240;
// The target for a switch against the motion inside its clip.
constexpr double kMaxSwitchRatio = 1.5;

}  // namespace

int main(int argc, char** argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: test_clip_render CROWDVIEW\n");
        return 2;
    }
    const std::string work = synthetic::temp_dir("clip-render");
    synthetic::Options o = synthetic::Options::two_clips();
    o.tile_size = 32;
    o.azimuths_deg = {0, 90, 180, 270};
    const std::string bundle = work + "/clips";
    const std::string error = synthetic::write_bundle(bundle, o);
    CHECK_MSG(error.empty(), error);
    const float radius = read_json(bundle + "/manifest.json")["impostor"]["bounds"]["radius"].get<float>();
    const float switch_m = crowdview::impostor_switch_distance(glm::radians(45.0f), kHeight, radius, o.tile_size);

    // Three characters at a high-mesh, a low-mesh and an impostor depth each, dwelling 0.2 to 0.6 s.
    json positions = json::array();
    for (float fraction : {0.3f, 0.75f, 1.5f})
        for (int lane = -1; lane <= 1; ++lane)
            positions.push_back({{"archetype", "walker"}, {"at", {0.25f * float(lane) * fraction * switch_m, -fraction * switch_m}},
                                 {"heading_deg", 40 * lane}});
    const json crowd = {
        {"crowd_format_version", 1},
        {"archetypes", {{{"name", "walker"}, {"bundle", "clips"}, {"share", 1}, {"clips", {{{"clip", "idle"}}, {{"clip", "walk"}, {"weight", 2}}}},
                         {"switch_after_s", {0.2, 0.6}}}}},
        {"layout", {{"kind", "positions"}, {"positions", positions}}},
        {"camera", {{"kind", "look_at"}, {"eye", {0, 1.2, 0}}, {"target", {0, 1.2, -10}}}}};
    std::ofstream(work + "/crowd.json") << crowd.dump(2);
    const std::string size = " --width " + std::to_string(kWidth) + " --height " + std::to_string(kHeight);
    const std::string report_file = work + "/report.json";
    // 80 frames (2.7 s): a dwell, up to a loop to the leave frame and the transition fit in.
    const Run r = run(argv[1], "--crowd '" + work + "/crowd.json' --headless --frames 80 --impostor-blend frames --report '" + report_file + "'" + size);
    if (r.status == 3) {
        std::fprintf(stderr, "SKIP: %s", r.err.c_str());
        fs::remove_all(work);
        return 77;
    }
    CHECK_MSG(r.status == 0, r.err);
    const json report = read_json(report_file);
    CHECK(!report.is_discarded());
    if (!report.is_discarded() && report["archetypes"].size() == 1) {
        const json& a = report["archetypes"][0];
        CHECK_MSG(a["clips"]["characters"] == 9 && a["clips"]["characters_switched"] == 9, a["clips"].dump());
        uint64_t counted = 0;
        for (const char* range : {"idle", "walk", "idle->walk", "walk->idle"}) {
            CHECK_MSG(a["clips"]["counts"].contains(range), a["clips"].dump());
            for (const char* lod : {"high", "low", "impostor"}) counted += a["clips"]["counts"][range][lod].get<uint64_t>();
        }
        CHECK(counted == 9);
        for (const char* lod : {"high", "low", "impostor"}) {
            const json& s = a["switch_jumps"][lod];
            CHECK_MSG(s["switches_measured"].get<int>() >= 3 && s["sampled_characters"] == 3, s.dump());
            // Transitions that ease phase and stride move about as much as a frame of their clips.
            CHECK_MSG(!s["largest_ratio"].is_null() && s["largest_ratio"].get<double>() <= kMaxSwitchRatio &&
                          s["largest_ratio"].get<double>() > 0.3 && s["reference_px"].get<double>() > 0,
                      std::string(lod) + ": " + s.dump());
            // Against the clip's own motion at that phase as well (never above the plain ratio).
            CHECK_MSG(!s["largest_ratio_same_phase"].is_null() && s["largest_ratio_same_phase"].get<double>() <= kMaxSwitchRatio &&
                          s["largest_ratio_same_phase"].get<double>() <= s["largest_ratio"].get<double>() + 1e-9,
                      std::string(lod) + ": " + s.dump());
        }
        CHECK_MSG(r.err.find("switches, largest jump / median motion in the clip: high ") != std::string::npos, r.err);
    }

    // Transitions that end 3/8 of a stride off their arrive frame pop, and the figure says so.
    synthetic::Options popping = o;
    popping.popping_transitions = true;
    const std::string error_popping = synthetic::write_bundle(work + "/popping", popping);
    CHECK_MSG(error_popping.empty(), error_popping);
    const Run pop = run(argv[1], "--bundle '" + work + "/popping' --count 4 --headless --frames 60 --lod high --camera street "
                                 "--switch-after 0.1,0.3 --report '" + work + "/pop.json'" + size);
    CHECK_MSG(pop.status == 0, pop.err);
    const json popped = read_json(work + "/pop.json");
    if (!popped.is_discarded()) {
        const json& s = popped["archetypes"][0]["switch_jumps"]["high"];
        CHECK_MSG(s["switches_measured"].get<int>() > 0 && s["largest_ratio"].get<double>() > kMaxSwitchRatio, s.dump());
        // The report points at the join that pops: out of a transition into the clip it arrives in.
        CHECK_MSG(s["worst"].is_object() && s["worst"]["from"].get<std::string>().find("->") != std::string::npos &&
                      s["worst"]["to"].get<std::string>().find("->") == std::string::npos,
                  s.dump());
    }

    // The mix is honoured: walk alone, and nothing leads from walk to a clip of weight > 0.
    const Run walk = run(argv[1], "--bundle '" + bundle + "' --count 6 --headless --frames 20 --lod low --clips walk=1 --switch-after 0,0.1 "
                                  "--report '" + work + "/walk.json'" + size);
    CHECK_MSG(walk.status == 0, walk.err);
    const json walked = read_json(work + "/walk.json");
    if (!walked.is_discarded()) {
        const json& clips = walked["archetypes"][0]["clips"];
        CHECK_MSG(clips["characters_switched"] == 0 && clips["counts"]["walk"]["low"] == 6 && clips["counts"]["idle"]["low"] == 0, clips.dump());
    }
    // A clip the bundle lacks: one line, exit 2.
    const Run unknown = run(argv[1], "--bundle '" + bundle + "' --count 2 --headless --clips walk=1,run=2");
    CHECK_MSG(unknown.status == 2 && unknown.err.find("--clips: clip 'run' is not in the bundle (its clips: idle, walk)") != std::string::npos,
              unknown.err);
    const Run bad_range = run(argv[1], "--bundle '" + bundle + "' --headless --switch-after 5,1");
    CHECK_MSG(bad_range.status == 2 && bad_range.err.find("--switch-after takes LO,HI") != std::string::npos, bad_range.err);
    if (!std::getenv("CROWDVIEW_KEEP_TEST_FILES")) fs::remove_all(work);
    else std::fprintf(stderr, "kept %s\n", work.c_str());
    return check::exit_code();
}
