// The per-frame instance upload (instance_upload.h).
#include "instance_upload.h"

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

}  // namespace crowdview
