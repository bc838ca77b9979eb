// The per-frame instance upload: one archetype's instance lists and impostor samples into its GL
// buffers. The renderer's draw and the frame benchmark (frame_bench.cpp) call the same code, so
// the benchmark's upload figure is the renderer's. Needs a current context (gl_context.h).
#pragma once

#include <cstdint>
#include <vector>

#include "crowd.h"

namespace crowdview {

// The buffers an archetype's instances go to: GL buffer names (GLuint), made by the caller.
struct InstanceBuffers {
    uint32_t by_lod[3] = {0, 0, 0};  // struct Instance, one list per Lod
    uint32_t impostor_samples = 0;   // struct ImpostorSamples, one per impostor
};

// Uploads `frame`'s lists into `buffers`, each buffer orphaned by glBufferData so the driver need
// not wait for draws still reading last frame's. A frame built without impostor samples gets each
// impostor's nearest view and frame (its Instance's tile and layer), made in `nearest_samples`
// (the caller's scratch, grown as needed). Leaves GL_ARRAY_BUFFER bound to the samples buffer.
// Returns the bytes uploaded.
uint64_t upload_instances(const FrameInstances& frame, const InstanceBuffers& buffers, std::vector<ImpostorSamples>* nearest_samples);

}  // namespace crowdview
