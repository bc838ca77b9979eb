// Skinned pose caches (shared_formats/SPEC.md "Skinned pose cache": CBSK, format version 4), without any GL.
//
// A skinned body stores its rest mesh, four joint influences a vertex and each joint's 3x4 skinning
// matrix per frame; a frame is the rest mesh skinned by linear blending (glTF 2.0 section 3.7.3):
//   p = sum_k w_k A_k (rest_position, 1),   n = normalize(sum_k w_k L_k^-T rest_normal),
// A_k the matrix of the vertex's k-th joint at the frame, L_k its left 3x3 block, w_k = code / 65535.
// mesh.vert.glsl (CV_SKINNED) skins the same way on the GPU, L^-T as the cofactor matrix over the
// determinant; these are the CPU's copy, for the parser's bounds check and for every CPU path that
// reads poses (pose_codec.h decode_pose_position, decode_pose_normal).
#pragma once

#include <cstdint>

#include "bundle.h"

namespace crowdview {

constexpr uint32_t kWeightCodeSum = 65535;  // each vertex's four weight codes sum to exactly this

// Bytes of a CBSK file of these counts (below 2^64 for any u32 counts and joint_count <= kMaxJoints).
uint64_t skinned_pose_cache_file_size(uint32_t index_count, uint32_t vertex_count, uint32_t frame_count, uint32_t joint_count);

// The 12 floats (three rows of four) of `joint`'s matrix at `frame`: index (frame * joint_count + joint) * 12.
inline const float* joint_matrix(const PoseSkin& skin, uint32_t frame, uint32_t joint) {
    return &skin.matrices[(size_t(frame) * skin.joint_count + joint) * 12];
}

// The determinant of the left 3x3 block of a 3x4 row-major matrix.
double joint_determinant(const float* matrix);

// `vertex` (in range) of a skinned cache at `frame` (in range), in double precision rounded to float32 at
// the end. Influences of weight 0 are skipped, so a singular matrix there never reaches the normal.
void skin_position(const PoseCache& cache, uint32_t frame, uint32_t vertex, float position[3]);
void skin_normal(const PoseCache& cache, uint32_t frame, uint32_t vertex, float normal[3]);

}  // namespace crowdview
