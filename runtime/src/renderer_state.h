// What a Renderer holds (renderer.h), shared by the files that make it
// (renderer.cpp) and draw with it (renderer_draw.cpp): the framebuffer and mesh program every
// archetype shares, and each archetype's GPU resources (archetype_gpu.h), in upload order.
// Destroying it frees every GL object, archetypes first, so it needs the context that made it.
#pragma once

#include <epoxy/gl.h>

#include <memory>
#include <vector>

#include "archetype_gpu.h"
#include "crowd_programs.h"
#include "instance_upload.h"
#include "renderer.h"

namespace crowdview {

struct RendererState {
    GLuint framebuffer = 0, color = 0, depth = 0;
    GLuint mesh_program = 0;  // quantized pose caches (CBPC)
    MeshUniforms mesh_uniforms;
    GLuint skinned_mesh_program = 0;  // skinned ones (CBSK)
    MeshUniforms skinned_mesh_uniforms;
    GLuint empty_array = 0;  // bound to unused material units so every sampler is complete
    GLuint draw_time_query = 0;  // GL_TIME_ELAPSED around draw_all, made on the first timed draw
    bool draws_timed = false;
    std::vector<ImpostorSamples> nearest_samples;  // for frames built without samples
    MappedInstanceStorage storage;                 // every archetype's instance buffers, by index
    // By renderer archetype: its uploads, shared by the archetypes drawn from one bundle
    // (Renderer::add_archetype_like), and the archetype that made them (itself, or the first).
    std::vector<std::shared_ptr<ArchetypeGpu>> archetypes;
    std::vector<size_t> uploaded_by;
    std::vector<InstanceBuffers> like_instances;  // the instance buffers made for sharing archetypes

    RendererState() = default;
    RendererState(const RendererState&) = delete;
    RendererState& operator=(const RendererState&) = delete;
    ~RendererState() {
        for (const InstanceBuffers& b : like_instances) {
            GLuint buffers[] = {b.by_lod[0], b.by_lod[1], b.by_lod[2], b.impostor_samples};
            glDeleteBuffers(4, buffers);
        }
        archetypes.clear();
        glDeleteTextures(1, &empty_array);
        if (draw_time_query) glDeleteQueries(1, &draw_time_query);
        glDeleteProgram(mesh_program);
        glDeleteProgram(skinned_mesh_program);
        glDeleteFramebuffers(1, &framebuffer);
        GLuint renderbuffers[] = {color, depth};
        glDeleteRenderbuffers(2, renderbuffers);
    }
};

}  // namespace crowdview
