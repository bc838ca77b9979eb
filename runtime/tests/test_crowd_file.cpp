// The crowd description (crowd_file.h): valid files parse to what they say, every kind of
// mistake is refused with the file, the JSON pointer and what is wrong; shares split exactly;
// the layouts keep characters of different sizes apart; each archetype's LOD distances follow
// its own radius and tile size.
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "check.h"
#include "crowd.h"
#include "crowd_file.h"
#include "crowd_layout.h"

using namespace crowdview;

namespace {

const char* kValid = R"({
  "crowd_format_version": 1,
  "seed": 7,
  "count": 10,
  "archetypes": [
    {"name": "walker", "bundle": "bundles/walker", "share": 2, "play_rate": [0.9, 1.1]},
    {"name": "robot", "published": {"server": "http://127.0.0.1:8000/", "name": "robot", "version": "latest"}, "count": 3},
    {"name": "dancer", "url": "https://cdn.example/bundles/dancer/1.0.0", "share": 1,
     "clips": [{"clip": "walk", "weight": 3}, {"clip": "idle"}], "switch_after_s": [2, 6.5]}
  ],
  "layout": {"kind": "paths", "walk_speed": 1.1},
  "camera": {"kind": "look_at", "eye": [0, 2, 30], "target": [0, 1, 0], "fov_deg": 50}
})";

std::string synthetic_read(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

std::string parse(const std::string& text, CrowdFile* out = nullptr) {
    CrowdFile scratch;
    return parse_crowd_description(text, "/data/crowd.json", out ? out : &scratch);
}

void test_valid() {
    CrowdFile f;
    const std::string error = parse(kValid, &f);
    CHECK_MSG(error.empty(), error);
    CHECK(f.seed == 7 && f.count == 10 && f.archetypes.size() == 3);
    CHECK(f.archetypes[0].source.folder == "/data/bundles/walker");  // relative to the description's folder
    CHECK(f.archetypes[0].share == 2 && f.archetypes[0].play_rate[0] == 0.9f && f.archetypes[0].play_rate[1] == 1.1f);
    CHECK(f.archetypes[1].source.url == "http://127.0.0.1:8000/v1/bundles/robot/latest" && f.archetypes[1].count == 3);
    CHECK(f.archetypes[2].source.is_url() && f.archetypes[2].clips.size() == 2 && f.archetypes[2].clips[0].weight == 3 &&
          f.archetypes[2].clips[1].weight == 1);
    // switch_after_s is optional: unset, crowdview's --switch-after applies.
    CHECK(!f.archetypes[0].has_switch_after && f.archetypes[2].has_switch_after && f.archetypes[2].switch_after_s[0] == 2 &&
          f.archetypes[2].switch_after_s[1] == 6.5f);
    CHECK(f.layout.kind == CrowdLayoutKind::paths && f.layout.walk_speed == 1.1f);
    CHECK(f.camera.kind == CrowdCameraKind::look_at && f.camera.eye == glm::vec3(0, 2, 30) && f.camera.fov_deg == 50);
    // 3 fixed, 7 shared 2:1 -> 4.67 and 2.33 -> 5 and 2 by largest remainder.
    const std::vector<uint64_t> counts = archetype_counts(f);
    CHECK(counts == (std::vector<uint64_t>{5, 3, 2}));

    // Defaults: spot layout, overview camera, version latest.
    CHECK(parse(R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "/b", "count": 4}]})", &f).empty());
    CHECK(f.layout.kind == CrowdLayoutKind::spot && f.camera.kind == CrowdCameraKind::overview && f.seed == 1);
    CHECK(archetype_counts(f) == std::vector<uint64_t>{4});

    // Positions: counts come from the list, archetypes by name.
    CHECK(parse(R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "share": 1}, {"name": "b", "bundle": "b", "share": 1}],
                    "layout": {"kind": "positions", "positions": [{"archetype": "b", "at": [1, 2], "heading_deg": 90},
                                                                  {"archetype": "b", "at": [3, 4]}, {"archetype": "a", "at": [0, 0]}]}})",
                &f).empty());
    CHECK(archetype_counts(f) == (std::vector<uint64_t>{1, 2}));
    CHECK(f.layout.positions[0].archetype == 1 && std::fabs(f.layout.positions[0].heading_rad - 1.5707964f) < 1e-5f);
    // A positions layout asked for a dummy share per archetype, and the error on a count said to leave
    // it out, which failed in turn: the entries count, so neither is needed and a count that agrees passes.
    CHECK(parse(R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a"}, {"name": "b", "bundle": "b", "count": 2}],
                    "layout": {"kind": "positions", "positions": [{"archetype": "b", "at": [1, 2]}, {"archetype": "b", "at": [3, 4]},
                                                                  {"archetype": "a", "at": [0, 0]}]}})",
                &f).empty());
    CHECK(archetype_counts(f) == (std::vector<uint64_t>{1, 2}));
    // Scatter.
    CHECK(parse(R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 2}],
                    "layout": {"kind": "scatter", "area": {"min": [-5, -5], "max": [5, 10]}}})", &f).empty());
    CHECK(f.layout.area_min == glm::vec2(-5, -5) && f.layout.area_max == glm::vec2(5, 10));
}

// Each bad file: the message names the file, the pointer and the problem, on one line.
void test_errors() {
    const std::string one = R"("archetypes": [{"name": "a", "bundle": "a", "count": 1}])";
    struct Case {
        std::string text, pointer, words;
    };
    const std::vector<Case> cases = {
        {"{", "", "not JSON"},
        {"[]", "/:", "must be an object"},
        {R"({"archetypes": []})", "/:", "crowd_format_version"},
        {R"({"crowd_format_version": 2, )" + one + "}", "/crowd_format_version", "version 2"},
        {R"({"crowd_format_version": 1, "colour": 1, )" + one + "}", "/colour", "unknown key"},
        {R"({"crowd_format_version": 1, "archetypes": []})", "/archetypes", "non-empty"},
        {R"({"crowd_format_version": 1, "seed": -1, )" + one + "}", "/seed", "whole number"},
        {R"({"crowd_format_version": 1, "count": 0, )" + one + "}", "/count", "whole number"},
        {R"({"crowd_format_version": 1, "archetypes": [{"bundle": "a", "count": 1}]})", "/archetypes/0", "name"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "count": 1}]})", "/archetypes/0", "exactly one of \"bundle\""},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "url": "http://x", "count": 1}]})", "/archetypes/0", "exactly one"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "url": "bundles/a", "count": 1}]})", "/archetypes/0/url", "URL"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "published": {"server": "http://h", "name": "Bad Name"}, "count": 1}]})",
         "/archetypes/0/published/name", "bundle name"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "published": {"server": "http://h", "name": "a", "version": "/x"}, "count": 1}]})",
         "/archetypes/0/published/version", "version"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "published": {"name": "a"}, "count": 1}]})", "/archetypes/0/published", "server"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a"}]})", "/archetypes/0", "\"count\" and \"share\""},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "share": 1}]})", "/archetypes/0", "exactly one of \"count\""},
        {R"({"crowd_format_version": 1, "count": 5, "archetypes": [{"name": "a", "bundle": "a", "share": -2}]})", "/archetypes/0/share", "> 0"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1.5}]})", "/archetypes/0/count", "whole number"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "share": 1}]})", "/:", "needs \"count\""},
        {R"({"crowd_format_version": 1, "count": 2, "archetypes": [{"name": "a", "bundle": "a", "count": 3}]})", "/count", "add up to 3"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1}, {"name": "a", "bundle": "b", "count": 1}]})",
         "/archetypes/1/name", "used twice"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "clips": []}]})", "/archetypes/0/clips", "non-empty"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "clips": [{"clip": "w", "weight": 0}]}]})",
         "/archetypes/0/clips/0/weight", "> 0"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "play_rate": [1.2, 0.8]}]})",
         "/archetypes/0/play_rate", "low <= high"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "play_rate": [0.1, 1]}]})",
         "/archetypes/0/play_rate/0", "[0.25, 4]"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "play_rate": 1}]})",
         "/archetypes/0/play_rate", "array of 2"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "switch_after_s": [6, 2]}]})",
         "/archetypes/0/switch_after_s", "low <= high"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 1, "switch_after_s": [-1, 2]}]})",
         "/archetypes/0/switch_after_s/0", "[0, 86400]"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "layout": {"kind": "spiral"}})", "/layout/kind", "spot, paths"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "layout": {"kind": "spot", "walk_speed": 1}})", "/layout/walk_speed", "unknown key"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "layout": {"kind": "paths", "walk_speed": 0}})", "/layout/walk_speed", "> 0"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "layout": {"kind": "scatter"}})", "/layout", "area"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "layout": {"kind": "scatter", "area": {"min": [0, 0], "max": [0, 5]}}})", "/layout/area",
         "max must exceed min"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "layout": {"kind": "scatter", "area": {"min": [0], "max": [1, 1]}}})",
         "/layout/area/min", "array of 2"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "share": 1}], "layout": {"kind": "positions", "positions": []}})",
         "/layout/positions", "non-empty"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "share": 1}], "layout": {"kind": "positions", "positions": [{"archetype": "b", "at": [0, 0]}]}})",
         "/layout/positions/0/archetype", "names no archetype"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "share": 1}], "layout": {"kind": "positions", "positions": [{"archetype": "a", "at": [0, "x"]}]}})",
         "/layout/positions/0/at/1", "number"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a", "count": 2}], "layout": {"kind": "positions", "positions": [{"archetype": "a", "at": [0, 0]}]}})",
         "/archetypes/0/count", "is 2 but /layout/positions places 1 of \"a\": with a positions layout an archetype's count is its number of entries; leave \"count\" out"},
        {R"({"crowd_format_version": 1, "archetypes": [{"name": "a", "bundle": "a"}], "layout": {"kind": "scatter", "area": {"min": [0, 0], "max": [1, 1]}}})",
         "/archetypes/0", "a positions layout, which counts each archetype's entries, takes neither"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "camera": {"kind": "drone"}})", "/camera/kind", "overview, street or look_at"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "camera": {"kind": "look_at", "eye": [0, 1, 2]}})", "/camera", "eye\" and \"target"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "camera": {"kind": "look_at", "eye": [0, 1, 2], "target": [0, 1, 2]}})", "/camera/target",
         "differ"},
        {R"({"crowd_format_version": 1, )" + one + R"(, "camera": {"fov_deg": 180}})", "/camera/fov_deg", "<= 170"},
    };
    for (const Case& c : cases) {
        const std::string error = parse(c.text);
        const std::string prefix = "/data/crowd.json: " + c.pointer;
        CHECK_MSG(error.rfind(prefix, 0) == 0 && error.find(c.words) != std::string::npos && error.find('\n') == std::string::npos,
                  "'" + c.text + "' gave '" + error + "', wanted '" + prefix + "...' with '" + c.words + "'");
    }
    // Every truncation of a valid file is refused, never a crash.
    const std::string valid = kValid;
    for (size_t n = 0; n < valid.size(); ++n) CHECK_MSG(!parse(valid.substr(0, n)).empty(), std::to_string(n));
    CrowdFile f;
    CHECK(load_crowd_description("/nonexistent/crowd.json", &f).find("cannot read") != std::string::npos);
}

ArchetypeTraits traits(uint64_t count, float radius) {
    ArchetypeTraits t;
    t.count = count;
    t.spacing = crowd_spacing(radius);
    t.variations = 3, t.outfits = 4, t.cycle_seconds = 1;
    return t;
}

// The closest two characters of any two archetypes stand at least min_separation apart.
float worst_overlap(const std::vector<Crowd>& crowds, const std::vector<ArchetypeTraits>& t, size_t* total) {
    float worst = INFINITY;  // smallest distance / allowed
    *total = 0;
    for (size_t a = 0; a < crowds.size(); ++a) {
        *total += crowds[a].characters.size();
        for (size_t b = a; b < crowds.size(); ++b)
            for (size_t i = 0; i < crowds[a].characters.size(); ++i)
                for (size_t j = a == b ? i + 1 : 0; j < crowds[b].characters.size(); ++j) {
                    const glm::vec3 d = crowds[a].characters[i].start - crowds[b].characters[j].start;
                    worst = std::min(worst, glm::length(d) / min_separation(t[a].spacing, t[b].spacing));
                }
    }
    return worst;
}

void test_layouts() {
    // Four sizes: a child, two adults and a 4 m robot (impostor radii 0.6, 0.9, 1.0, 2.2 m).
    const std::vector<ArchetypeTraits> t = {traits(120, 0.9f), traits(40, 2.2f), traits(80, 0.6f), traits(60, 1.0f)};
    CHECK(t[1].spacing > 3.5f && t[0].spacing == 1.6f);
    for (CrowdLayoutKind kind : {CrowdLayoutKind::spot, CrowdLayoutKind::paths, CrowdLayoutKind::scatter}) {
        CrowdFile f;
        f.seed = 3;
        f.layout.kind = kind;
        f.layout.area_min = glm::vec2(-10, -10), f.layout.area_max = glm::vec2(10, 10);  // scatter: too small for all 300
        std::string note;
        const std::vector<Crowd> crowds = lay_out_crowd(f, t, &note);
        size_t total = 0;
        const float worst = worst_overlap(crowds, t, &total);
        CHECK_MSG(worst >= 1.0f, "closest pair at " + std::to_string(worst) + " of its allowed distance");
        if (kind == CrowdLayoutKind::scatter) {
            CHECK_MSG(total < 300 && note.find("did not fit") != std::string::npos, note);
            for (const Crowd& c : crowds)
                for (const Character& ch : c.characters) CHECK(std::fabs(ch.start.x) <= 10 && std::fabs(ch.start.z) <= 10);
        } else {
            CHECK(total == 300 && note.empty());
            for (size_t a = 0; a < t.size(); ++a) CHECK(crowds[a].characters.size() == t[a].count);
            // Not spread needlessly thin: the square is within twice the ground the grid would give.
            double ground = 0;
            for (const ArchetypeTraits& x : t) ground += double(x.count) * x.spacing * x.spacing;
            CHECK(crowds[0].half_extent <= std::sqrt(ground));
        }
        CHECK(crowds[0].layout == (kind == CrowdLayoutKind::paths ? Layout::paths : Layout::on_the_spot));
        for (size_t a = 0; a < t.size(); ++a) {
            CHECK(crowds[a].half_extent == crowds[0].half_extent);
            for (const Character& ch : crowds[a].characters) CHECK(ch.variation < 3 && ch.outfit < 4);
        }
        // Deterministic.
        const std::vector<Crowd> again = lay_out_crowd(f, t, nullptr);
        CHECK(again[1].characters.size() == crowds[1].characters.size() &&
              (again[1].characters.empty() || again[1].characters.back().start == crowds[1].characters.back().start));
    }
    // One archetype on the spot is make_crowd's grid, exactly as --bundle lays it out.
    CrowdFile f;
    f.seed = 5;
    const std::vector<Crowd> one = lay_out_crowd(f, {traits(50, 0.9f)}, nullptr);
    CrowdDesc desc;
    desc.count = 50, desc.seed = 5, desc.spacing = 1.6f;
    const Crowd grid = make_crowd(desc, 3, 4, 1);
    CHECK(one[0].characters.size() == 50 && one[0].characters[17].start == grid.characters[17].start);
    // Positions: as given, an archetype left out (count 0) drops its entries; play rates in range.
    f.layout.kind = CrowdLayoutKind::positions;
    f.layout.positions = {{0, 1, 2, 0.5f}, {1, 3, 4, 0}, {0, -1, -2, 0}};
    std::vector<ArchetypeTraits> two = {traits(2, 0.9f), traits(0, 0.9f)};
    two[0].play_rate[0] = 0.8f, two[0].play_rate[1] = 1.2f;
    const std::vector<Crowd> placed = lay_out_crowd(f, two, nullptr);
    CHECK(placed[0].characters.size() == 2 && placed[1].characters.empty());
    CHECK(placed[0].characters[0].start == glm::vec3(1, 0, 2) && placed[0].characters[0].heading == 0.5f);
    for (const Character& c : placed[0].characters) CHECK(c.rate >= 0.8f && c.rate <= 1.2f);
    CHECK(placed[0].half_extent == 2);
}

// Each archetype's LOD distances follow its own radius and tile: twice the radius, twice the
// distance; twice the tile, half. A 4 m robot turns impostor further away than a person.
void test_lod_per_archetype() {
    Camera camera;
    CharacterModel person, robot, fine;
    person.radius = 0.9f, person.tile_size = 64, person.has_low = true;
    robot = person, robot.radius = 2.2f;
    fine = person, fine.tile_size = 128;
    const LodRule rp = lod_rule_for(person, camera, 720), rr = lod_rule_for(robot, camera, 720), rf = lod_rule_for(fine, camera, 720);
    CHECK_NEAR(rr.impostor_distance / rp.impostor_distance, 2.2 / 0.9, 1e-4);
    CHECK_NEAR(rf.impostor_distance / rp.impostor_distance, 0.5, 1e-5);
    // At a distance between the two, the person is an impostor and the robot a mesh.
    const float d = 0.5f * (rp.impostor_distance + rr.impostor_distance);
    CHECK(lod_without_history(d, rp) == Lod::impostor && lod_without_history(d, rr) != Lod::impostor);
    // Play rate: twice the rate, twice the frames.
    CHECK(cycle_frame(2.0f * 0.5f, 0, 8, 8) == 8 % 8 && cycle_frame(1.0f * 0.5f, 0, 8, 8) == 4);
}

// The shared vectors (shared_formats/vectors/crowd-v1), which the schema test reads too: good
// files parse, each bad one is refused at the pointer expect.json names.
void test_shared_vectors() {
    const std::string dir = CROWDVIEW_VECTORS_DIR "/crowd-v1";
    int good = 0;
    for (const auto& entry : std::filesystem::directory_iterator(dir + "/good")) {
        CrowdFile f;
        const std::string error = load_crowd_description(entry.path().string(), &f);
        CHECK_MSG(error.empty(), error);
        ++good;
    }
    CHECK(good >= 3);
    const nlohmann::json expect = nlohmann::json::parse(synthetic_read(dir + "/bad/expect.json"), nullptr, false);
    CHECK(expect.is_object() && expect.size() >= 8);
    if (!expect.is_object()) return;
    for (auto it = expect.begin(); it != expect.end(); ++it) {
        CrowdFile f;
        const std::string path = dir + "/bad/" + it.key() + ".json";
        const std::string error = load_crowd_description(path, &f);
        CHECK_MSG(error.rfind(path + ": " + it.value().get<std::string>() + ": ", 0) == 0, it.key() + ": " + error);
    }
}

}  // namespace

int main() {
    test_shared_vectors();
    test_valid();
    test_errors();
    test_layouts();
    test_lod_per_archetype();
    return check::exit_code();
}
