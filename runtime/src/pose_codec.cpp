// Quantized pose frames: see pose_codec.h.
#include "pose_codec.h"
#include "skinned_pose.h"

#include <algorithm>
#include <cmath>
#include <cstring>

namespace crowdview {

namespace {

float sign_not_zero(float v) { return v >= 0.0f ? 1.0f : -1.0f; }

uint16_t code_of(double unit) {  // unit in [0, 1]
    return uint16_t(std::clamp(std::lround(unit * kPoseCodeMax), 0L, long(kPoseCodeMax)));
}

bool all_finite(const float* values, size_t count) {
    return std::all_of(values, values + count, [](float x) { return std::isfinite(x); });
}

// Version 1's float frames checked as SPEC.md says: finite, unit normals, positions inside the bounds.
Status check_float_frames(const float* positions, const float* normals, size_t values, const float bounds[6],
                          const std::string& file, const char* function) {
    if (!all_finite(positions, values)) return make_error(ErrorCode::invalid_data, function, file, "positions contain NaN or infinity");
    if (!all_finite(normals, values)) return make_error(ErrorCode::invalid_data, function, file, "normals contain NaN or infinity");
    for (size_t i = 0; i < values; i += 3) {
        const double x = normals[i], y = normals[i + 1], z = normals[i + 2];
        if (std::fabs(std::sqrt(x * x + y * y + z * z) - 1.0) > kNormalLengthTolerance)
            return make_error(ErrorCode::invalid_data, function, file, "normal " + std::to_string(i / 3) + " (frame-major) is not unit length");
        for (int axis = 0; axis < 3; ++axis) {
            const double v = positions[i + axis];
            if (v < double(bounds[axis]) - kBoundsTolerance || v > double(bounds[3 + axis]) + kBoundsTolerance)
                return make_error(ErrorCode::invalid_data, function, file,
                                  "position " + std::to_string(i / 3) + " (frame-major) lies outside the header's bounds");
        }
    }
    return {};
}

// Version 1's checked float frames in version 2's stored form: each frame's bounds, then its codes.
void quantize_float_frames(const float* positions, const float* normals, PoseCache* cache) {
    const size_t vertices = cache->vertex_count;
    for (size_t f = 0; f < cache->frame_count; ++f) {
        const float* frame = positions + f * vertices * 3;
        float* bounds = &cache->frame_bounds[f * 6];
        for (int axis = 0; axis < 3; ++axis) bounds[axis] = bounds[3 + axis] = frame[axis];
        for (size_t v = 0; v < vertices * 3; ++v)
            bounds[v % 3] = std::min(bounds[v % 3], frame[v]), bounds[3 + v % 3] = std::max(bounds[3 + v % 3], frame[v]);
        for (size_t v = 0; v < vertices * 3; ++v) {
            const double extent = double(bounds[3 + v % 3]) - bounds[v % 3];
            cache->position_codes[f * vertices * 3 + v] = extent > 0 ? code_of((frame[v] - double(bounds[v % 3])) / extent) : 0;
        }
    }
    for (size_t v = 0; v < cache->frame_count * vertices; ++v) encode_octahedral(normals + v * 3, &cache->normal_codes[v * 2]);
}

// Version 2's frame bounds: finite, min <= max, inside the header's bounds.
Status check_frame_bounds(const std::vector<float>& frame_bounds, const float bounds[6], const std::string& file, const char* function) {
    if (!all_finite(frame_bounds.data(), frame_bounds.size()))
        return make_error(ErrorCode::invalid_data, function, file, "frame bounds contain NaN or infinity");
    for (size_t f = 0; f < frame_bounds.size() / 6; ++f) {
        const float* b = &frame_bounds[f * 6];
        for (int axis = 0; axis < 3; ++axis) {
            if (b[axis] > b[3 + axis])
                return make_error(ErrorCode::invalid_data, function, file,
                                  "frame " + std::to_string(f) + "'s bounds have a minimum above the maximum");
            if (b[axis] < bounds[axis] - kBoundsTolerance || b[3 + axis] > bounds[3 + axis] + kBoundsTolerance)
                return make_error(ErrorCode::invalid_data, function, file,
                                  "frame " + std::to_string(f) + "'s bounds reach outside the header's bounds");
        }
    }
    return {};
}

}  // namespace

void encode_octahedral(const float normal[3], uint16_t code[2]) {
    const double sum = std::max(std::fabs(double(normal[0])) + std::fabs(double(normal[1])) + std::fabs(double(normal[2])), 1e-30);
    double x = normal[0] / sum, y = normal[1] / sum;
    if (normal[2] < 0) {
        const double folded_x = (1 - std::fabs(y)) * sign_not_zero(float(x));
        y = (1 - std::fabs(x)) * sign_not_zero(float(y));
        x = folded_x;
    }
    code[0] = code_of((x + 1) * 0.5);
    code[1] = code_of((y + 1) * 0.5);
}

void decode_octahedral(const uint16_t code[2], float normal[3]) {
    float x = float(code[0]) * (2.0f / float(kPoseCodeMax)) - 1.0f, y = float(code[1]) * (2.0f / float(kPoseCodeMax)) - 1.0f;
    const float z = 1.0f - std::fabs(x) - std::fabs(y);
    if (z < 0) {
        const float unfolded_x = (1.0f - std::fabs(y)) * sign_not_zero(x);
        y = (1.0f - std::fabs(x)) * sign_not_zero(y);
        x = unfolded_x;
    }
    const float length = std::sqrt(x * x + y * y + z * z);
    normal[0] = x / length, normal[1] = y / length, normal[2] = z / length;
}

void decode_pose_position(const PoseCache& cache, uint32_t frame, uint32_t vertex, float position[3]) {
    if (cache.skinned()) return skin_position(cache, frame, vertex, position);
    const float* bounds = &cache.frame_bounds[size_t(frame) * 6];
    const uint16_t* code = &cache.position_codes[(size_t(frame) * cache.vertex_count + vertex) * 3];
    for (int axis = 0; axis < 3; ++axis)
        position[axis] = bounds[axis] + float(code[axis]) * ((bounds[3 + axis] - bounds[axis]) / float(kPoseCodeMax));
}

void decode_pose_normal(const PoseCache& cache, uint32_t frame, uint32_t vertex, float normal[3]) {
    if (cache.skinned()) return skin_normal(cache, frame, vertex, normal);
    decode_octahedral(&cache.normal_codes[(size_t(frame) * cache.vertex_count + vertex) * 2], normal);
}

uint64_t pose_cache_file_size(uint32_t version, uint32_t index_count, uint32_t vertex_count, uint32_t frame_count) {
    const uint64_t frame_vertices = uint64_t(vertex_count) * frame_count;
    const uint64_t frames = version == 1 ? 24 * frame_vertices : 24 * uint64_t(frame_count) + 10 * frame_vertices;
    return kPoseCacheHeaderSize + 4 * uint64_t(index_count) + 8 * uint64_t(vertex_count) + frames;
}

Status read_pose_frames(uint32_t version, const uint8_t* frames, const float bounds[6], const std::string& file,
                        const char* function, PoseCache* cache) {
    const size_t frame_vertices = size_t(cache->frame_count) * cache->vertex_count;
    cache->frame_bounds.resize(size_t(cache->frame_count) * 6);
    cache->position_codes.resize(frame_vertices * 3);
    cache->normal_codes.resize(frame_vertices * 2);
    if (version == 1) {
        std::vector<float> positions(frame_vertices * 3), normals(frame_vertices * 3);
        std::memcpy(positions.data(), frames, 12 * frame_vertices);
        std::memcpy(normals.data(), frames + 12 * frame_vertices, 12 * frame_vertices);
        if (Status s = check_float_frames(positions.data(), normals.data(), positions.size(), bounds, file, function); !s) return s;
        quantize_float_frames(positions.data(), normals.data(), cache);
        return {};
    }
    std::memcpy(cache->frame_bounds.data(), frames, 24 * size_t(cache->frame_count));
    frames += 24 * size_t(cache->frame_count);
    std::memcpy(cache->normal_codes.data(), frames, 4 * frame_vertices);
    std::memcpy(cache->position_codes.data(), frames + 4 * frame_vertices, 6 * frame_vertices);
    return check_frame_bounds(cache->frame_bounds, bounds, file, function);
}

}  // namespace crowdview
