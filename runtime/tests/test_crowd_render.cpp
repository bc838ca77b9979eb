// `crowdview --crowd FILE` headless: four synthetic archetypes of different sizes and impostor
// tiles, each placed at a high-mesh, a low-mesh and an impostor distance of its own, are all
// drawn at each of their LODs; the report gives counts per archetype and LOD and GPU memory per
// archetype; a fifth archetype whose bundle is missing stops alone, with a message; 64 archetypes
// naming one bundle share one load and one upload.
//   test_crowd_render CROWDVIEW
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
#include "renderer.h"
#include "synthetic_bundle.h"

namespace fs = std::filesystem;

namespace {

using synthetic::Run;

Run run(const std::string& crowdview, const std::string& args) { return synthetic::run_crowdview(crowdview, args + " >/dev/null"); }

struct Archetype {
    const char* name;
    float scale;
    uint32_t tile;
};

// 320 x 240 keeps llvmpipe quick; the LOD distances below are for this height.
constexpr int kWidth = 320, kHeight = 240;
constexpr float kEyeHeight = 1.2f;

// A crowd naming one bundle from many archetypes. Regression: 64 archetypes naming one bundle loaded
// and uploaded it 64 times (4.3 GB for a real bundle). It is loaded and uploaded once, each archetype
// keeping its own count, and draws the very pixels of two separately uploaded copies.
void check_shared_bundle(const std::string& crowdview, const std::string& work, const std::string& size) {
    nlohmann::json many = nlohmann::json::array();
    for (int k = 0; k < 64; ++k)  // the folder spelled three ways: one bundle all the same
        many.push_back({{"name", "p" + std::to_string(k)}, {"bundle", k % 3 == 0 ? "person" : k % 3 == 1 ? "./person" : "person/"},
                        {"count", 1 + k % 2}});
    std::ofstream(work + "/many.json") << nlohmann::json({{"crowd_format_version", 1}, {"archetypes", many}}).dump();
    const std::string report_file = work + "/many-report.json";
    const Run r = run(crowdview, "--crowd '" + work + "/many.json' --headless --impostor-blend off" + size + " --report '" + report_file + "'");
    CHECK_MSG(r.status == 0 && r.err.find("loaded once for 64 archetypes ('p0', 'p1', 'p2' and 61 more)") != std::string::npos, r.err);
    const nlohmann::json report = nlohmann::json::parse(synthetic::read_text(report_file), nullptr, false);
    CHECK(!report.is_discarded() && report["archetypes"].size() == 64);
    if (report.is_discarded() || report["archetypes"].size() != 64) return;
    const uint64_t one = report["archetypes"][0]["gpu_memory_bytes"]["total"].get<uint64_t>();
    CHECK_MSG(one > 0 && report["gpu_memory_bytes_total"].get<uint64_t>() == one, report["gpu_memory_bytes_total"].dump());
    for (size_t k = 1; k < 64; ++k) {
        const nlohmann::json& a = report["archetypes"][k];
        CHECK_MSG(a["gpu_memory_bytes"]["total"] == 0 && a["shares_uploads_of"] == "p0" && a["characters"] == 1 + k % 2, a.dump());
    }
    // Two archetypes drawing one upload through their own instance buffers, against two uploads
    // (a copy under another version, so not the same bundle): the same picture.
    const std::string copy = work + "/person-copy";
    fs::copy(work + "/person", copy, fs::copy_options::recursive);
    nlohmann::json manifest = nlohmann::json::parse(synthetic::read_text(copy + "/manifest.json"));
    manifest["version"] = "9.9.9";
    std::ofstream(copy + "/manifest.json") << manifest.dump();
    std::string pngs[2];
    for (int twice = 0; twice < 2; ++twice) {
        const nlohmann::json pair = {
            {"crowd_format_version", 1},
            {"archetypes", {{{"name", "a"}, {"bundle", "person"}, {"share", 1}}, {{"name", "b"}, {"bundle", twice ? "person-copy" : "person"}, {"share", 1}}}},
            {"layout", {{"kind", "positions"}, {"positions", {{{"archetype", "a"}, {"at", {-0.6, -3}}}, {{"archetype", "b"}, {"at", {0.6, -3}}},
                                                              {{"archetype", "a"}, {"at", {-4, -60}}}, {{"archetype", "b"}, {"at", {4, -60}}}}}}},
            {"camera", {{"kind", "look_at"}, {"eye", {0, kEyeHeight, 0}}, {"target", {0, kEyeHeight, -10}}}}};
        std::ofstream(work + "/pair.json") << pair.dump();
        pngs[twice] = work + "/pair" + std::to_string(twice) + ".png";
        const Run p = run(crowdview, "--crowd '" + work + "/pair.json' --headless --impostor-blend off" + size + " --screenshot '" + pngs[twice] + "'");
        CHECK_MSG(p.status == 0 && (p.err.find("loaded once for 2 archetypes") != std::string::npos) == !twice, p.err);
    }
    int w = 0, h = 0;
    std::vector<uint8_t> shared, separate;
    CHECK(crowdview::read_png(pngs[0], &w, &h, &shared) && crowdview::read_png(pngs[1], &w, &h, &separate));
    CHECK_MSG(!shared.empty() && shared == separate, "one upload drawn twice differs from two uploads");
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: test_crowd_render CROWDVIEW\n");
        return 2;
    }
    const std::string work = synthetic::temp_dir("crowd-render");
    // A child, a person with a coarse tile, a person with a fine tile, a 4 m robot.
    const Archetype archetypes[] = {{"child", 0.6f, 32}, {"person", 1.0f, 32}, {"fine", 1.0f, 64}, {"giant", 2.2f, 32}};
    nlohmann::json positions = nlohmann::json::array(), list = nlohmann::json::array();
    float furthest = 0;
    for (int k = 0; k < 4; ++k) {
        synthetic::Options o;
        o.scale = archetypes[k].scale;
        o.tile_size = archetypes[k].tile;
        o.name = archetypes[k].name;
        o.frames = 4;
        o.frame_indices = {0, 2};
        o.azimuths_deg = {0, 90, 180, 270};
        const std::string dir = work + "/" + archetypes[k].name;
        const std::string error = synthetic::write_bundle(dir, o);
        CHECK_MSG(error.empty(), error);
        const nlohmann::json manifest = nlohmann::json::parse(synthetic::read_text(dir + "/manifest.json"));
        const float radius = manifest["impostor"]["bounds"]["radius"].get<float>();
        // Its own 1:1 distance; the low mesh takes over at half of it (LodRule::low_fraction).
        const float switch_m = crowdview::impostor_switch_distance(glm::radians(45.0f), kHeight, radius, archetypes[k].tile);
        list.push_back({{"name", archetypes[k].name}, {"bundle", archetypes[k].name}, {"share", 1}});
        // Depths (along the view, to the bounds centre) of 0.3, 0.75 and 1.5 switch distances: high, low, impostor.
        for (float fraction : {0.3f, 0.75f, 1.5f}) {
            const float depth = fraction * switch_m;
            // Lanes across the view, each archetype its own, within the view's half width at that depth.
            const float lane = (float(k) - 1.5f) * 0.22f * depth;
            // The camera looks along -Z, level: a character's depth is -z (its centre sits above the feet only).
            positions.push_back({{"archetype", archetypes[k].name}, {"at", {lane, -depth}}, {"heading_deg", 30 * k}});
            furthest = std::max(furthest, depth);
        }
    }
    list.push_back({{"name", "missing"}, {"bundle", "no-such-bundle"}, {"share", 1}});
    positions.push_back({{"archetype", "missing"}, {"at", {0, -5}}});
    const nlohmann::json crowd = {{"crowd_format_version", 1},
                                  {"seed", 2},
                                  {"archetypes", list},
                                  {"layout", {{"kind", "positions"}, {"positions", positions}}},
                                  {"camera", {{"kind", "look_at"}, {"eye", {0, kEyeHeight, 0}}, {"target", {0, kEyeHeight, -10}}}}};
    const std::string crowd_file = work + "/crowd.json";
    std::ofstream(crowd_file) << crowd.dump(2);

    const std::string report_file = work + "/report.json", png = work + "/crowd.png";
    const std::string size = " --width " + std::to_string(kWidth) + " --height " + std::to_string(kHeight);
    const Run r = run(argv[1], "--crowd '" + crowd_file + "' --allow-missing --headless --frames 2" + size +
                                   " --impostor-blend off --report '" + report_file + "' --screenshot '" + png + "'");
    if (r.status == 3) {
        std::fprintf(stderr, "SKIP: %s", r.err.c_str());
        fs::remove_all(work);
        return 77;
    }
    CHECK_MSG(r.status == 0, r.err);
    CHECK_MSG(r.err.find("archetype 'missing': bundle refused: ") != std::string::npos, r.err);
    CHECK_MSG(r.err.find("archetype 'giant': high 1 | low 1 | impostor 1 | culled 0") != std::string::npos, r.err);
    const nlohmann::json report = nlohmann::json::parse(synthetic::read_text(report_file), nullptr, false);
    CHECK(!report.is_discarded());
    if (!report.is_discarded()) {
        CHECK(report["archetypes"].size() == 4);
        CHECK(report["refused"].size() == 1 && report["refused"][0]["name"] == "missing");
        for (size_t k = 0; k < report["archetypes"].size() && k < 4; ++k) {
            const nlohmann::json& a = report["archetypes"][k];
            CHECK(a["name"] == archetypes[k].name && a["characters"] == 3);
            // Each archetype at each of its LODs, none culled.
            for (const char* lod : {"high", "low", "impostor"}) CHECK_MSG(a["lod_counts"][lod] == 1, a.dump());
            CHECK_MSG(a["lod_counts"]["culled"] == 0, a.dump());
            CHECK_MSG(a["impostor_blend"] == "off", a.dump());  // the blend that ran, as --impostor-blend asked
            for (const char* part : {"meshes", "textures", "impostors"}) CHECK_MSG(a["gpu_memory_bytes"][part].get<uint64_t>() > 0, a.dump());
            CHECK(a["gpu_memory_bytes"]["total"].get<uint64_t>() == a["gpu_memory_bytes"]["meshes"].get<uint64_t>() +
                                                                    a["gpu_memory_bytes"]["textures"].get<uint64_t>() +
                                                                    a["gpu_memory_bytes"]["impostors"].get<uint64_t>());
        }
        const nlohmann::json& as = report["archetypes"];
        if (as.size() == 4) {
            // LOD distances follow each archetype's own size and tile.
            CHECK(as[3]["impostor_switch_m"].get<float>() > as[1]["impostor_switch_m"].get<float>() * 2);
            CHECK(as[0]["impostor_switch_m"].get<float>() < as[1]["impostor_switch_m"].get<float>());
            CHECK_NEAR(as[2]["impostor_switch_m"].get<float>(), 0.5f * as[1]["impostor_switch_m"].get<float>(), 1e-3);
            // A 64-texel tile takes four times the impostor memory of a 32-texel one (same views and frames).
            CHECK(as[2]["gpu_memory_bytes"]["impostors"].get<uint64_t>() > 3 * as[1]["gpu_memory_bytes"]["impostors"].get<uint64_t>());
            CHECK(as[3]["spacing_m"].get<float>() > as[1]["spacing_m"].get<float>());
        }
        CHECK(report["cpu_build_ms_per_frame"].get<double>() >= 0 && report["frames"] == 2);
    }
    // The picture shows more than the sky.
    int w = 0, h = 0;
    std::vector<uint8_t> rgba;
    CHECK(crowdview::read_png(png, &w, &h, &rgba) && w == kWidth && h == kHeight);

    check_shared_bundle(argv[1], work, size);

    // Without --allow-missing the missing archetype stops the crowd: exit 1, before any picture.
    const std::string strict_png = work + "/strict.png";
    const Run strict = run(argv[1], "--crowd '" + crowd_file + "' --headless --impostor-blend off" + size + " --screenshot '" + strict_png + "'");
    CHECK_MSG(strict.status == 1 && strict.err.find("archetype 'missing': bundle refused: ") != std::string::npos &&
                  strict.err.find("1 of 5 archetypes of ") != std::string::npos && !fs::exists(strict_png),
              strict.err);
    // --allow-missing goes with --crowd only.
    Run lone = run(argv[1], "--bundle '" + work + "/child' --allow-missing --headless");
    CHECK_MSG(lone.status == 2 && lone.err.find("--allow-missing goes with --crowd") != std::string::npos, lone.err);
    // A clip mix naming a clip the bundle lacks is the description's error: exit 1, like any bad description.
    std::ofstream(work + "/clip.json") << R"({"crowd_format_version": 1, "archetypes": [{"name": "c", "bundle": "child", "count": 1, "clips": [{"clip": "run"}]}]})";
    Run clip = run(argv[1], "--crowd '" + work + "/clip.json' --headless");
    CHECK_MSG(clip.status == 1 && clip.err.find("archetype 'c': clip 'run' is not in the bundle") != std::string::npos, clip.err);
    // A description whose every bundle is refused stops with one line and exit 1, --allow-missing or not.
    std::ofstream(work + "/none.json") << R"({"crowd_format_version": 1, "archetypes": [{"name": "x", "bundle": "nowhere", "count": 3}]})";
    Run none = run(argv[1], "--crowd '" + work + "/none.json' --headless --allow-missing");
    CHECK_MSG(none.status == 1 && none.err.find("no archetype of") != std::string::npos, none.err);
    // A bad description: the file, the pointer, the problem; exit 1.
    std::ofstream(work + "/bad.json") << R"({"crowd_format_version": 1, "archetypes": [{"name": "x", "bundle": "a", "count": 0}]})";
    Run bad = run(argv[1], "--crowd '" + work + "/bad.json' --headless");
    CHECK_MSG(bad.status == 1 && bad.err.find("bad.json: /archetypes/0/count: must be a whole number") != std::string::npos, bad.err);
    Run mixed = run(argv[1], "--crowd '" + work + "/bad.json' --count 4");
    CHECK_MSG(mixed.status == 2 && mixed.err.find("go in the --crowd description") != std::string::npos, mixed.err);
    if (!std::getenv("CROWDVIEW_KEEP_TEST_FILES")) fs::remove_all(work);
    else std::fprintf(stderr, "kept %s\n", work.c_str());
    return check::exit_code();
}
