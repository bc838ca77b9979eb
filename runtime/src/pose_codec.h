// Quantized pose frames (shared_formats/SPEC.md "Pose cache version 2"), without any GL.
//
// A pose cache keeps its frames as version 2 stores them: per frame, the bounds of its positions;
// per vertex and frame, three 16-bit position codes within those bounds and two 16-bit octahedral
// normal codes. mesh.vert.glsl decodes the same codes on the GPU; crowdbake.formats.pose_codec
// writes them.
#pragma once

#include <cstdint>
#include <string>

#include "bundle.h"

namespace crowdview {

constexpr uint32_t kPoseCodeMax = 65535;  // 16 bits per stored coordinate

// Octahedral code of a unit normal (Meyer et al. 2010, section 3.3), each coordinate in 16 bits.
void encode_octahedral(const float normal[3], uint16_t code[2]);
// The unit normal of an octahedral code.
void decode_octahedral(const uint16_t code[2], float normal[3]);

// Position and normal of `vertex` at `frame` (both in range), decoded in float32 as the shader does; a
// skinned cache's (CBSK) skinned from its rest mesh (skinned_pose.h). Every CPU path that reads poses
// goes through these two, so it reads quantized and skinned caches alike.
void decode_pose_position(const PoseCache& cache, uint32_t frame, uint32_t vertex, float position[3]);
void decode_pose_normal(const PoseCache& cache, uint32_t frame, uint32_t vertex, float normal[3]);

// Bytes of a CBPC file of these counts: version 1's float frames, version 2's quantized ones.
uint64_t pose_cache_file_size(uint32_t version, uint32_t index_count, uint32_t vertex_count, uint32_t frame_count);

// The frame sections of a CBPC file whose sizes already agree with its header: `frames` points just after
// the UVs, `bounds` holds the header's bounds (min xyz, max xyz). Version 1's float frames are checked
// (finite, unit normals, inside the bounds) and quantized; version 2's frame bounds are checked (finite,
// min <= max, inside the header's). Fills cache->frame_bounds, position_codes and normal_codes from the
// counts already in `cache`; returns invalid_data naming `file` (messages start with `function`).
Status read_pose_frames(uint32_t version, const uint8_t* frames, const float bounds[6], const std::string& file,
                        const char* function, PoseCache* cache);

}  // namespace crowdview
