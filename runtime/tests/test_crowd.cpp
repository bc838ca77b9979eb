// The crowd without GL: the 1:1 pixel-to-texel LOD rule and its hysteresis, impostor view
// selection in the character's frame, view and frame blending weights, culling, determinism
// and frame selection.
#include <cmath>
#include <cstring>

#include <glm/gtc/matrix_transform.hpp>

#include "check.h"
#include "crowd.h"

using namespace crowdview;

namespace {

const std::vector<float> kAzimuths = {0, 30, 60, 90, 120, 150, 180, 210, 240, 270, 300, 330};
const std::vector<float> kElevations = {0, 30};

glm::vec3 direction(float azimuth_deg, float elevation_deg) {
    const float a = glm::radians(azimuth_deg), e = glm::radians(elevation_deg);
    return glm::vec3(std::sin(a) * std::cos(e), std::sin(e), std::cos(a) * std::cos(e));
}

void test_switch_distance() {
    // At the switch distance one pixel spans exactly one impostor texel.
    for (float fov_deg : {30.0f, 45.0f, 60.0f, 90.0f})
        for (float height : {240.0f, 720.0f, 2160.0f})
            for (uint32_t tile : {32u, 64u, 256u}) {
                const float fov = glm::radians(fov_deg), radius = 0.9f;
                const float d = impostor_switch_distance(fov, height, radius, tile);
                const float pixel = 2.0f * d * std::tan(0.5f * fov) / height;
                const float texel = 2.0f * radius / float(tile);
                CHECK_NEAR(pixel / texel, 1.0, 1e-5);
            }
    // A worked example: fov 60, 1000 px, radius 1 m, 128 texels: 1000 / (128 tan 30) = 13.5316 m.
    CHECK_NEAR(impostor_switch_distance(glm::radians(60.0f), 1000, 1, 128), 13.5316, 1e-3);
    // Twice the tile resolution halves the distance; twice the viewport doubles it.
    const float base = impostor_switch_distance(0.8f, 720, 1, 64);
    CHECK_NEAR(impostor_switch_distance(0.8f, 720, 1, 128), base / 2, 1e-4);
    CHECK_NEAR(impostor_switch_distance(0.8f, 1440, 1, 64), base * 2, 1e-4);
    CHECK(impostor_switch_distance(0.8f, 720, 1, 0) == 0);
}

void test_lod_levels() {
    LodRule rule;
    rule.impostor_distance = 20;
    CHECK(lod_without_history(5, rule) == Lod::high);
    CHECK(lod_without_history(9.99f, rule) == Lod::high);
    CHECK(lod_without_history(10, rule) == Lod::low);
    CHECK(lod_without_history(19.99f, rule) == Lod::low);
    CHECK(lod_without_history(20, rule) == Lod::impostor);
    CHECK(lod_without_history(500, rule) == Lod::impostor);
    rule.has_low = false;
    CHECK(lod_without_history(15, rule) == Lod::high);
    CHECK(lod_without_history(25, rule) == Lod::impostor);
    CHECK(select_lod(15, Lod::low, rule) == Lod::high);  // no low mesh: history of one is ignored

    // Hysteresis: hovering around a boundary keeps the level; no flicker.
    rule.has_low = true;
    rule.hysteresis = 0.05f;
    Lod lod = Lod::low;
    int switches = 0;
    for (int i = 0; i < 200; ++i) {
        const float d = 20.0f * (1.0f + 0.04f * std::sin(0.7f * i));  // within +-4 % of the switch
        const Lod next = select_lod(d, lod, rule);
        switches += next != lod;
        lod = next;
    }
    CHECK_MSG(switches <= 1, std::to_string(switches) + " switches while hovering");
    // Walking away switches at boundary * (1 + h); walking back at the boundary itself.
    lod = Lod::high;
    float out_at = 0, back_at = 0;
    for (float d = 1; d < 40; d += 0.01f) {
        const Lod next = select_lod(d, lod, rule);
        if (lod == Lod::low && next == Lod::impostor) out_at = d;
        lod = next;
    }
    for (float d = 40; d > 1; d -= 0.01f) {
        const Lod next = select_lod(d, lod, rule);
        if (lod == Lod::impostor && next == Lod::low) back_at = d;
        lod = next;
    }
    CHECK_NEAR(out_at, 21.0, 0.02);
    CHECK_NEAR(back_at, 20.0, 0.02);
    CHECK(select_lod(3, Lod::impostor, rule) == Lod::high);   // a jump skips levels
    CHECK(select_lod(80, Lod::high, rule) == Lod::impostor);

    // The paper's rule holds at every step: an impostor is never drawn nearer than 1:1.
    Rng rng(7);
    lod = Lod::high;
    float d = 15;
    bool magnified = false;
    for (int i = 0; i < 5000; ++i) {
        d = glm::clamp(d + rng.uniform(-1.5f, 1.5f), 1.0f, 40.0f);
        lod = select_lod(d, lod, rule);
        magnified |= lod == Lod::impostor && d < rule.impostor_distance;
    }
    CHECK(!magnified);
}

void test_view_selection() {
    auto view = [](glm::vec3 to_camera, float heading_deg) {
        return select_view(to_camera, glm::radians(heading_deg), kAzimuths, kElevations);
    };
    // Heading 0: the character faces +Z; a camera on +Z sees its front (azimuth 0), on +X its left (90).
    CHECK(view(direction(0, 0), 0).azimuth == 0);
    CHECK(view(direction(90, 0), 0).azimuth == 3);
    CHECK(view(direction(180, 0), 0).azimuth == 6);
    CHECK(view(direction(270, 0), 0).azimuth == 9);
    // Turned to face +X, the camera on +X sees the front; one on -Z sees its left side.
    CHECK(view(direction(90, 0), 90).azimuth == 0);
    CHECK(view(glm::vec3(0, 0, -1), 90).azimuth == 3);
    // Every azimuth and heading: the chosen view is the baked one nearest the relative angle.
    for (float heading = 0; heading < 360; heading += 17)
        for (float az = 0; az < 360; az += 7) {
            const ImpostorView v = view(direction(az + heading, 10) * 5.0f, heading);
            const float d = std::fmod(std::fabs(az - kAzimuths[v.azimuth]) + 360.0f, 360.0f);
            CHECK_MSG(std::min(d, 360.0f - d) <= 15.0f + 1e-3f, "az " + std::to_string(az) + " heading " + std::to_string(heading));
        }
    // Wrap-around: 350 degrees is nearer 0 than 330.
    CHECK(view(direction(350, 0), 0).azimuth == 0);
    CHECK(view(direction(344, 0), 0).azimuth == 11);
    // Elevation: nearest row, clamped to the rows there are.
    CHECK(view(direction(0, 10), 0).elevation == 0);
    CHECK(view(direction(0, 20), 0).elevation == 1);
    CHECK(view(direction(0, 85), 0).elevation == 1);
    CHECK(view(direction(0, -40), 0).elevation == 0);
}

void test_culling() {
    Camera camera;
    camera.position = glm::vec3(0, 2, 0);
    camera.yaw = 0;  // looking along -Z
    camera.near_m = 0.1f, camera.far_m = 100;
    const Frustum f = frustum_from(camera.projection(16.0f / 9.0f) * camera.view());
    CHECK(sphere_in_frustum(f, glm::vec3(0, 2, -10), 1));
    CHECK(!sphere_in_frustum(f, glm::vec3(0, 2, 10), 1));     // behind
    CHECK(!sphere_in_frustum(f, glm::vec3(0, 2, -150), 1));   // beyond the far plane
    CHECK(!sphere_in_frustum(f, glm::vec3(40, 2, -10), 1));   // far to the right
    // A sphere straddling the left edge still counts: its centre is outside, its radius reaches in.
    const float edge_x = -10.0f * std::tan(0.5f * camera.fov_y) * 16.0f / 9.0f;
    CHECK(sphere_in_frustum(f, glm::vec3(edge_x - 0.5f, 2, -10), 1));
    CHECK(!sphere_in_frustum(f, glm::vec3(edge_x - 2.0f, 2, -10), 1));
    // camera_for_crowd frames every character.
    CrowdDesc desc;
    desc.count = 400;
    const Crowd crowd = make_crowd(desc, 2, 4, 1);
    const Camera overview = camera_for_crowd(crowd, 1.8f, 16.0f / 9.0f, 0.5f);
    const Frustum fo = frustum_from(overview.projection(16.0f / 9.0f) * overview.view());
    for (const Character& c : crowd.characters) CHECK(sphere_in_frustum(fo, c.start + glm::vec3(0, 0.9f, 0), 0.0f));
}

void test_crowd_and_frames() {
    CrowdDesc desc;
    desc.count = 100;
    desc.seed = 42;
    const Crowd a = make_crowd(desc, 3, 4, 1.0f), b = make_crowd(desc, 3, 4, 1.0f);
    CHECK(a.characters.size() == 100);
    bool same = true, variations[3] = {}, outfits[4] = {};
    for (size_t i = 0; i < 100; ++i) {
        same &= a.characters[i].start == b.characters[i].start && a.characters[i].heading == b.characters[i].heading &&
                a.characters[i].variation == b.characters[i].variation && a.characters[i].outfit == b.characters[i].outfit;
        CHECK(a.characters[i].variation < 3 && a.characters[i].outfit < 4);
        CHECK(a.characters[i].phase_s >= 0 && a.characters[i].phase_s < 1.0f);
        CHECK(std::fabs(a.characters[i].start.x) <= a.half_extent && std::fabs(a.characters[i].start.z) <= a.half_extent);
        variations[a.characters[i].variation] = outfits[a.characters[i].outfit] = true;
    }
    CHECK(same);
    CHECK(variations[0] && variations[1] && variations[2] && outfits[0] && outfits[3]);
    desc.seed = 43;
    CHECK(make_crowd(desc, 3, 4, 1.0f).characters[0].start != a.characters[0].start);
    // Neighbours keep apart: the jitter is a quarter spacing at most.
    float nearest = INFINITY;
    for (size_t i = 0; i < 100; ++i)
        for (size_t j = i + 1; j < 100; ++j) nearest = std::min(nearest, glm::distance(a.characters[i].start, a.characters[j].start));
    CHECK(nearest >= 0.5f * 1.6f - 1e-4f);
    // Spacing from the character's size: human-sized and smaller keep 1.6 m; a robot whose impostor
    // sphere has a 2.2 m radius gets 2.2 times it, and its neighbours stand as far apart in proportion.
    CHECK(crowd_spacing(0) == 1.6f && crowd_spacing(0.95f) == 1.6f);
    CHECK_NEAR(crowd_spacing(2.2f), 1.6 * 2.2, 1e-5);
    CrowdDesc robots = desc;
    robots.spacing = crowd_spacing(2.2f);
    const Crowd big = make_crowd(robots, 3, 4, 1.0f);
    float nearest_big = INFINITY;
    for (size_t i = 0; i < 100; ++i)
        for (size_t j = i + 1; j < 100; ++j) nearest_big = std::min(nearest_big, glm::distance(big.characters[i].start, big.characters[j].start));
    CHECK(nearest_big >= 0.5f * crowd_spacing(2.2f) - 1e-4f && nearest_big > 1.6f);

    // Paths: walk along the heading, wrapped into the square.
    desc.layout = Layout::paths;
    const Crowd walkers = make_crowd(desc, 1, 1, 1.0f);
    const Character& w = walkers.characters[5];
    const glm::vec3 p0 = character_position(walkers, w, 0), p1 = character_position(walkers, w, 0.5f);
    CHECK(glm::distance(p0, w.start) < 1e-5f);
    CHECK_NEAR(glm::dot(p1 - p0, glm::vec3(std::sin(w.heading), 0, std::cos(w.heading))), 0.65, 1e-3);
    for (float t = 0; t < 200; t += 3.7f) {
        const glm::vec3 p = character_position(walkers, w, t);
        CHECK(std::fabs(p.x) <= walkers.half_extent + 1e-3f && std::fabs(p.z) <= walkers.half_extent + 1e-3f);
    }
    CHECK(character_position(a, a.characters[5], 10) == a.characters[5].start);  // on the spot

    // Frames: 8 fps, 8 frames; frame 8 wraps to 0.
    CHECK(cycle_frame(0, 0, 8, 8) == 0);
    CHECK(cycle_frame(0.99f, 0, 8, 8) == 7);
    CHECK(cycle_frame(1.0f, 0, 8, 8) == 0);
    CHECK(cycle_frame(0.5f, 0.25f, 8, 8) == 6);
    CHECK(cycle_frame(1000.3f, 0, 8, 8) == 2);
    const std::vector<uint32_t> baked = {0, 2, 4, 6};
    CHECK(impostor_layer(0, baked, 8) == 0);
    CHECK(impostor_layer(3, baked, 8) == 1);  // 2 and 4 tie: the first wins
    CHECK(impostor_layer(6, baked, 8) == 3);
    CHECK(impostor_layer(7, baked, 8) == 0);  // 6 and 0 (= 8) tie around the cycle
    CHECK(impostor_layer(7, {0, 3}, 8) == 0); // 0 is one frame away around the cycle, 3 is four
}

// Weight of `tile` in `w` (0 when absent; repeated tiles add up).
float weight_of(const ViewWeights& w, uint32_t tile) {
    float total = 0;
    for (int k = 0; k < 4; ++k) total += w.tiles[k] == tile ? w.weights[k] : 0.0f;
    return total;
}

void test_view_blending() {
    const uint32_t columns = uint32_t(kAzimuths.size());
    auto blend = [](float azimuth, float elevation) { return blend_view_weights({azimuth, elevation}, kAzimuths, kElevations); };
    // On a baked view: that view alone.
    CHECK_NEAR(weight_of(blend(60, 0), 2), 1.0f, 1e-6);
    CHECK_NEAR(weight_of(blend(60, 30), 2 + columns), 1.0f, 1e-6);
    // Half way in azimuth: the two neighbours, half each.
    CHECK_NEAR(weight_of(blend(15, 0), 0), 0.5f, 1e-6);
    CHECK_NEAR(weight_of(blend(15, 0), 1), 0.5f, 1e-6);
    // A third of the way from 90 to 120: two thirds on 90.
    CHECK_NEAR(weight_of(blend(100, 0), 3), 2.0f / 3.0f, 1e-5);
    CHECK_NEAR(weight_of(blend(100, 0), 4), 1.0f / 3.0f, 1e-5);
    // Around the wrap: 345 lies half way between 330 and 0; -15 is the same direction.
    CHECK_NEAR(weight_of(blend(345, 0), 11), 0.5f, 1e-5);
    CHECK_NEAR(weight_of(blend(345, 0), 0), 0.5f, 1e-5);
    CHECK_NEAR(weight_of(blend(-15, 0), 11), 0.5f, 1e-5);
    // Bilinear: half way in azimuth and elevation, a quarter on each of four tiles.
    for (uint32_t tile : {0u, 1u, columns, columns + 1}) CHECK_NEAR(weight_of(blend(15, 15), tile), 0.25f, 1e-5);
    // Elevation clamped to the baked rows: above the top row, the top row alone.
    CHECK_NEAR(weight_of(blend(0, 70), columns), 1.0f, 1e-6);
    CHECK_NEAR(weight_of(blend(0, -40), 0), 1.0f, 1e-6);
    // Unsorted rows and columns, and a single azimuth.
    const ViewWeights unsorted = blend_view_weights({45, 20}, {90, 0, 60, 30}, {40, 0});
    // Tile = column + row * 4: azimuth 30 is column 3, 60 column 2; elevation 40 row 0, 0 row 1.
    for (uint32_t tile : {3u, 2u, 3u + 4u, 2u + 4u}) CHECK_NEAR(weight_of(unsorted, tile), 0.25f, 1e-5);
    CHECK_NEAR(weight_of(unsorted, 0u + 4u), 0.0f, 1e-6);
    const ViewWeights single = blend_view_weights({123, 0}, {0}, {0});
    CHECK_NEAR(weight_of(single, 0), 1.0f, 1e-6);
    // Everywhere: weights in [0, 1] summing to 1, the heaviest tile is the nearest view (away
    // from ties), and the weights follow the camera in the character's frame.
    for (float heading = 0; heading < 360; heading += 41)
        for (float az = 0; az < 360; az += 11)
            for (float el = -20; el < 60; el += 13) {
                const glm::vec2 angles = view_angles_deg(direction(az + heading, el) * 3.0f, glm::radians(heading));
                const ViewWeights w = blend_view_weights(angles, kAzimuths, kElevations);
                float sum = 0, heaviest = -1;
                uint32_t heaviest_tile = 0;
                for (int k = 0; k < 4; ++k) {
                    CHECK(w.weights[k] >= 0.0f && w.weights[k] <= 1.0f);
                    sum += w.weights[k];
                }
                for (int k = 0; k < 4; ++k)
                    if (weight_of(w, w.tiles[k]) > heaviest) heaviest = weight_of(w, w.tiles[k]), heaviest_tile = w.tiles[k];
                CHECK_NEAR(sum, 1.0f, 1e-5);
                const ImpostorView nearest = select_view(direction(az + heading, el), glm::radians(heading), kAzimuths, kElevations);
                const float az_off = std::fmod(az + 3600.0f, 30.0f), el_clamped = glm::clamp(el, 0.0f, 30.0f);
                if (std::fabs(az_off - 15.0f) > 0.5f && std::fabs(el_clamped - 15.0f) > 0.5f)
                    CHECK_MSG(heaviest_tile == nearest.azimuth + nearest.elevation * columns,
                              "az " + std::to_string(az) + " el " + std::to_string(el) + " heading " + std::to_string(heading));
            }
    // Nearest, as ViewWeights: one tile with all the weight, the same as select_view.
    const ViewWeights nearest = nearest_view_weights({100, 20}, kAzimuths, kElevations);
    CHECK(nearest.tiles[0] == 3 + columns && nearest.weights[0] == 1.0f);
}

void test_frame_blending() {
    const std::vector<uint32_t> baked = {0, 2, 4, 6};
    FrameWeights f = blend_frame_weights(2, baked, 8);  // a baked frame: that layer alone
    CHECK(f.layers[0] == 1 && f.weight == 0.0f);
    f = blend_frame_weights(3, baked, 8);  // half way between baked frames 2 and 4
    CHECK(f.layers[0] == 1 && f.layers[1] == 2);
    CHECK_NEAR(f.weight, 0.5f, 1e-6);
    f = blend_frame_weights(7, baked, 8);  // wraps from 6 through 8 to 0
    CHECK(f.layers[0] == 3 && f.layers[1] == 0);
    CHECK_NEAR(f.weight, 0.5f, 1e-6);
    f = blend_frame_weights(1, {3, 6}, 9);  // before the first baked frame: from 6 round to 3
    CHECK(f.layers[0] == 1 && f.layers[1] == 0);
    CHECK_NEAR(f.weight, 4.0f / 6.0f, 1e-6);  // 6 -> 1 is 4 frames of the 6 from 6 to 3 (+9)
    f = blend_frame_weights(5, {4}, 8);  // a single baked frame
    CHECK(f.layers[0] == 0 && f.layers[1] == 0 && f.weight == 0.0f);
    // The heavier layer is impostor_layer's nearest one (away from ties).
    for (uint32_t frame = 0; frame < 24; ++frame) {
        const std::vector<uint32_t> uneven = {1, 5, 6, 13, 20};
        const FrameWeights w = blend_frame_weights(frame, uneven, 24);
        CHECK(w.weight >= 0.0f && w.weight < 1.0f);
        if (std::fabs(w.weight - 0.5f) > 1e-3f) CHECK(w.layers[w.weight > 0.5f ? 1 : 0] == impostor_layer(frame, uneven, 24));
    }
}

void test_build_frame() {
    // A line of characters walking away from the camera along -Z.
    Crowd crowd;
    for (int i = 0; i < 60; ++i) crowd.characters.push_back({glm::vec3(0, 0, -1.0f - float(i)), 0.0f, 0.0f, 0, 0});
    crowd.characters.push_back({glm::vec3(0, 0, 30), 0.0f, 0.0f, 0, 0});  // behind the camera
    CharacterModel model;
    model.center = glm::vec3(0, 0.9f, 0);
    model.radius = 1;
    model.frame_count = 8;
    model.frames_per_second = 8;
    model.azimuths_deg = kAzimuths;
    model.elevations_deg = kElevations;
    model.frame_indices = {0, 2, 4, 6};
    model.has_low = true;
    Camera camera;
    camera.position = glm::vec3(0, 0.9f, 0);
    camera.far_m = 500;
    LodRule rule;
    rule.impostor_distance = 20;
    FrameState state;
    FrameInstances frame;
    build_frame(crowd, model, camera, 1.5f, LodMode::automatic, rule, 0.3f, &state, &frame);
    CHECK(frame.culled == 1);
    CHECK(frame.by_lod[0].size() == 9);   // depth 1..9 m < 10 m
    CHECK(frame.by_lod[1].size() == 10);  // 10..19 m
    CHECK(frame.by_lod[2].size() == 41);  // 20..60 m
    for (const Instance& inst : frame.by_lod[2]) {
        CHECK(inst.tile == 0);   // seen from the front: azimuth 0, elevation 0
        CHECK(inst.frame == 1);  // cycle frame 2 at 0.3 s, baked as layer 1
    }
    CHECK(frame.by_lod[0][0].frame == 2);
    // Blend samples, one per impostor: the front view alone; cycle frame 2 is baked, so one
    // layer; with blending off, the same.
    CHECK(frame.impostor_samples.size() == frame.by_lod[2].size());
    for (const ImpostorSamples& s : frame.impostor_samples) {
        CHECK(s.tiles[0] == 0 && std::fabs(s.view_weights[0] - 1.0f) < 1e-5f);
        CHECK(s.layers[0] == 1 && s.frame_weight == 0.0f);
    }
    // At 0.4 s (cycle frame 3, between baked 2 and 4): half each; blending off keeps the nearest.
    build_frame(crowd, model, camera, 1.5f, LodMode::impostor, rule, 0.4f, &state, &frame, ImpostorBlend::full);
    CHECK(frame.impostor_samples[0].layers[0] == 1 && frame.impostor_samples[0].layers[1] == 2);
    CHECK(std::fabs(frame.impostor_samples[0].frame_weight - 0.5f) < 1e-6f);
    build_frame(crowd, model, camera, 1.5f, LodMode::impostor, rule, 0.4f, &state, &frame, ImpostorBlend::views);
    CHECK(frame.impostor_samples[0].frame_weight == 0.0f && frame.impostor_samples[0].layers[0] == frame.by_lod[2][0].frame);
    build_frame(crowd, model, camera, 1.5f, LodMode::impostor, rule, 0, &state, &frame);
    CHECK(frame.by_lod[2].size() == 60 && frame.by_lod[0].empty());
    build_frame(crowd, model, camera, 1.5f, LodMode::low, rule, 0, &state, &frame);
    CHECK(frame.by_lod[1].size() == 60);
    model.has_low = false;
    build_frame(crowd, model, camera, 1.5f, LodMode::low, rule, 0, &state, &frame);
    CHECK(frame.by_lod[0].size() == 60);  // no low mesh in the bundle: the high one stands in
}

// Every list of `a` equals that of `b` byte for byte, impostor samples included.
bool same_frame(const FrameInstances& a, const FrameInstances& b) {
    bool same = a.culled == b.culled && a.impostor_samples.size() == b.impostor_samples.size();
    for (int l = 0; l < 3 && same; ++l)
        same = a.by_lod[l].size() == b.by_lod[l].size() &&
               std::memcmp(a.by_lod[l].data(), b.by_lod[l].data(), a.by_lod[l].size() * sizeof(Instance)) == 0;
    return same && std::memcmp(a.impostor_samples.data(), b.impostor_samples.data(), a.impostor_samples.size() * sizeof(ImpostorSamples)) == 0;
}

void test_archetypes_side_by_side() {
    // Three archetypes, one of them several chunks long and walking, built in turn by build_frame and
    // together by build_frames on 1, 2 and 3 threads: the same instances in the same order, frame
    // after frame (the LOD history and clip states carry over) while the camera moves.
    std::vector<Crowd> crowds(3);
    std::vector<CharacterModel> models(3);
    for (size_t a = 0; a < 3; ++a) {
        const int count = a == 1 ? 5000 : 200;
        for (int i = 0; i < count; ++i)
            crowds[a].characters.push_back({glm::vec3(float(i % 20) - 10.0f, 0, -2.0f - float(i / 20) * 3.0f), 0.3f * float(i), 0.1f * float(a), uint32_t(i % 8), 0});
        models[a].center = glm::vec3(0, 0.9f * float(a + 1), 0);
        models[a].radius = float(a + 1);
        models[a].frame_count = 24, models[a].frames_per_second = 24;
        models[a].azimuths_deg = kAzimuths, models[a].elevations_deg = kElevations;
        models[a].frame_indices = {0, 6, 12, 18};
        models[a].has_low = true;
    }
    crowds[1].layout = Layout::paths, crowds[1].half_extent = 400, crowds[1].walk_speed = 1.3f;
    models[2].azimuths_deg = {0, 100, 200};  // uneven: view_blend.h's search
    LodRule rule;
    rule.impostor_distance = 12;
    for (unsigned threads : {1u, 2u, 3u}) {
        std::vector<FrameState> alone(3), together(3);
        std::vector<FrameInstances> in_turn(3), side_by_side(3);
        std::vector<ArchetypeFrame> builds;
        for (size_t a = 0; a < 3; ++a) builds.push_back({&crowds[a], &models[a], &rule, &together[a], &side_by_side[a]});
        size_t meshes = 0, impostors = 0, culled = 0;
        for (int frame = 0; frame < 4; ++frame) {
            Camera camera;
            camera.position = glm::vec3(2.0f * float(frame), 3, 5 - 4.0f * float(frame));  // moving in and across
            camera.yaw = 0.1f * float(frame);
            camera.far_m = 500;
            const float time_s = 0.7f + float(frame) * kFixedTimeStep;
            for (size_t a = 0; a < 3; ++a)
                build_frame(crowds[a], models[a], camera, 1.5f, LodMode::automatic, rule, time_s, &alone[a], &in_turn[a], ImpostorBlend::warp);
            build_frames(builds, camera, 1.5f, LodMode::automatic, time_s, ImpostorBlend::warp, threads);
            for (size_t a = 0; a < 3; ++a) {
                CHECK(same_frame(in_turn[a], side_by_side[a]));
                CHECK(alone[a].lod == together[a].lod);
                meshes += in_turn[a].by_lod[0].size() + in_turn[a].by_lod[1].size(), impostors += in_turn[a].by_lod[2].size();
                culled += in_turn[a].culled;
            }
        }
        CHECK(meshes > 0 && impostors > 0 && culled > 0);  // the frames hold every kind
    }
    CHECK(frame_threads() >= 1);
}

void test_frame_views() {
    // build_frame's views (a vectorised pass on fast angles, exact angles near a tie) against
    // view_blend.h's reference on exact angles: the same nearest tile, the same blend within float
    // rounding; on evenly spaced azimuths with 1, 3 and 5 elevations (5: the general path), one
    // azimuth, and characters whose camera direction lies exactly half way between two views.
    const std::vector<std::vector<float>> elevations = {{0, 20, 40}, {10}, {40, 0, 20, 60, 80}};
    Rng rng(11);
    Crowd crowd;
    for (int i = 0; i < 3000; ++i) {
        const float heading = i < 24 ? glm::radians(15.0f * float(i)) : rng.uniform(0.0f, 6.2831853f);
        const glm::vec3 feet(i < 24 ? 0.0f : rng.uniform(-20.0f, 20.0f), i < 24 ? -0.9f : rng.uniform(-25.0f, 15.0f),
                             i < 24 ? -10.0f : rng.uniform(-60.0f, -5.0f));
        crowd.characters.push_back({feet, heading, 0.0f, 0, 0});
    }
    Camera camera;
    camera.position = glm::vec3(0, 0, 0);
    camera.pitch = -0.2f;
    camera.fov_y = glm::radians(100.0f);
    camera.far_m = 500;
    for (size_t e = 0; e < elevations.size() * 2; ++e) {
        CharacterModel model;
        model.center = glm::vec3(0, 0.9f, 0);  // on the axis: the centre is the feet plus 0.9 m up
        model.frame_count = 8, model.frames_per_second = 8, model.frame_indices = {0, 4};
        model.azimuths_deg = e < elevations.size() ? std::vector<float>{0, 30, 60, 90, 120, 150, 180, 210, 240, 270, 300, 330} : std::vector<float>{0};
        model.elevations_deg = elevations[e % elevations.size()];
        for (ImpostorBlend blend : {ImpostorBlend::warp, ImpostorBlend::off}) {
            FrameState state;
            FrameInstances frame;
            build_frame(crowd, model, camera, 1.5f, LodMode::impostor, LodRule(), 0.0f, &state, &frame, blend);
            CHECK(frame.by_lod[2].size() > 1000 && frame.impostor_samples.size() == frame.by_lod[2].size());
            for (size_t k = 0; k < frame.by_lod[2].size(); ++k) {
                const Instance& inst = frame.by_lod[2][k];
                const ImpostorSamples& got = frame.impostor_samples[k];
                const glm::vec3 to_camera = camera.position - glm::vec3(inst.position[0], inst.position[1] + 0.9f, inst.position[2]);
                const glm::vec2 angles = view_angles_deg(to_camera, inst.heading);
                // The reference's choice; at an exact tie (the first 24 characters) float rounding of the
                // angles may pick either side, so a millidegree either way is accepted too.
                auto nearest = [&](glm::vec2 a) { return nearest_view_weights(a, model.azimuths_deg, model.elevations_deg).tiles[0]; };
                const glm::vec2 nudge(1e-3f, 1e-3f);
                CHECK(inst.tile == nearest(angles) || (k < 24 && (inst.tile == nearest(angles - nudge) || inst.tile == nearest(angles + nudge))));
                if (blend == ImpostorBlend::off) {
                    CHECK(got.tiles[0] == inst.tile && got.view_weights[0] == 1.0f && got.view_weights[1] == 0.0f);
                    continue;
                }
                const ViewWeights want = blend_view_weights(angles, model.azimuths_deg, model.elevations_deg);
                float sum = 0;
                for (int m = 0; m < 4; ++m) {
                    sum += got.view_weights[m];
                    CHECK(m == 0 || got.view_weights[m] <= got.view_weights[m - 1]);  // heaviest first
                    float expected = 0;  // the reference's weight for this sample's tile
                    for (int r = 0; r < 4; ++r) expected += want.tiles[r] == got.tiles[m] ? want.weights[r] : 0.0f;
                    if (got.view_weights[m] > 0) CHECK(std::fabs(got.view_weights[m] - expected) < 2e-4f);
                }
                CHECK(std::fabs(sum - 1.0f) < 1e-5f);
            }
        }
    }
}

}  // namespace

int main() {
    test_switch_distance();
    test_lod_levels();
    test_view_selection();
    test_view_blending();
    test_frame_blending();
    test_culling();
    test_crowd_and_frames();
    test_build_frame();
    test_archetypes_side_by_side();
    test_frame_views();
    return check::exit_code();
}
