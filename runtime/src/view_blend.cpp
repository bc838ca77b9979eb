// Impostor view and frame weights (view_blend.h): pure functions, unit-tested in test_crowd.cpp.
#include "view_blend.h"

#include <algorithm>
#include <cmath>

namespace crowdview {

namespace {

// Degrees from `from` to `to` going the positive way round, in [0, 360).
float ccw_gap(float from, float to) {
    float d = std::fmod(to - from, 360.0f);
    if (d < 0) d += 360.0f;
    return d >= 360.0f ? 0.0f : d;
}

// Angle difference in degrees folded into [0, 180].
float azimuth_gap(float a, float b) {
    const float d = std::fmod(std::fabs(a - b), 360.0f);
    return std::min(d, 360.0f - d);
}

}  // namespace

glm::vec2 view_angles_deg(const glm::vec3& to_camera, float heading) {
    // Into the character's frame: undo its heading (a rotation about +Y).
    const float c = std::cos(heading), s = std::sin(heading);
    const glm::vec3 local(c * to_camera.x - s * to_camera.z, to_camera.y, s * to_camera.x + c * to_camera.z);
    const float length = glm::length(local);
    const glm::vec3 d = length > 0 ? local / length : glm::vec3(0, 0, 1);
    return glm::vec2(glm::degrees(std::atan2(d.x, d.z)), glm::degrees(std::asin(glm::clamp(d.y, -1.0f, 1.0f))));
}

ViewWeights nearest_view_weights(const glm::vec2& angles, const std::vector<float>& azimuths_deg,
                                 const std::vector<float>& elevations_deg) {
    uint32_t azimuth = 0, elevation = 0;
    float best = INFINITY;
    for (uint32_t a = 0; a < azimuths_deg.size(); ++a)
        if (const float gap = azimuth_gap(angles.x, azimuths_deg[a]); gap < best) best = gap, azimuth = a;
    best = INFINITY;
    for (uint32_t e = 0; e < elevations_deg.size(); ++e)
        if (const float gap = std::fabs(angles.y - elevations_deg[e]); gap < best) best = gap, elevation = e;
    ViewWeights v;
    const uint32_t tile = azimuth + elevation * uint32_t(azimuths_deg.size());
    for (uint32_t& t : v.tiles) t = tile;
    return v;
}

ViewWeights blend_view_weights(const glm::vec2& angles, const std::vector<float>& azimuths_deg,
                               const std::vector<float>& elevations_deg) {
    const uint32_t columns = uint32_t(azimuths_deg.size());
    // Azimuth: a0 is the nearest baked azimuth at or before the camera's going the positive
    // way, a1 the nearest after it; the weight of a1 is the camera's share of the gap.
    uint32_t a0 = 0, a1 = 0;
    float before = INFINITY, after = INFINITY;
    for (uint32_t a = 0; a < columns; ++a)
        if (const float g = ccw_gap(azimuths_deg[a], angles.x); g < before) before = g, a0 = a;
    for (uint32_t a = 0; a < columns; ++a)
        if (const float g = ccw_gap(angles.x, azimuths_deg[a]); a != a0 && g < after) after = g, a1 = a;
    float wa = 0;  // weight of a1
    if (columns < 2) a1 = a0;
    else if (before + after > 0) wa = before / (before + after);
    // Elevation: clamped to the baked range, then the rows either side.
    const auto [lowest, highest] = std::minmax_element(elevations_deg.begin(), elevations_deg.end());
    const float elevation = glm::clamp(angles.y, *lowest, *highest);
    uint32_t e0 = uint32_t(lowest - elevations_deg.begin()), e1 = uint32_t(highest - elevations_deg.begin());
    for (uint32_t e = 0; e < elevations_deg.size(); ++e) {
        const float v = elevations_deg[e];
        if (v <= elevation && v > elevations_deg[e0]) e0 = e;
        if (v >= elevation && v < elevations_deg[e1]) e1 = e;
    }
    const float span = elevations_deg[e1] - elevations_deg[e0];
    const float we = span > 0 ? (elevation - elevations_deg[e0]) / span : 0.0f;  // weight of e1
    ViewWeights v;
    v.tiles[0] = a0 + e0 * columns, v.weights[0] = (1 - wa) * (1 - we);
    v.tiles[1] = a1 + e0 * columns, v.weights[1] = wa * (1 - we);
    v.tiles[2] = a0 + e1 * columns, v.weights[2] = (1 - wa) * we;
    v.tiles[3] = a1 + e1 * columns, v.weights[3] = wa * we;
    return v;
}

FrameWeights blend_frame_weights(uint32_t frame, const std::vector<uint32_t>& frame_indices, uint32_t frame_count) {
    FrameWeights f;
    const uint32_t n = uint32_t(frame_indices.size());
    if (n < 2 || frame_count == 0) return f;  // one baked frame (or none): layer 0 alone
    // k: the last baked frame at or before `frame`; before the first one, the last (wrapping).
    uint32_t k = n - 1;
    for (uint32_t i = 0; i < n; ++i)
        if (frame_indices[i] <= frame) k = i;
    const uint32_t next = (k + 1) % n;
    const uint64_t from = frame_indices[k], to = frame_indices[next];
    const uint64_t span = next > k ? to - from : to + frame_count - from;  // the wrap goes through frame_count
    const uint64_t offset = frame >= from ? frame - from : uint64_t(frame) + frame_count - from;
    f.layers[0] = k, f.layers[1] = next;
    f.weight = span > 0 ? float(double(offset) / double(span)) : 0.0f;
    return f;
}

}  // namespace crowdview
