// Impostor blending, without GL: which baked views and frames an impostor mixes, and with what
// weights. The paper shows the nearest view of the nearest of N baked frames; blending the
// neighbours removes the pop when the camera or the animation crosses from one to the next.
// The renderer samples each (view, frame) pair with that view's own UV map texel and blends
// the resulting colours, normals and coverage (impostor_uv.frag.glsl), never the texture
// coordinates. runtime/README.md ("Impostor blending") writes these rules out for the bake.
#pragma once

#include <cstdint>
#include <vector>

#include <glm/glm.hpp>

namespace crowdview {

// --impostor-blend: off is the paper (nearest view, nearest frame); warp is full blending with
// every sample reprojected by the bundle's surface map (shaders/impostor_warp.glsl), drawn as
// full where a bundle has no surface map.
enum class ImpostorBlend { off, views, frames, full, warp };

// Up to four atlas tiles (azimuth + elevation * azimuth_count) and their weights, summing to 1;
// unused entries have weight 0 (and repeat a used tile).
struct ViewWeights {
    uint32_t tiles[4] = {0, 0, 0, 0};
    float weights[4] = {1, 0, 0, 0};
};

// Two atlas layers (indices into frame_indices) and the weight of the second; the first has
// 1 - weight.
struct FrameWeights {
    uint32_t layers[2] = {0, 0};
    float weight = 0;
};

// The camera direction in the character's frame as the bake's azimuth and elevation, in
// degrees: `to_camera` points from the bounds centre to the camera (world space, any length
// > 0; zero gives azimuth 0, elevation 0), `heading` is the character's (radians about +Y).
// SPEC.md: the bake camera (t, p) sits at (sin t cos p, sin p, cos t cos p).
glm::vec2 view_angles_deg(const glm::vec3& to_camera, float heading);

// Bilinear over azimuth x elevation. Azimuth: the two baked azimuths either side of the
// camera's around the ring (wrapping at 360; one azimuth: that one alone), weighted by
// angular distance. Elevation: the camera's elevation clamped to the baked range, then the
// two baked elevations either side (equal: that one alone), weighted linearly. Tile (a, e)
// gets w_a * w_e. Azimuths and elevations need not be sorted; neither may be empty.
ViewWeights blend_view_weights(const glm::vec2& angles_deg, const std::vector<float>& azimuths_deg,
                               const std::vector<float>& elevations_deg);

// The nearest tile alone (the paper's choice; ties go to the lower index), as ViewWeights.
ViewWeights nearest_view_weights(const glm::vec2& angles_deg, const std::vector<float>& azimuths_deg,
                                 const std::vector<float>& elevations_deg);

// The baked frames either side of cycle frame `frame` around the cycle (frame_indices
// ascending, not empty, each < frame_count), weighted linearly by frame distance, wrapping
// from the last baked frame to the first through frame_count.
FrameWeights blend_frame_weights(uint32_t frame, const std::vector<uint32_t>& frame_indices, uint32_t frame_count);

}  // namespace crowdview
