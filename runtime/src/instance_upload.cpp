// The per-frame instance upload (instance_upload.h).
#include "instance_upload.h"

#include <time.h>

#include <chrono>

#include <epoxy/gl.h>

namespace crowdview {

namespace {

template <typename T>
uint64_t upload(GLuint buffer, const std::vector<T>& list) {
    const uint64_t bytes = uint64_t(list.size()) * sizeof(T);
    glBindBuffer(GL_ARRAY_BUFFER, buffer);
    glBufferData(GL_ARRAY_BUFFER, GLsizeiptr(bytes), list.empty() ? nullptr : list.data(), GL_STREAM_DRAW);
    return bytes;
}

}  // namespace

uint64_t upload_instances(const FrameInstances& frame, const InstanceBuffers& buffers, std::vector<ImpostorSamples>* nearest_samples) {
    uint64_t bytes = 0;
    for (int lod = 0; lod < 3; ++lod) bytes += upload(buffers.by_lod[lod], frame.by_lod[lod]);
    const std::vector<Instance>& impostors = frame.by_lod[int(Lod::impostor)];
    const std::vector<ImpostorSamples>* samples = &frame.impostor_samples;
    if (samples->size() != impostors.size()) {
        nearest_samples->resize(impostors.size());
        for (size_t i = 0; i < impostors.size(); ++i) {
            ImpostorSamples& s = (*nearest_samples)[i];
            s = ImpostorSamples{};
            for (uint16_t& t : s.tiles) t = impostors[i].tile;
            s.view_weights[0] = 1;
            s.layers[0] = s.layers[1] = impostors[i].frame;
        }
        samples = nearest_samples;
    }
    return bytes + upload(buffers.impostor_samples, *samples);
}

namespace {

double thread_cpu_ms() {
    timespec t;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
    return 1e3 * double(t.tv_sec) + 1e-6 * double(t.tv_nsec);
}

double steady_ms() { return 1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count(); }

}  // namespace

void* MappedInstanceStorage::map(uint32_t buffer, uint64_t bytes) {
    bytes_ += bytes;
    if (bytes == 0) return nullptr;  // a 0-byte range is not mappable; nothing is written there
    glBindBuffer(GL_ARRAY_BUFFER, buffer);
    // Reallocated only to grow (with a quarter to spare, as the counts change with the camera):
    // a new store costs the driver an allocation, and llvmpipe zeroes it: 0.4-0.8 ms a frame for
    // 5.6 MB (services/benchmarks/LOG.md). Draws read only the frame's count.
    GLint64 capacity = 0;
    glGetBufferParameteri64v(GL_ARRAY_BUFFER, GL_BUFFER_SIZE, &capacity);
    if (uint64_t(capacity) < bytes) glBufferData(GL_ARRAY_BUFFER, GLsizeiptr(bytes + bytes / 4), nullptr, GL_STREAM_DRAW);
    // Write-only, the old contents invalidated: a driver whose draws still read last frame's
    // instances gives a fresh store (or waits for them); none is read back.
    void* place = glMapBufferRange(GL_ARRAY_BUFFER, 0, GLsizeiptr(bytes), GL_MAP_WRITE_BIT | GL_MAP_INVALIDATE_BUFFER_BIT);
    mapped_.push_back({buffer, bytes, {}});
    if (!place) {  // the driver would not map it (out of address space, say): build in memory, copy at close
        ++failed_maps_;
        mapped_.back().scratch.resize(bytes);
        place = mapped_.back().scratch.data();  // a moved vector keeps its memory: stays valid as mapped_ grows
    }
    return place;
}

InstancePlaces MappedInstanceStorage::open(size_t archetype, const uint32_t sizes[3], bool samples) {
    const double start = thread_cpu_ms(), wall_start = steady_ms();
    if (!frame_open_) bytes_ = 0, frame_open_ = true;  // the frame's first archetype
    const InstanceBuffers& b = buffers.at(archetype);
    InstancePlaces places{};
    for (int l = 0; l < 3; ++l) places.by_lod[l] = static_cast<Instance*>(map(b.by_lod[l], uint64_t(sizes[l]) * sizeof(Instance)));
    const uint64_t sample_bytes = samples ? uint64_t(sizes[int(Lod::impostor)]) * sizeof(ImpostorSamples) : 0;
    places.impostor_samples = static_cast<ImpostorSamples*>(map(b.impostor_samples, sample_bytes));
    cpu_ms_ += thread_cpu_ms() - start, wall_ms_ += steady_ms() - wall_start;
    return places;
}

void MappedInstanceStorage::close() {
    const double start = thread_cpu_ms(), wall_start = steady_ms();
    for (Mapped& m : mapped_) {
        glBindBuffer(GL_ARRAY_BUFFER, m.buffer);
        if (!m.scratch.empty()) {
            glBufferSubData(GL_ARRAY_BUFFER, 0, GLsizeiptr(m.bytes), m.scratch.data());
        } else if (glUnmapBuffer(GL_ARRAY_BUFFER) == GL_FALSE) {
            ++lost_unmaps_;  // the contents are undefined (a display mode change, say): this frame draws them as they are
        }
    }
    mapped_.clear();
    frame_open_ = false;
    cpu_ms_ += thread_cpu_ms() - start, wall_ms_ += steady_ms() - wall_start;
}

}  // namespace crowdview
