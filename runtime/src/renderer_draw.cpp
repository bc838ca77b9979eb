// One frame of the crowd: per archetype its instances, one instanced draw per mesh part per mesh
// LOD, then one of its impostors (see renderer.h, Renderer::draw).
#include <glm/gtc/type_ptr.hpp>

#include <utility>

#include "config.h"
#include "renderer.h"
#include "renderer_state.h"

namespace crowdview {

namespace {

// The overcast sky every frame starts from.
constexpr float kSky[4] = {0.62f, 0.70f, 0.78f, 1.0f};

void add(DrawStats* total, const DrawStats& more) {
    total->draw_calls += more.draw_calls;
    total->triangles += more.triangles;
}

// This frame's instances into the archetype's buffers, one per LOD, and the impostors' blend
// samples; a frame built in the instance storage is there already.
void upload_frame(RendererState& shared, const InstanceBuffers& buffers, const FrameInstances& frame) {
    if (!frame.in_storage) upload_instances(frame, buffers, &shared.nearest_samples);
}

// The camera and light of this frame into both mesh programs (quantized and skinned); leaves neither in use.
void set_mesh_view(const RendererState& shared, const glm::mat4& view_projection, const glm::vec3& light) {
    const std::pair<GLuint, const MeshUniforms*> programs[] = {{shared.mesh_program, &shared.mesh_uniforms},
                                                               {shared.skinned_mesh_program, &shared.skinned_mesh_uniforms}};
    for (const auto& [program, mu] : programs) {
        glUseProgram(program);
        glUniformMatrix4fv(mu->view_projection, 1, GL_FALSE, glm::value_ptr(view_projection));
        glUniform3fv(mu->light_dir, 1, glm::value_ptr(light));
    }
}

// One instanced draw per part per mesh LOD shown, each with the program of its pose cache's kind.
DrawStats draw_meshes(const RendererState& shared, const ArchetypeGpu& g, const FrameInstances& frame,
                      const glm::mat4& view_projection, const glm::vec3& light) {
    DrawStats stats;
    set_mesh_view(shared, view_projection, light);
    for (const MeshPart& p : g.parts) {
        const GLsizei count = GLsizei(frame.shown[int(p.lod)]);
        if (count == 0) continue;
        const bool skinned = p.joint_count > 0;
        const MeshUniforms& mu = skinned ? shared.skinned_mesh_uniforms : shared.mesh_uniforms;
        glUseProgram(skinned ? shared.skinned_mesh_program : shared.mesh_program);
        // Bodies are closed: skip their back faces. Garments are open cloth, seen from inside too.
        if (p.garment) glDisable(GL_CULL_FACE);
        else glEnable(GL_CULL_FACE);
        // By stream (PoseStream or SkinStream): config.h gives both kinds' streams these units.
        const GLenum pose_units[kPoseStreams] = {CV_UNIT_POSES, CV_UNIT_POSE_NORMALS, CV_UNIT_POSE_FRAME_BOUNDS, CV_UNIT_SKIN_JOINTS,
                                                 CV_UNIT_SKIN_WEIGHTS};
        for (int k = 0; k < kPoseStreams; ++k) {
            glActiveTexture(GL_TEXTURE0 + pose_units[k]);
            glBindTexture(GL_TEXTURE_BUFFER, p.pose_textures[k]);
        }
        glActiveTexture(GL_TEXTURE0 + CV_UNIT_DIFFUSE0);
        glBindTexture(GL_TEXTURE_2D_ARRAY, g.diffuse[p.material]);
        glUniform1i(mu.vertex_count, GLint(p.vertex_count));
        glUniform1i(mu.joint_count, GLint(p.joint_count));
        glUniform1i(mu.variations, g.variations[p.material]);
        glUniform1i(mu.has_regions, g.has_regions[p.material] ? 1 : 0);
        glBindVertexArray(p.vao);
        glDrawElementsInstanced(GL_TRIANGLES, GLsizei(p.index_count), GL_UNSIGNED_INT, nullptr, count);
        ++stats.draw_calls;
        stats.triangles += uint64_t(p.index_count / 3) * uint64_t(count);
    }
    glDisable(GL_CULL_FACE);
    return stats;
}

// The impostor maps and every material unit; units past the archetype's materials get the empty array.
void bind_impostor_textures(const RendererState& shared, const ArchetypeGpu& g, const ImpostorUniforms& iu) {
    glActiveTexture(GL_TEXTURE0 + CV_UNIT_IMPOSTOR_NORMAL);
    glBindTexture(GL_TEXTURE_2D_ARRAY, g.normal_map);
    glActiveTexture(GL_TEXTURE0 + CV_UNIT_IMPOSTOR_UV);
    glBindTexture(GL_TEXTURE_2D_ARRAY, g.uv_map);
    glActiveTexture(GL_TEXTURE0 + CV_UNIT_IMPOSTOR_DETAIL);
    glBindTexture(GL_TEXTURE_2D_ARRAY, g.detail_map);
    glActiveTexture(GL_TEXTURE0 + CV_UNIT_IMPOSTOR_SURFACE);
    glBindTexture(GL_TEXTURE_2D_ARRAY, g.surface_map ? g.surface_map : shared.empty_array);
    for (int k = 0; k < CV_MAX_MATERIALS; ++k) {
        const bool used = size_t(k) < g.diffuse.size();
        glActiveTexture(GL_TEXTURE0 + CV_UNIT_DIFFUSE0 + k);
        glBindTexture(GL_TEXTURE_2D_ARRAY, used ? g.diffuse[k] : shared.empty_array);
        glUniform1i(iu.variations[k], used ? g.variations[k] : 1);
        glUniform1i(iu.has_regions[k], used && g.has_regions[k] ? 1 : 0);
    }
}

// One instanced draw of camera-facing quads, with the program of `impostors` and the frame's blend.
DrawStats draw_impostors(const RendererState& shared, const ArchetypeGpu& g, const FrameInstances& frame,
                         const glm::mat4& view_projection, const Camera& camera, ImpostorKind impostors, const glm::vec3& light) {
    DrawStats stats;
    const uint32_t quads = frame.shown[int(Lod::impostor)];
    if (quads == 0) return stats;
    const int kind = int(impostors), blend = int(g.drawn_blend(frame.blend));
    const ImpostorUniforms& iu = g.impostor_uniforms[kind][blend];
    glUseProgram(g.impostor_programs[kind][blend]);
    glUniformMatrix4fv(iu.view_projection, 1, GL_FALSE, glm::value_ptr(view_projection));
    glUniform3fv(iu.light_dir, 1, glm::value_ptr(light));
    glUniform3fv(iu.camera_position, 1, glm::value_ptr(camera.position));
    glUniform3fv(iu.center, 1, glm::value_ptr(g.model.center));
    glUniform1f(iu.radius, g.model.radius);
    glUniform1i(iu.tile_size, GLint(g.tile_size));
    glUniform1i(iu.azimuth_count, GLint(g.azimuth_count));
    glUniform4i(iu.crop, GLint(g.crop.x), GLint(g.crop.y), GLint(g.crop.width), GLint(g.crop.height));
    glUniform1i(iu.material_count, GLint(g.diffuse.size()));
    glUniform1i(iu.has_surface, g.surface_map ? 1 : 0);  // its alpha: the silhouette's coverage, in every blend
    bind_impostor_textures(shared, g, iu);
    glBindVertexArray(g.impostor_vao);
    // Soft silhouettes (config.h CV_EDGE_LOW) mix over what is already drawn. Edge pixels still
    // write depth, so an impostor behind one, drawn later, shows the background there instead.
    glEnable(GL_BLEND);
    glBlendFuncSeparate(GL_SRC_ALPHA, GL_ONE_MINUS_SRC_ALPHA, GL_ONE, GL_ONE_MINUS_SRC_ALPHA);
    glDrawArraysInstanced(GL_TRIANGLE_STRIP, 0, 4, GLsizei(quads));
    glDisable(GL_BLEND);
    ++stats.draw_calls;
    stats.triangles += 2 * uint64_t(quads);
    return stats;
}

}  // namespace

DrawStats Renderer::draw(const FrameInstances& frame, const Camera& camera, ImpostorKind impostors,
                         const glm::vec3& light_dir) {
    return draw_all(&frame, 1, camera, impostors, light_dir);
}

DrawStats Renderer::draw(const std::vector<FrameInstances>& frames, const Camera& camera, ImpostorKind impostors,
                         const glm::vec3& light_dir) {
    return draw_all(frames.data(), frames.size(), camera, impostors, light_dir);
}

DrawStats Renderer::draw_all(const FrameInstances* frames, size_t frame_count, const Camera& camera, ImpostorKind impostors,
                             const glm::vec3& light_dir) {
    RendererState& shared = *state_;
    DrawStats stats;
    if (shared.draws_timed) glBeginQuery(GL_TIME_ELAPSED, shared.draw_time_query);
    glBindFramebuffer(GL_FRAMEBUFFER, shared.framebuffer);
    glViewport(0, 0, width_, height_);
    glClearColor(kSky[0], kSky[1], kSky[2], kSky[3]);
    glClear(GL_COLOR_BUFFER_BIT | GL_DEPTH_BUFFER_BIT);
    glEnable(GL_DEPTH_TEST);
    glDisable(GL_BLEND);
    const glm::mat4 view_projection = camera.projection(aspect()) * camera.view();
    const glm::vec3 light = glm::normalize(light_dir);
    // Each archetype in turn: its instances, then its meshes and its impostors.
    for (size_t a = 0; a < frame_count && a < shared.archetypes.size(); ++a) {
        const ArchetypeGpu& g = *shared.archetypes[a];
        const InstanceBuffers& buffers = shared.storage.buffers[a];
        // Uploads several archetypes share: their VAOs read this archetype's instances now.
        if (shared.archetypes[a].use_count() > 1) point_instance_attributes(g, buffers);
        upload_frame(shared, buffers, frames[a]);
        glActiveTexture(GL_TEXTURE0 + CV_UNIT_OUTFITS);
        glBindTexture(GL_TEXTURE_2D, g.outfits);
        add(&stats, draw_meshes(shared, g, frames[a], view_projection, light));
        add(&stats, draw_impostors(shared, g, frames[a], view_projection, camera, impostors, light));
    }
    glBindVertexArray(0);
    if (shared.draws_timed) glEndQuery(GL_TIME_ELAPSED);
    return stats;
}

}  // namespace crowdview
