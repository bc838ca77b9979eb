// The crowd renderer (OpenGL 3.3 core): each archetype's pose caches and textures uploaded
// once, then per frame a few instanced draws per archetype: one per mesh part per mesh LOD, one
// for impostors.
// Needs a current context (gl_context.h). Draws into its own framebuffer, so headless and
// windowed runs render the same pixels.
// Its files, by job: renderer.cpp (the framebuffer, adding archetypes, reading frames back),
// renderer_draw.cpp (a frame's draws), archetype_gpu.* (one archetype's GPU resources),
// crowd_programs.* (the mesh and impostor programs), texture_upload.* (bundle textures into GL),
// gl_programs.* (labels, shader files, GL errors).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "bundle.h"
#include "crowd.h"

namespace crowdview {

enum class ImpostorKind { uv, detail };

struct RendererDesc {
    int width = 1280, height = 720;
    std::string shader_dir;  // holds <name>.<stage>.glsl; "#include" resolves from here
    bool force_cpu_texture_decode = false;  // upload BC textures as decoded RGBA8 even with S3TC
};

struct DrawStats {
    uint32_t draw_calls = 0;
    uint64_t triangles = 0;
};

// Every scene is lit dynamically, as in the paper's test: a sun up and to the side, so the
// normal maps show. Points towards the light.
inline glm::vec3 scene_light_dir() { return glm::normalize(glm::vec3(0.4f, 0.8f, 0.45f)); }

// What the crowd code needs from a bundle (centre, radius, frames, the impostor layout).
CharacterModel character_model(const Bundle& bundle);

// GPU memory one archetype's uploads take (bytes as uploaded: compressed blocks stay compressed;
// mipmapped diffuse maps count their whole chain).
struct ArchetypeMemory {
    uint64_t bodies = 0;     // UVs, indices and pose buffers of the body parts' two mesh LODs
    uint64_t garments = 0;   // the same of the garments'
    uint64_t textures = 0;   // diffuse arrays and the outfit map
    uint64_t impostors = 0;  // normal, UV, detail and surface maps
    uint64_t meshes() const { return bodies + garments; }
    uint64_t total() const { return meshes() + textures + impostors; }
};

struct RendererState;  // renderer_state.h

// Draws a crowd of one or more archetypes (bundles) into one framebuffer. Each bundle's uploads and
// impostor programs (archetype_gpu.h) are made once, for the archetypes drawn from it; each archetype
// has its own instance buffers; the framebuffer and the mesh program are shared.
class Renderer {
public:
    ~Renderer();
    Renderer(const Renderer&) = delete;
    Renderer& operator=(const Renderer&) = delete;

    // The framebuffer and shared programs, no archetype yet; nullptr and a one-line `error`
    // (starting "Renderer::create:") when a shader does not build, GL is too old or the
    // framebuffer cannot be made.
    static std::unique_ptr<Renderer> create(const RendererDesc& desc, std::string* error);
    // create() and add_archetype(bundle): a one-archetype renderer; nullptr and the error of
    // whichever of the two refused.
    static std::unique_ptr<Renderer> create(const Bundle& bundle, const RendererDesc& desc, std::string* error);
    // Uploads a bundle as the next archetype (index archetype_count() - 1). False and a one-line
    // `error` (starting "Renderer::add_archetype:") when the bundle needs more than this renderer
    // supports (archetype_gpu.h, upload_archetype); the renderer and its other archetypes stay usable.
    bool add_archetype(const Bundle& bundle, std::string* error);
    // Adds an archetype drawn with archetype `existing`'s uploads (one bundle named by several
    // archetypes of a crowd): only its instance buffers are new, and memory() counts nothing for it.
    void add_archetype_like(size_t existing);

    // One frame into the offscreen framebuffer: frames[a] are archetype a's instances (at most
    // archetype_count() entries). `light_dir` points towards the light.
    DrawStats draw(const std::vector<FrameInstances>& frames, const Camera& camera, ImpostorKind impostors,
                   const glm::vec3& light_dir);
    // The same for a one-archetype renderer.
    DrawStats draw(const FrameInstances& frame, const Camera& camera, ImpostorKind impostors, const glm::vec3& light_dir);
    // Where build_frames may put the frames for draw(): straight into the archetypes' instance
    // buffers (instance_upload.h), so draw() copies nothing. Draw each frame built there before
    // building the next; frames built into their own vectors are copied in by draw().
    InstanceStorage* instance_storage();

    // Copies the frame to the default framebuffer of a window of this size.
    void present(int window_width, int window_height) const;
    // The frame as RGBA8, top row first (width * height * 4 bytes).
    std::vector<uint8_t> read_rgba() const;
    // Waits until the GPU (or llvmpipe) has finished every command: frame timing.
    void finish() const;
    // With `on`, each draw() is timed on the GPU by a GL_TIME_ELAPSED query (core since GL 3.3):
    // the time the GPU spent on the frame's commands, apart from the CPU's build and its wait.
    void time_draws(bool on);
    // The last timed draw's GPU milliseconds (waits for its result); -1 where no draw was timed.
    double last_draw_gpu_ms() const;

    int width() const { return width_; }
    int height() const { return height_; }
    float aspect() const { return float(width_) / float(height_); }
    size_t archetype_count() const;
    const CharacterModel& model(size_t archetype = 0) const;
    // What the archetype's own uploads take; zero for one added by add_archetype_like.
    ArchetypeMemory memory(size_t archetype) const;
    // The archetype whose uploads `archetype` draws with: itself, or the one add_archetype_like named.
    size_t uploaded_by(size_t archetype) const;
    bool compressed_textures() const { return compressed_; }  // S3TC used, not the CPU decode
    // The blend a frame built for `blend` is drawn with: warp is full where the bundle has no
    // surface map (or more views than CV_MAX_AZIMUTHS x CV_MAX_ELEVATIONS).
    ImpostorBlend effective_blend(ImpostorBlend blend, size_t archetype = 0) const;
    uint32_t triangles_per_character(Lod lod, size_t archetype = 0) const;

private:
    Renderer() = default;
    DrawStats draw_all(const FrameInstances* frames, size_t frame_count, const Camera& camera, ImpostorKind impostors,
                       const glm::vec3& light_dir);
    std::unique_ptr<RendererState> state_;
    int width_ = 0, height_ = 0;
    RendererDesc desc_;
    bool compressed_ = false;
};

// PNG files (stb_image_write / stb_image). rgba: width * height * 4 bytes, top row first.
bool write_png(const std::string& path, int width, int height, const std::vector<uint8_t>& rgba);
bool read_png(const std::string& path, int* width, int* height, std::vector<uint8_t>* rgba);

}  // namespace crowdview
