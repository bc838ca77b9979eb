// The impostor blend weights against runtime/tests/data/view_blend_vectors.json, the answers the
// bake's numpy copy (services/crowdbake/bake/impostor_blend.py) is tested against as well.
#include <cmath>
#include <fstream>
#include <map>
#include <sstream>

#include <nlohmann/json.hpp>

#include "check.h"
#include "crowd.h"
#include "view_blend.h"

#ifndef CROWDVIEW_TEST_DATA_DIR
#error "CMake sets CROWDVIEW_TEST_DATA_DIR to runtime/tests/data"
#endif

using namespace crowdview;
using nlohmann::json;

int main() {
    std::ifstream in(std::string(CROWDVIEW_TEST_DATA_DIR) + "/view_blend_vectors.json");
    CHECK_MSG(in.good(), "view_blend_vectors.json is readable");
    if (!in.good()) return check::exit_code();
    std::stringstream text;
    text << in.rdbuf();
    const json vectors = json::parse(text.str());
    const double tolerance = vectors["tolerance"].get<double>();
    const auto azimuths = vectors["azimuths_deg"].get<std::vector<float>>();
    const auto elevations = vectors["elevations_deg"].get<std::vector<float>>();

    for (const json& c : vectors["views"]) {
        const std::string why = c["why"].get<std::string>();
        const auto d = c["to_camera"].get<std::vector<float>>();
        const glm::vec2 angles = view_angles_deg({d[0], d[1], d[2]}, c["heading"].get<float>());
        const double azimuth_error = std::fmod(angles.x - c["angles_deg"][0].get<double>() + 540.0, 360.0) - 180.0;
        CHECK_MSG(std::fabs(azimuth_error) < tolerance, why + ": azimuth");
        CHECK_MSG(std::fabs(angles.y - c["angles_deg"][1].get<double>()) < tolerance, why + ": elevation");
        const ViewWeights w = blend_view_weights(angles, azimuths, elevations);
        // Tiles with weight: the same set, each with its weight (order and unused slots may differ).
        std::map<uint32_t, double> got, expected;
        for (int i = 0; i < 4; ++i) {
            if (w.weights[i] > tolerance) got[w.tiles[i]] += w.weights[i];
            if (c["weights"][i].get<double>() > tolerance) expected[c["tiles"][i].get<uint32_t>()] += c["weights"][i].get<double>();
        }
        CHECK_MSG(got.size() == expected.size(), why + ": tiles");
        for (const auto& [tile, weight] : expected)
            CHECK_MSG(got.count(tile) && std::fabs(got[tile] - weight) < tolerance, why + ": tile " + std::to_string(tile));
    }
    for (const json& c : vectors["frames"]) {
        const std::string why = c["why"].get<std::string>();
        const FrameWeights f = blend_frame_weights(c["frame"].get<uint32_t>(), c["frame_indices"].get<std::vector<uint32_t>>(),
                                                   c["frame_count"].get<uint32_t>());
        CHECK_MSG(f.layers[0] == c["layers"][0].get<uint32_t>() && f.layers[1] == c["layers"][1].get<uint32_t>(), why + ": layers");
        CHECK_MSG(std::fabs(f.weight - c["weight"].get<double>()) < tolerance, why + ": weight");
    }
    for (const json& c : vectors["cycle_frames"]) {
        const uint32_t frame = cycle_frame(c["seconds"].get<float>(), c["phase"].get<float>(), c["frames_per_second"].get<float>(),
                                           c["frame_count"].get<uint32_t>());
        CHECK_MSG(frame == c["frame"].get<uint32_t>(), c["why"].get<std::string>());
    }
    return check::exit_code();
}
