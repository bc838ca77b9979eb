// Skinned pose caches: the CBSK parser and the CPU's skinning (see skinned_pose.h).
#include "skinned_pose.h"

#include <algorithm>
#include <cmath>
#include <cstring>

namespace crowdview {

namespace {

const char* kParse = "parse_skinned_pose_cache";

uint32_t read_u32(const uint8_t* p) {
    uint32_t v;
    std::memcpy(&v, p, 4);
    return v;
}

template <typename T>
const uint8_t* read_section(const uint8_t* p, size_t count, std::vector<T>* out) {
    out->resize(count);
    std::memcpy(out->data(), p, count * sizeof(T));
    return p + count * sizeof(T);
}

bool all_finite(const std::vector<float>& values) {
    return std::all_of(values.begin(), values.end(), [](float x) { return std::isfinite(x); });
}

Status invalid(const std::string& file, const std::string& detail) { return make_error(ErrorCode::invalid_data, kParse, file, detail); }

// The header's own fields (SPEC.md table), after the common header: invalid_header where one breaks its rule.
Status read_skinned_header(const uint8_t* data, const std::string& file, PoseCache* cache) {
    cache->version = read_u32(data + 4);
    cache->vertex_count = read_u32(data + 16);
    cache->index_count = read_u32(data + 20);
    cache->frame_count = read_u32(data + 24);
    cache->skin.joint_count = read_u32(data + 28);
    std::memcpy(&cache->frames_per_second, data + 32, 4);
    std::memcpy(cache->bounds_min, data + 36, 12);
    std::memcpy(cache->bounds_max, data + 48, 12);
    const uint32_t reserved = read_u32(data + 60);
    if (cache->vertex_count == 0 || cache->frame_count == 0 || cache->index_count == 0 || cache->index_count % 3)
        return make_error(ErrorCode::invalid_header, kParse, file,
                          "vertex_count " + std::to_string(cache->vertex_count) + ", index_count " + std::to_string(cache->index_count) +
                              ", frame_count " + std::to_string(cache->frame_count) +
                              ": all must be positive and index_count a multiple of 3");
    if (cache->skin.joint_count < 1 || cache->skin.joint_count > kMaxJoints)
        return make_error(ErrorCode::invalid_header, kParse, file,
                          "joint_count " + std::to_string(cache->skin.joint_count) + " is outside 1 to " + std::to_string(kMaxJoints));
    // A reader skins every frame to check the bounds, and the frames are not stored: without a cap a
    // small file could ask for hours of work (SPEC.md: frame_count x vertex_count at most 2^26).
    if (uint64_t(cache->vertex_count) * cache->frame_count > kMaxSkinnedVertexFrames)
        return make_error(ErrorCode::invalid_header, kParse, file,
                          std::to_string(cache->frame_count) + " frames of " + std::to_string(cache->vertex_count) +
                              " vertices: more than the 2^26 a skinned pose cache holds");
    if (reserved != 0) return make_error(ErrorCode::invalid_header, kParse, file, "reserved must be 0");
    if (!(std::isfinite(cache->frames_per_second) && cache->frames_per_second > 0))
        return make_error(ErrorCode::invalid_header, kParse, file,
                          "frames_per_second " + std::to_string(cache->frames_per_second) + " must be positive");
    return {};
}

// The payload's sections, in the file's order; the size was checked, so each lies inside the buffer.
void read_skinned_sections(const uint8_t* p, PoseCache* cache) {
    const size_t vertices = cache->vertex_count;
    PoseSkin& skin = cache->skin;
    p = read_section(p, cache->index_count, &cache->indices);
    p = read_section(p, vertices * 2, &cache->uvs);
    p = read_section(p, vertices * 3, &skin.rest_positions);
    p = read_section(p, vertices * 3, &skin.rest_normals);
    p = read_section(p, vertices * 4, &skin.joints);
    p = read_section(p, vertices * 4, &skin.weight_codes);
    read_section(p, size_t(cache->frame_count) * skin.joint_count * 12, &skin.matrices);
}

// Indices, joint indices and weight sums: the integers.
Status check_skinned_integers(const PoseCache& cache, const std::string& file) {
    const uint32_t max_index = *std::max_element(cache.indices.begin(), cache.indices.end());
    if (max_index >= cache.vertex_count)
        return invalid(file, "index " + std::to_string(max_index) + " >= vertex_count " + std::to_string(cache.vertex_count));
    const PoseSkin& skin = cache.skin;
    for (size_t v = 0; v < cache.vertex_count; ++v) {
        uint32_t sum = 0;
        for (size_t k = 0; k < 4; ++k) {
            if (skin.joints[v * 4 + k] >= skin.joint_count)
                return invalid(file, "vertex " + std::to_string(v) + " names joint " + std::to_string(skin.joints[v * 4 + k]) + ", joint_count is " +
                                         std::to_string(skin.joint_count));
            sum += skin.weight_codes[v * 4 + k];
        }
        if (sum != kWeightCodeSum)
            return invalid(file, "vertex " + std::to_string(v) + "'s weight codes sum to " + std::to_string(sum) + ", not 65535");
    }
    return {};
}

// Every float finite, and the rest normals unit length.
Status check_skinned_floats(const PoseCache& cache, const std::string& file) {
    const PoseSkin& skin = cache.skin;
    const float bounds[6] = {cache.bounds_min[0], cache.bounds_min[1], cache.bounds_min[2],
                             cache.bounds_max[0], cache.bounds_max[1], cache.bounds_max[2]};
    if (!std::all_of(bounds, bounds + 6, [](float x) { return std::isfinite(x); })) return invalid(file, "bounds contain NaN or infinity");
    const std::pair<const char*, const std::vector<float>*> sections[] = {
        {"uvs", &cache.uvs}, {"rest_positions", &skin.rest_positions}, {"rest_normals", &skin.rest_normals}, {"matrices", &skin.matrices}};
    for (const auto& [name, values] : sections)
        if (!all_finite(*values)) return invalid(file, std::string(name) + " contain NaN or infinity");
    for (size_t v = 0; v < cache.vertex_count; ++v) {
        const float* n = &skin.rest_normals[v * 3];
        const double length = std::sqrt(double(n[0]) * n[0] + double(n[1]) * n[1] + double(n[2]) * n[2]);
        if (std::fabs(length - 1.0) > kNormalLengthTolerance) return invalid(file, "rest normal " + std::to_string(v) + " is not unit length");
    }
    return {};
}

// Every matrix a vertex weights (code > 0) invertible in its 3x3 block, at every frame.
Status check_joint_determinants(const PoseCache& cache, const std::string& file) {
    const PoseSkin& skin = cache.skin;
    std::vector<bool> weighted(skin.joint_count, false);
    for (size_t i = 0; i < skin.joints.size(); ++i)
        if (skin.weight_codes[i] > 0) weighted[skin.joints[i]] = true;
    for (uint32_t f = 0; f < cache.frame_count; ++f)
        for (uint32_t j = 0; j < skin.joint_count; ++j)
            if (weighted[j] && !(std::fabs(joint_determinant(joint_matrix(skin, f, j))) >= kMinJointDeterminant))
                return invalid(file, "joint " + std::to_string(j) + "'s matrix at frame " + std::to_string(f) +
                                         " is singular (|det| < 1e-6) and a vertex weights it");
    return {};
}

// The header's bounds enclose every skinned position of every frame.
Status check_skinned_bounds(const PoseCache& cache, const std::string& file) {
    for (uint32_t f = 0; f < cache.frame_count; ++f)
        for (uint32_t v = 0; v < cache.vertex_count; ++v) {
            float p[3];
            skin_position(cache, f, v, p);
            for (int axis = 0; axis < 3; ++axis)
                if (!(p[axis] >= double(cache.bounds_min[axis]) - kBoundsTolerance && p[axis] <= double(cache.bounds_max[axis]) + kBoundsTolerance))
                    return invalid(file, "vertex " + std::to_string(v) + " skinned at frame " + std::to_string(f) +
                                             " lies outside the header's bounds");
        }
    return {};
}

// The influences of `vertex` with a weight: joint, weight (code / 65535); returns how many.
int weighted_influences(const PoseSkin& skin, uint32_t vertex, uint32_t joints[4], double weights[4]) {
    int count = 0;
    for (int k = 0; k < 4; ++k) {
        const uint16_t code = skin.weight_codes[size_t(vertex) * 4 + k];
        if (code == 0) continue;
        joints[count] = skin.joints[size_t(vertex) * 4 + k];
        weights[count++] = double(code) / kWeightCodeSum;
    }
    return count;
}

}  // namespace

uint64_t skinned_pose_cache_file_size(uint32_t index_count, uint32_t vertex_count, uint32_t frame_count, uint32_t joint_count) {
    return kPoseCacheHeaderSize + 4 * uint64_t(index_count) + 48 * uint64_t(vertex_count) + 48 * uint64_t(frame_count) * joint_count;
}

double joint_determinant(const float* m) {
    // Rows (m[0..2], m[4..6], m[8..10]): the triple product of the first row with the cross of the others.
    const double a = m[0], b = m[1], c = m[2], d = m[4], e = m[5], f = m[6], g = m[8], h = m[9], i = m[10];
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g);
}

void skin_position(const PoseCache& cache, uint32_t frame, uint32_t vertex, float position[3]) {
    const PoseSkin& skin = cache.skin;
    uint32_t joints[4];
    double weights[4];
    const int count = weighted_influences(skin, vertex, joints, weights);
    const float* rest = &skin.rest_positions[size_t(vertex) * 3];
    double sum[3] = {0, 0, 0};
    for (int k = 0; k < count; ++k) {
        const float* m = joint_matrix(skin, frame, joints[k]);
        for (int row = 0; row < 3; ++row)
            sum[row] += weights[k] * (m[row * 4] * double(rest[0]) + m[row * 4 + 1] * double(rest[1]) + m[row * 4 + 2] * double(rest[2]) +
                                      m[row * 4 + 3]);
    }
    for (int axis = 0; axis < 3; ++axis) position[axis] = float(sum[axis]);
}

void skin_normal(const PoseCache& cache, uint32_t frame, uint32_t vertex, float normal[3]) {
    const PoseSkin& skin = cache.skin;
    uint32_t joints[4];
    double weights[4];
    const int count = weighted_influences(skin, vertex, joints, weights);
    const float* rest = &skin.rest_normals[size_t(vertex) * 3];
    double sum[3] = {0, 0, 0};
    for (int k = 0; k < count; ++k) {
        const float* m = joint_matrix(skin, frame, joints[k]);
        // The 3x3 block L itself (SPEC.md "Skinning"), as mesh.vert.glsl turns the normal.
        for (int row = 0; row < 3; ++row)
            sum[row] += weights[k] * (double(m[row * 4]) * rest[0] + double(m[row * 4 + 1]) * rest[1] + double(m[row * 4 + 2]) * rest[2]);
    }
    const double length = std::sqrt(sum[0] * sum[0] + sum[1] * sum[1] + sum[2] * sum[2]);
    for (int axis = 0; axis < 3; ++axis) normal[axis] = length > 0 ? float(sum[axis] / length) : 0.0f;
}

Status parse_skinned_pose_cache(const uint8_t* data, size_t size, const std::string& file, PoseCache* out) {
    if (Status s = check_common_header(data, size, file, kParse, "CBSK", kPoseCacheHeaderSize, kSkinnedPoseCacheVersion); !s) return s;
    PoseCache cache;
    if (Status s = read_skinned_header(data, file, &cache); !s) return s;
    const uint64_t expected = skinned_pose_cache_file_size(cache.index_count, cache.vertex_count, cache.frame_count, cache.skin.joint_count);
    if (expected != size)
        return make_error(ErrorCode::size_mismatch, kParse, file,
                          "counts imply " + std::to_string(expected) + " bytes, file has " + std::to_string(size));
    read_skinned_sections(data + kPoseCacheHeaderSize, &cache);
    for (auto check : {check_skinned_integers, check_skinned_floats, check_joint_determinants, check_skinned_bounds})
        if (Status s = check(cache, file); !s) return s;
    *out = std::move(cache);
    return {};
}

}  // namespace crowdview
