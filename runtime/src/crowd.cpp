// The crowd, the LOD rule and view selection: pure functions over glm, unit-tested.
#include "crowd.h"

#include <algorithm>
#include <cmath>

#include <glm/gtc/matrix_transform.hpp>

namespace crowdview {

uint64_t Rng::next() {
    uint64_t z = (state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

float Rng::uniform(float lo, float hi) { return lo + (hi - lo) * float(next() >> 40) * (1.0f / 16777216.0f); }

uint32_t Rng::below(uint32_t n) { return uint32_t((next() >> 32) % n); }

Crowd make_crowd(const CrowdDesc& desc, uint32_t variation_count, uint32_t outfit_count, float cycle_seconds) {
    Crowd crowd;
    crowd.layout = desc.layout;
    crowd.walk_speed = desc.walk_speed > 0 ? desc.walk_speed : 1.3f;
    const float spacing = desc.spacing > 0 ? desc.spacing : 1.6f;
    const uint32_t side = uint32_t(std::ceil(std::sqrt(double(desc.count))));
    crowd.half_extent = 0.5f * spacing * float(std::max(side, 1u));
    Rng rng(desc.seed);
    crowd.characters.reserve(desc.count);
    for (uint32_t i = 0; i < desc.count; ++i) {
        const uint32_t row = i / side, column = i % side;
        Character c;
        // A quarter spacing of jitter breaks the grid up without letting neighbours touch.
        c.start = glm::vec3((float(column) + 0.5f) * spacing - crowd.half_extent + rng.uniform(-0.25f, 0.25f) * spacing, 0.0f,
                            (float(row) + 0.5f) * spacing - crowd.half_extent + rng.uniform(-0.25f, 0.25f) * spacing);
        c.heading = rng.uniform(0.0f, 2.0f * glm::pi<float>());
        c.phase_s = rng.uniform(0.0f, std::max(cycle_seconds, 0.0f));
        c.variation = rng.below(std::max(variation_count, 1u));
        c.outfit = rng.below(std::max(outfit_count, 1u));
        crowd.characters.push_back(c);
    }
    return crowd;
}

void assign_clips(Crowd* crowd, const std::vector<float>& weights, const std::vector<float>& clip_seconds, uint64_t seed) {
    float total = 0;
    size_t drawable = 0;
    for (float w : weights) total += std::max(w, 0.0f), drawable += w > 0;
    if (total <= 0 || (drawable == 1 && weights[0] > 0)) return;  // clip 0 for everyone, drawing nothing: the crowd its seed gives without clips
    // Its own stream, so positions, headings and outfits stay those of the same seed without clips.
    Rng rng(seed ^ 0xC11D5EEDC11D5EEDull);
    for (Character& c : crowd->characters) {
        const float pick = rng.uniform(0.0f, total);
        uint32_t clip = 0;
        float sum = 0;
        for (uint32_t k = 0; k < weights.size(); ++k) {
            if (!(weights[k] > 0)) continue;
            clip = k;
            sum += weights[k];
            if (pick < sum) break;
        }
        c.clip = clip;
        c.phase_s = rng.uniform(0.0f, clip < clip_seconds.size() ? std::max(clip_seconds[clip], 0.0f) : 0.0f);
    }
}

// The impostor bounding sphere of a 1.8 m walker: about half its height plus the swing of arms and
// cloth (the sample and CesiumMan bake to 0.9 to 1.0 m). Up to it, the human spacing of CrowdDesc.
constexpr float kHumanRadius = 1.0f;
constexpr float kHumanSpacing = 1.6f;

float crowd_spacing(float radius) {
    if (!(radius > kHumanRadius)) return kHumanSpacing;
    return kHumanSpacing * radius / kHumanRadius;
}

glm::vec3 character_position(const Crowd& crowd, const Character& c, float time_s) {
    if (crowd.layout == Layout::on_the_spot || crowd.half_extent <= 0) return c.start;
    const float size = 2.0f * crowd.half_extent;
    glm::vec3 p = c.start + glm::vec3(std::sin(c.heading), 0.0f, std::cos(c.heading)) * (crowd.walk_speed * time_s);
    for (int axis : {0, 2}) p[axis] = p[axis] + crowd.half_extent - size * std::floor((p[axis] + crowd.half_extent) / size) - crowd.half_extent;
    return p;
}

uint32_t cycle_frame(float time_s, float phase_s, float frames_per_second, uint32_t frame_count) {
    if (frame_count == 0) return 0;
    const double f = std::floor(double(time_s + phase_s) * frames_per_second);
    const double wrapped = f - double(frame_count) * std::floor(f / frame_count);
    return std::min(uint32_t(wrapped), frame_count - 1);
}

uint32_t impostor_layer(uint32_t frame, const std::vector<uint32_t>& frame_indices, uint32_t frame_count) {
    uint32_t best = 0, best_distance = UINT32_MAX;
    for (uint32_t k = 0; k < frame_indices.size(); ++k) {
        const uint32_t d = frame > frame_indices[k] ? frame - frame_indices[k] : frame_indices[k] - frame;
        const uint32_t around = std::min(d, frame_count > d ? frame_count - d : d);
        if (around < best_distance) best = k, best_distance = around;
    }
    return best;
}

// ---------------------------------------------------------------------------------------

float impostor_switch_distance(float fov_y_rad, float viewport_height_px, float radius_m, uint32_t tile_size) {
    if (tile_size == 0 || viewport_height_px <= 0 || fov_y_rad <= 0) return 0;
    return radius_m * viewport_height_px / (float(tile_size) * std::tan(0.5f * fov_y_rad));
}

namespace {

// Levels present, nearest first, and the distance where each hands over to the next.
int level_boundaries(const LodRule& rule, Lod levels[3], float boundaries[2]) {
    if (rule.has_low && rule.low_fraction < 1.0f) {
        levels[0] = Lod::high, levels[1] = Lod::low, levels[2] = Lod::impostor;
        boundaries[0] = rule.impostor_distance * rule.low_fraction;
        boundaries[1] = rule.impostor_distance;
        return 3;
    }
    levels[0] = Lod::high, levels[1] = Lod::impostor;
    boundaries[0] = rule.impostor_distance;
    return 2;
}

}  // namespace

Lod lod_without_history(float distance, const LodRule& rule) {
    Lod levels[3];
    float boundaries[2];
    const int n = level_boundaries(rule, levels, boundaries);
    int i = 0;
    while (i < n - 1 && distance >= boundaries[i]) ++i;
    return levels[i];
}

Lod select_lod(float distance, Lod previous, const LodRule& rule) {
    Lod levels[3];
    float boundaries[2];
    const int n = level_boundaries(rule, levels, boundaries);
    int i = 0;
    while (i < n - 1 && levels[i] != previous) ++i;
    if (levels[i] != previous) return lod_without_history(distance, rule);  // e.g. low when the bundle has none
    while (i < n - 1 && distance > boundaries[i] * (1.0f + rule.hysteresis)) ++i;
    while (i > 0 && distance < boundaries[i - 1]) --i;
    return levels[i];
}

// ---------------------------------------------------------------------------------------

ImpostorView select_view(const glm::vec3& to_camera, float heading, const std::vector<float>& azimuths_deg,
                         const std::vector<float>& elevations_deg) {
    const ViewWeights nearest = nearest_view_weights(view_angles_deg(to_camera, heading), azimuths_deg, elevations_deg);
    const uint32_t columns = uint32_t(azimuths_deg.size());
    return ImpostorView{nearest.tiles[0] % columns, nearest.tiles[0] / columns};
}

// ---------------------------------------------------------------------------------------

glm::vec3 Camera::forward() const {
    return glm::vec3(-std::sin(yaw) * std::cos(pitch), std::sin(pitch), -std::cos(yaw) * std::cos(pitch));
}

glm::mat4 Camera::view() const { return glm::lookAt(position, position + forward(), glm::vec3(0, 1, 0)); }

glm::mat4 Camera::projection(float aspect) const { return glm::perspective(fov_y, aspect, near_m, far_m); }

Frustum frustum_from(const glm::mat4& m) {
    // Gribb and Hartmann: each clip plane is a sum or difference of the matrix's rows.
    Frustum f;
    const glm::vec4 row0(m[0][0], m[1][0], m[2][0], m[3][0]), row1(m[0][1], m[1][1], m[2][1], m[3][1]);
    const glm::vec4 row2(m[0][2], m[1][2], m[2][2], m[3][2]), row3(m[0][3], m[1][3], m[2][3], m[3][3]);
    f.planes[0] = row3 + row0;
    f.planes[1] = row3 - row0;
    f.planes[2] = row3 + row1;
    f.planes[3] = row3 - row1;
    f.planes[4] = row3 + row2;
    f.planes[5] = row3 - row2;
    for (glm::vec4& p : f.planes) p /= glm::length(glm::vec3(p));
    return f;
}

bool sphere_in_frustum(const Frustum& frustum, const glm::vec3& center, float radius) {
    for (const glm::vec4& p : frustum.planes)
        if (glm::dot(glm::vec3(p), center) + p.w < -radius) return false;
    return true;
}

Crowd make_crowd_in_view(const CrowdDesc& desc, const Camera& camera, float aspect, float center_height, float radius,
                         float near_m, uint32_t variation_count, uint32_t outfit_count, float cycle_seconds) {
    Crowd crowd;
    crowd.layout = Layout::on_the_spot;
    const float spacing = desc.spacing > 0 ? desc.spacing : 1.6f;
    const Frustum frustum = frustum_from(camera.projection(aspect) * camera.view());
    const glm::vec3 f = camera.forward();
    const glm::vec3 ahead = glm::length(glm::vec2(f.x, f.z)) > 1e-4f ? glm::normalize(glm::vec3(f.x, 0, f.z)) : glm::vec3(0, 0, -1);
    const glm::vec3 side = glm::cross(ahead, glm::vec3(0, 1, 0));
    const glm::vec3 ground(camera.position.x, 0, camera.position.z);
    const float half_width = std::tan(0.5f * camera.fov_y) * aspect;  // view half width per metre of depth
    Rng rng(desc.seed);
    auto inside = [&](const glm::vec3& c) {
        for (const glm::vec4& p : frustum.planes)
            if (glm::dot(glm::vec3(p), c) + p.w < radius) return false;
        return true;
    };
    std::vector<glm::vec3> row;
    for (uint32_t k = 0; crowd.characters.size() < desc.count; ++k) {
        const float depth = near_m + spacing * float(k);
        if (depth > camera.far_m) break;
        row.clear();
        const int reach = int(std::ceil((depth + camera.position.y) * half_width / spacing)) + 1;
        for (int i = -reach; i <= reach; ++i) {
            const glm::vec3 feet = ground + ahead * depth + side * ((float(i) + 0.5f * float(k % 2)) * spacing);  // staggered rows
            if (inside(feet + glm::vec3(0, center_height, 0))) row.push_back(feet);
        }
        // Centre first, so a partial last row stays in the middle of the view.
        std::sort(row.begin(), row.end(), [&](const glm::vec3& a, const glm::vec3& b) {
            return std::fabs(glm::dot(a - ground, side)) < std::fabs(glm::dot(b - ground, side));
        });
        for (const glm::vec3& feet : row) {
            if (crowd.characters.size() == desc.count) break;
            Character c;
            c.start = feet;
            c.heading = rng.uniform(0.0f, 2.0f * glm::pi<float>());
            c.phase_s = rng.uniform(0.0f, std::max(cycle_seconds, 0.0f));
            c.variation = rng.below(std::max(variation_count, 1u));
            c.outfit = rng.below(std::max(outfit_count, 1u));
            crowd.characters.push_back(c);
            crowd.half_extent = std::max(crowd.half_extent, std::max(std::fabs(feet.x), std::fabs(feet.z)));
        }
    }
    return crowd;
}

Camera camera_for_crowd(const Crowd& crowd, float character_height, float aspect, float pitch_rad) {
    Camera camera;
    const float half = crowd.half_extent;
    // The crowd's square seen from above at `pitch` is foreshortened vertically by sin(pitch),
    // so the width decides: fit the square's circumcircle (plus a character) across the
    // horizontal field of view, and the vertical one only where that is the tighter fit.
    const glm::vec3 center(0, 0.5f * character_height, 0);
    const float radius = std::sqrt(2.0f) * half + character_height;
    const float half_fov_x = std::atan(std::tan(0.5f * camera.fov_y) * aspect);
    const float half_fov_y = std::atan(std::tan(0.5f * camera.fov_y) / std::max(std::sin(pitch_rad), 0.5f));
    const float distance = radius / std::sin(std::min(half_fov_x, half_fov_y));
    camera.pitch = -pitch_rad;
    camera.yaw = 0;
    camera.position = center - camera.forward() * distance;
    camera.near_m = std::max(0.1f, distance - radius - 1.0f);
    camera.far_m = distance + radius + 1.0f;
    return camera;
}

Camera street_camera(const Crowd& crowd, float character_height) {
    Camera camera;
    camera.pitch = -0.25f;  // about 14 degrees down: the crowd fills the frame, little empty sky
    camera.yaw = 0;
    const glm::vec3 eye_target(0, 0.8f * character_height, 0);
    camera.position = eye_target - camera.forward() * (crowd.half_extent + 2.0f * character_height);
    camera.near_m = 0.1f;
    camera.far_m = 2.0f * (crowd.half_extent + 2.0f * character_height) + 10.0f;
    return camera;
}

// ---------------------------------------------------------------------------------------

LodRule lod_rule_for(const CharacterModel& model, const Camera& camera, float viewport_height_px) {
    LodRule rule;
    rule.impostor_distance = impostor_switch_distance(camera.fov_y, viewport_height_px, model.radius, model.tile_size);
    rule.has_low = model.has_low;
    return rule;
}

Camera look_at(glm::vec3 eye, glm::vec3 target) {
    Camera c;
    const glm::vec3 f = glm::normalize(target - eye);
    c.position = eye;
    c.yaw = std::atan2(-f.x, -f.z);
    c.pitch = std::asin(f.y);
    c.near_m = 0.1f, c.far_m = 200.0f;
    return c;
}

}  // namespace crowdview
