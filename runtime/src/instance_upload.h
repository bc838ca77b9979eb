// The per-frame instances into GL buffers, two ways: built straight into mapped buffer memory
// (MappedInstanceStorage, crowdview's frame loop), or built into vectors and copied (upload_instances,
// for frames built without it). The renderer and the frame benchmark (frame_bench.cpp) use the same
// code, so the benchmark's figures are the renderer's. Needs a current context (gl_context.h).
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

// build_frames' lists (crowd.h InstanceStorage) written straight into the archetypes' GL buffers:
// open() maps the start of each buffer, list-sized (glMapBufferRange, write-only, the whole buffer
// invalidated), growing a buffer first where the list outgrew it; close() unmaps them all. A
// buffer may so be larger than its list: draw the frame's counts (FrameInstances::shown). GL 3.3
// core. Leaves GL_ARRAY_BUFFER bound to the last buffer it touched.
class MappedInstanceStorage : public InstanceStorage {
public:
    std::vector<InstanceBuffers> buffers;  // one per archetype, by build_frames' index

    InstancePlaces open(size_t archetype, const uint32_t sizes[3], bool samples) override;
    void close() override;
    bool always_samples() const override { return true; }

    uint64_t bytes() const { return bytes_; }              // the last frame's lists (for figures)
    double cpu_ms() const { return cpu_ms_; }              // the calling thread's CPU time in open and close, all frames
    double wall_ms() const { return wall_ms_; }            // and the wall-clock time
    uint64_t failed_maps() const { return failed_maps_; }  // lists the driver would not map (copied instead)
    uint64_t lost_unmaps() const { return lost_unmaps_; }  // unmaps that reported the contents lost

private:
    struct Mapped {
        uint32_t buffer;
        uint64_t bytes;
        std::vector<uint8_t> scratch;  // where the driver would not map: written here, copied at close
    };
    void* map(uint32_t buffer, uint64_t bytes);
    std::vector<Mapped> mapped_;
    bool frame_open_ = false;  // open() was called since the last close()
    uint64_t bytes_ = 0, failed_maps_ = 0, lost_unmaps_ = 0;
    double cpu_ms_ = 0, wall_ms_ = 0;
};

}  // namespace crowdview
