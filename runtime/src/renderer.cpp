// The renderer's framebuffer, its archetypes and reading frames back (see renderer.h); a frame's
// draws are in renderer_draw.cpp.
#include "renderer.h"

#include <algorithm>
#include <cstring>

#define STB_IMAGE_IMPLEMENTATION
#define STBI_ONLY_PNG
#include <stb/stb_image.h>
#define STB_IMAGE_WRITE_IMPLEMENTATION
#include <stb/stb_image_write.h>

#include "config.h"
#include "gl_programs.h"
#include "renderer_state.h"
#include "texture_upload.h"

namespace crowdview {

static_assert(CV_MAX_MATERIALS == 4 && CV_UNIT_DIFFUSE0 + CV_MAX_MATERIALS <= 16,
              "impostor_uv.frag.glsl unrolls four materials; GL 3.3 promises 16 texture units");

namespace {

// The framebuffer every frame is drawn into: RGBA8 colour and 24-bit depth renderbuffers.
// False where the driver reports it incomplete.
bool make_framebuffer(int width, int height, RendererState* state) {
    glGenFramebuffers(1, &state->framebuffer);
    glBindFramebuffer(GL_FRAMEBUFFER, state->framebuffer);
    label(GL_FRAMEBUFFER, state->framebuffer, "frame");
    glGenRenderbuffers(1, &state->color);
    glBindRenderbuffer(GL_RENDERBUFFER, state->color);
    glRenderbufferStorage(GL_RENDERBUFFER, GL_RGBA8, width, height);
    label(GL_RENDERBUFFER, state->color, "frame:color");
    glGenRenderbuffers(1, &state->depth);
    glBindRenderbuffer(GL_RENDERBUFFER, state->depth);
    glRenderbufferStorage(GL_RENDERBUFFER, GL_DEPTH_COMPONENT24, width, height);
    label(GL_RENDERBUFFER, state->depth, "frame:depth");
    glFramebufferRenderbuffer(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_RENDERBUFFER, state->color);
    glFramebufferRenderbuffer(GL_FRAMEBUFFER, GL_DEPTH_ATTACHMENT, GL_RENDERBUFFER, state->depth);
    return glCheckFramebufferStatus(GL_FRAMEBUFFER) == GL_FRAMEBUFFER_COMPLETE;
}

}  // namespace

CharacterModel character_model(const Bundle& bundle) {
    const Manifest& m = bundle.manifest;
    CharacterModel model;
    model.center = glm::vec3(m.impostor.center[0], m.impostor.center[1], m.impostor.center[2]);
    model.radius = m.impostor.radius;
    model.frames_per_second = float(m.frames_per_second);
    model.frame_count = m.pose_frames;
    for (const ClipInfo& c : m.clips) model.clips.push_back({c.name, c.first_frame, c.frames});
    for (const TransitionInfo& t : m.transitions)
        model.transitions.push_back({t.from_clip, t.to_clip, t.leave_frame, t.arrive_frame, t.first_frame, t.frames});
    model.tile_size = m.impostor.tile_size;
    model.azimuths_deg = m.impostor.azimuths_deg;
    model.elevations_deg = m.impostor.elevations_deg;
    model.frame_indices = m.impostor.frame_indices;
    model.has_low = std::any_of(m.meshes.begin(), m.meshes.end(), [](const MeshInfo& mesh) { return mesh.lod == 1; });
    return model;
}

std::unique_ptr<Renderer> Renderer::create(const RendererDesc& desc, std::string* error) {
    const std::string fn = "Renderer::create: ";
    if (epoxy_gl_version() < 33) {
        *error = fn + "OpenGL 3.3 is needed, the context offers " + std::to_string(epoxy_gl_version());
        return nullptr;
    }
    enable_labels_if_supported();
    std::unique_ptr<Renderer> r(new Renderer());
    r->state_ = std::make_unique<RendererState>();
    RendererState& state = *r->state_;
    r->width_ = desc.width;
    r->height_ = desc.height;
    r->desc_ = desc;
    r->compressed_ = !desc.force_cpu_texture_decode && epoxy_has_gl_extension("GL_EXT_texture_compression_s3tc");
    std::string program_error;
    state.mesh_program = build_mesh_program(desc.shader_dir, false, &state.mesh_uniforms, &program_error);
    if (state.mesh_program)
        state.skinned_mesh_program = build_mesh_program(desc.shader_dir, true, &state.skinned_mesh_uniforms, &program_error);
    if (!state.mesh_program || !state.skinned_mesh_program) {
        *error = fn + program_error;
        return nullptr;
    }
    state.empty_array = upload_unused_material_array();
    if (!make_framebuffer(desc.width, desc.height, &state)) {
        *error = fn + "the " + std::to_string(desc.width) + "x" + std::to_string(desc.height) + " framebuffer is incomplete";
        return nullptr;
    }
    if (GLenum e = glGetError(); e != GL_NO_ERROR) {
        *error = fn + gl_error_text(e) + " while making the framebuffer and programs";
        return nullptr;
    }
    return r;
}

std::unique_ptr<Renderer> Renderer::create(const Bundle& bundle, const RendererDesc& desc, std::string* error) {
    std::unique_ptr<Renderer> r = create(desc, error);
    if (!r || !r->add_archetype(bundle, error)) return nullptr;
    return r;
}

bool Renderer::add_archetype(const Bundle& bundle, std::string* error) {
    std::string refusal;
    std::unique_ptr<ArchetypeGpu> archetype = upload_archetype(bundle, desc_, &refusal);
    if (!archetype) {
        *error = "Renderer::add_archetype: " + refusal;
        return false;
    }
    state_->storage.buffers.push_back(archetype->instance_targets());
    state_->uploaded_by.push_back(state_->archetypes.size());
    state_->archetypes.push_back(std::move(archetype));
    return true;
}

void Renderer::add_archetype_like(size_t existing) {
    const size_t owner = state_->uploaded_by.at(existing);
    InstanceBuffers buffers;
    GLuint names[4];
    glGenBuffers(4, names);
    const char* labels[] = {"instances:high", "instances:low", "instances:impostor", "instances:impostor-samples"};
    for (int i = 0; i < 4; ++i) {
        glBindBuffer(GL_ARRAY_BUFFER, names[i]);  // a name becomes a buffer when first bound
        label(GL_BUFFER, names[i], labels[i] + std::string(":archetype ") + std::to_string(state_->archetypes.size()));
    }
    std::copy(names, names + 3, buffers.by_lod);
    buffers.impostor_samples = names[3];
    state_->like_instances.push_back(buffers);
    state_->storage.buffers.push_back(buffers);
    state_->uploaded_by.push_back(owner);
    state_->archetypes.push_back(state_->archetypes[owner]);
}

Renderer::~Renderer() = default;

size_t Renderer::archetype_count() const { return state_->archetypes.size(); }
const CharacterModel& Renderer::model(size_t archetype) const { return state_->archetypes.at(archetype)->model; }
ArchetypeMemory Renderer::memory(size_t archetype) const {
    return uploaded_by(archetype) == archetype ? state_->archetypes[archetype]->memory : ArchetypeMemory();
}
size_t Renderer::uploaded_by(size_t archetype) const { return state_->uploaded_by.at(archetype); }

uint32_t Renderer::triangles_per_character(Lod lod, size_t archetype) const {
    if (lod == Lod::impostor) return 2;
    uint32_t triangles = 0;
    for (const MeshPart& p : state_->archetypes.at(archetype)->parts)
        if (p.lod == lod) triangles += p.index_count / 3;
    return triangles;
}

InstanceStorage* Renderer::instance_storage() { return &state_->storage; }

ImpostorBlend Renderer::effective_blend(ImpostorBlend blend, size_t archetype) const {
    return state_->archetypes.at(archetype)->drawn_blend(blend);
}

void Renderer::present(int window_width, int window_height) const {
    glBindFramebuffer(GL_READ_FRAMEBUFFER, state_->framebuffer);
    glBindFramebuffer(GL_DRAW_FRAMEBUFFER, 0);
    glBlitFramebuffer(0, 0, width_, height_, 0, 0, window_width, window_height, GL_COLOR_BUFFER_BIT, GL_LINEAR);
    glBindFramebuffer(GL_FRAMEBUFFER, state_->framebuffer);
}

std::vector<uint8_t> Renderer::read_rgba() const {
    std::vector<uint8_t> bottom_up(size_t(width_) * height_ * 4), rgba(bottom_up.size());
    glBindFramebuffer(GL_READ_FRAMEBUFFER, state_->framebuffer);
    glPixelStorei(GL_PACK_ALIGNMENT, 1);
    glReadPixels(0, 0, width_, height_, GL_RGBA, GL_UNSIGNED_BYTE, bottom_up.data());
    const size_t row = size_t(width_) * 4;
    for (int y = 0; y < height_; ++y) std::memcpy(&rgba[y * row], &bottom_up[(height_ - 1 - y) * row], row);
    return rgba;
}

void Renderer::finish() const { glFinish(); }

void Renderer::time_draws(bool on) {
    if (on && !state_->draw_time_query) glGenQueries(1, &state_->draw_time_query);
    state_->draws_timed = on;
}

double Renderer::last_draw_gpu_ms() const {
    if (!state_->draw_time_query || !state_->draws_timed) return -1.0;
    GLuint64 nanoseconds = 0;
    glGetQueryObjectui64v(state_->draw_time_query, GL_QUERY_RESULT, &nanoseconds);
    return 1e-6 * double(nanoseconds);
}

bool write_png(const std::string& path, int width, int height, const std::vector<uint8_t>& rgba) {
    if (rgba.size() != size_t(width) * height * 4) return false;
    return stbi_write_png(path.c_str(), width, height, 4, rgba.data(), width * 4) != 0;
}

bool read_png(const std::string& path, int* width, int* height, std::vector<uint8_t>* rgba) {
    int channels = 0;
    unsigned char* pixels = stbi_load(path.c_str(), width, height, &channels, 4);
    if (!pixels) return false;
    rgba->assign(pixels, pixels + size_t(*width) * *height * 4);
    stbi_image_free(pixels);
    return true;
}

}  // namespace crowdview
