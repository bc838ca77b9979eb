// OpenGL 3.3 core renderer: uploads once, then instanced draws per LOD (see renderer.h).
#include "renderer.h"
#include "instance_upload.h"

#include <epoxy/gl.h>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>

#include <glm/gtc/type_ptr.hpp>

#define STB_IMAGE_IMPLEMENTATION
#define STBI_ONLY_PNG
#include <stb/stb_image.h>
#define STB_IMAGE_WRITE_IMPLEMENTATION
#include <stb/stb_image_write.h>

#include "config.h"

namespace crowdview {

static_assert(CV_MAX_MATERIALS == 4 && CV_UNIT_DIFFUSE0 + CV_MAX_MATERIALS <= 16,
              "impostor_uv.frag.glsl unrolls four materials; GL 3.3 promises 16 texture units");

namespace {

// ---------------------------------------------------------------------------------------
// Labels and shaders

bool g_has_labels = false;

// Names a GL object for debuggers (apitrace, RenderDoc); a no-op without KHR_debug.
void label(GLenum identifier, GLuint name, const std::string& text) {
    if (g_has_labels) glObjectLabel(identifier, name, GLsizei(text.size()), text.c_str());
}

bool read_text(const std::string& path, std::string* text) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return false;
    std::stringstream ss;
    ss << in.rdbuf();
    *text = ss.str();
    return true;
}

// `<dir>/<file>` with each `#include "x"` line replaced by `<dir>/x` (one level: config.h).
bool load_shader_source(const std::string& dir, const std::string& file, std::string* source, std::string* error) {
    std::string text;
    if (!read_text(dir + "/" + file, &text)) {
        *error = "cannot read " + dir + "/" + file;
        return false;
    }
    std::istringstream lines(text);
    std::string line;
    source->clear();
    while (std::getline(lines, line)) {
        const size_t open = line.find("#include \"");
        if (open != std::string::npos && line.find_first_not_of(" \t") == open) {
            const size_t close = line.find('"', open + 10);
            std::string included;
            if (close == std::string::npos || !read_text(dir + "/" + line.substr(open + 10, close - open - 10), &included)) {
                *error = file + ": cannot resolve " + line;
                return false;
            }
            *source += included + "\n";
        } else {
            *source += line + "\n";
        }
    }
    return true;
}

// `defines` ("#define X 1\n" lines) go right after the #version line, which must come first.
GLuint compile_shader(GLenum stage, const std::string& dir, const std::string& file, const std::string& defines,
                      std::string* error) {
    std::string source;
    if (!load_shader_source(dir, file, &source, error)) return 0;
    if (!defines.empty()) {
        const size_t end_of_version = source.find('\n');
        source.insert(end_of_version == std::string::npos ? source.size() : end_of_version + 1, defines);
    }
    GLuint shader = glCreateShader(stage);
    const char* text = source.c_str();
    glShaderSource(shader, 1, &text, nullptr);
    glCompileShader(shader);
    GLint ok = 0;
    glGetShaderiv(shader, GL_COMPILE_STATUS, &ok);
    if (!ok) {
        char log[2048] = "";
        glGetShaderInfoLog(shader, sizeof log, nullptr, log);
        *error = file + ": " + log;
        glDeleteShader(shader);
        return 0;
    }
    label(GL_SHADER, shader, file);
    return shader;
}

// Program `name` from <name>.vert.glsl (or `vertex_name`) and <name>.frag.glsl, with `defines`.
GLuint build_program(const std::string& dir, const std::string& vertex_name, const std::string& fragment_name,
                     std::string* error, const std::string& defines = "") {
    GLuint vs = compile_shader(GL_VERTEX_SHADER, dir, vertex_name + ".vert.glsl", defines, error);
    if (!vs) return 0;
    GLuint fs = compile_shader(GL_FRAGMENT_SHADER, dir, fragment_name + ".frag.glsl", defines, error);
    if (!fs) {
        glDeleteShader(vs);
        return 0;
    }
    GLuint program = glCreateProgram();
    glAttachShader(program, vs);
    glAttachShader(program, fs);
    glLinkProgram(program);
    glDeleteShader(vs);
    glDeleteShader(fs);
    GLint ok = 0;
    glGetProgramiv(program, GL_LINK_STATUS, &ok);
    if (!ok) {
        char log[2048] = "";
        glGetProgramInfoLog(program, sizeof log, nullptr, log);
        *error = fragment_name + " program: " + log;
        glDeleteProgram(program);
        return 0;
    }
    label(GL_PROGRAM, program, fragment_name);
    return program;
}

GLint uniform(GLuint program, const char* name) { return glGetUniformLocation(program, name); }

// ---------------------------------------------------------------------------------------
// Textures

struct Upload {
    bool s3tc = false;           // driver takes S3TC blocks as they are
    bool force_cpu_decode = false;  // RendererDesc::force_cpu_texture_decode: every block format decoded here
    bool cpu_decode_used = false;
    uint64_t bytes = 0;  // GPU bytes uploaded so far (ArchetypeMemory)
};

// A CBTX as a GL_TEXTURE_2D_ARRAY. BC blocks go up untouched where S3TC is available and
// are decoded to RGBA8 otherwise; rgba16 stays 16-bit and uv32 goes up as one unsigned
// integer a texel (R32UI) for the shader to unpack (UV maps need the bits, SPEC.md); uvblock
// goes up as its blocks, three RG32UI texels each, decoded in impostor_uv_map.glsl.
// `filtered`: trilinear with mipmaps (diffuse maps); otherwise nearest, base level only.
GLuint upload_texture_array(const TextureArray& t, bool filtered, const std::string& name, Upload* upload) {
    GLuint texture = 0;
    glGenTextures(1, &texture);
    glBindTexture(GL_TEXTURE_2D_ARRAY, texture);
    glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
    const GLsizei w = GLsizei(t.width), h = GLsizei(t.height), layers = GLsizei(t.layer_count);
    const bool s3tc = t.format == PixelFormat::bc1 || t.format == PixelFormat::bc2;
    // BC5 (RGTC2) is core since OpenGL 3.0; S3TC needs the extension. Either may be decoded here instead.
    const bool gpu_blocks = t.format == PixelFormat::bc5 ? !upload->force_cpu_decode : s3tc && upload->s3tc;
    if (gpu_blocks) {
        // bc1 is RGB in the spec (normal and surface maps): the RGB flavour keeps alpha at 1.
        const GLenum format = t.format == PixelFormat::bc5   ? GL_COMPRESSED_RG_RGTC2
                              : t.format == PixelFormat::bc1 ? GL_COMPRESSED_RGB_S3TC_DXT1_EXT
                                                             : GL_COMPRESSED_RGBA_S3TC_DXT3_EXT;
        glCompressedTexImage3D(GL_TEXTURE_2D_ARRAY, 0, format, w, h, layers, 0, GLsizei(t.data.size()), t.data.data());
    } else if (s3tc || t.format == PixelFormat::bc5) {
        std::vector<uint8_t> rgba;
        rgba.reserve(size_t(w) * h * 4 * layers);
        for (uint32_t k = 0; k < t.layer_count; ++k) {
            const std::vector<uint8_t> layer = decode_layer_rgba8(t, k);
            rgba.insert(rgba.end(), layer.begin(), layer.end());
        }
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RGBA8, w, h, layers, 0, GL_RGBA, GL_UNSIGNED_BYTE, rgba.data());
        upload->cpu_decode_used = true;
    } else if (t.format == PixelFormat::rgba16) {
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RGBA16, w, h, layers, 0, GL_RGBA, GL_UNSIGNED_SHORT, t.data.data());
    } else if (t.format == PixelFormat::uv32) {  // integer texture: nearest filtering only (set below)
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_R32UI, w, h, layers, 0, GL_RED_INTEGER, GL_UNSIGNED_INT, t.data.data());
    } else if (t.format == PixelFormat::uvblock) {
        // Each 24-byte block is three RG32UI texels in a row: block rows are texture rows, as stored.
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RG32UI, 3 * (w / 4), h / 4, layers, 0, GL_RG_INTEGER, GL_UNSIGNED_INT, t.data.data());
    } else {
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RGBA8, w, h, layers, 0, GL_RGBA, GL_UNSIGNED_BYTE, t.data.data());
    }
    // Bytes as stored on the GPU: blocks as they are, a CPU decode as RGBA8; a mip chain adds a third.
    const uint64_t level0 = gpu_blocks || !(s3tc || t.format == PixelFormat::bc5) ? t.data.size() : uint64_t(w) * h * 4 * layers;
    upload->bytes += filtered ? level0 * 4 / 3 : level0;
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAG_FILTER, filtered ? GL_LINEAR : GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_WRAP_S, filtered ? GL_REPEAT : GL_CLAMP_TO_EDGE);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_WRAP_T, filtered ? GL_REPEAT : GL_CLAMP_TO_EDGE);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAX_LEVEL, 0);
    if (filtered) {
        while (glGetError() != GL_NO_ERROR) {
        }
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAX_LEVEL, 1000);  // the levels glGenerateMipmap fills
        glGenerateMipmap(GL_TEXTURE_2D_ARRAY);
        if (glGetError() == GL_NO_ERROR) {
            glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_LINEAR_MIPMAP_LINEAR);
        } else {  // some drivers cannot mipmap compressed arrays: stay on level 0
            glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAX_LEVEL, 0);
            glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
        }
    }
    label(GL_TEXTURE, texture, name);
    return texture;
}

}  // namespace

// ---------------------------------------------------------------------------------------

struct Renderer::Part {
    GLuint vao = 0, uv_buffer = 0, index_buffer = 0, pose_buffer = 0, pose_texture = 0;
    uint32_t index_count = 0, vertex_count = 0, material = 0;
    Lod lod = Lod::high;
    bool garment = false;
};

static_assert(int(ImpostorBlend::off) == 0 && int(ImpostorBlend::warp) == 4, "impostor programs are indexed by ImpostorBlend");
constexpr int kBlendModes = 5;

namespace {

// Uniform locations, looked up once when a program is linked (-1: the program has no such
// uniform, which glUniform* ignores).
struct MeshUniforms {
    GLint view_projection = -1, light_dir = -1, vertex_count = -1, variations = -1, has_regions = -1;
};

struct ImpostorUniforms {
    GLint view_projection = -1, light_dir = -1, camera_position = -1, center = -1, radius = -1, tile_size = -1,
          azimuth_count = -1, crop = -1, material_count = -1, has_surface = -1;
    GLint variations[CV_MAX_MATERIALS], has_regions[CV_MAX_MATERIALS];
};

MeshUniforms mesh_uniforms(GLuint program) {
    MeshUniforms u;
    u.view_projection = uniform(program, "u_view_projection");
    u.light_dir = uniform(program, "u_light_dir");
    u.vertex_count = uniform(program, "u_vertex_count");
    u.variations = uniform(program, "u_variations");
    u.has_regions = uniform(program, "u_has_regions");
    return u;
}

ImpostorUniforms impostor_uniforms(GLuint program) {
    ImpostorUniforms u;
    u.view_projection = uniform(program, "u_view_projection");
    u.light_dir = uniform(program, "u_light_dir");
    u.camera_position = uniform(program, "u_camera_position");
    u.center = uniform(program, "u_center");
    u.radius = uniform(program, "u_radius");
    u.tile_size = uniform(program, "u_tile_size");
    u.azimuth_count = uniform(program, "u_azimuth_count");
    u.crop = uniform(program, "u_crop");
    u.material_count = uniform(program, "u_material_count");
    u.has_surface = uniform(program, "u_has_surface");
    for (int k = 0; k < CV_MAX_MATERIALS; ++k) {
        const std::string index = "[" + std::to_string(k) + "]";
        u.variations[k] = uniform(program, ("u_variations" + index).c_str());
        u.has_regions[k] = uniform(program, ("u_has_regions" + index).c_str());
    }
    return u;
}

}  // namespace

// One archetype's uploads: its mesh parts, instance buffers, textures and impostor programs
// (their defines follow the bundle's map formats, their uniform arrays its baked views).
struct Renderer::Archetype {
    CharacterModel model;
    ArchetypeMemory memory;
    // Impostor programs by ImpostorKind and ImpostorBlend: each blend mode is its own shader
    // variant with constant sample counts, so blending off costs what the paper's lookup does.
    GLuint impostor_programs[2][kBlendModes] = {};
    ImpostorUniforms impostor_uniforms[2][kBlendModes];
    std::vector<Part> parts;
    GLuint impostor_vao = 0;
    GLuint instance_buffers[3] = {0, 0, 0};  // by Lod
    GLuint impostor_sample_buffer = 0;       // struct ImpostorSamples, one per impostor
    std::vector<GLuint> diffuse;
    std::vector<int> variations;
    std::vector<bool> has_regions;
    GLuint outfits = 0, normal_map = 0, uv_map = 0, detail_map = 0;
    GLuint surface_map = 0;  // 0: the bundle has none (or more views than the warp shader holds), warp draws as full
    uint32_t tile_size = 0, azimuth_count = 0;
    ImpostorCrop crop;

    ~Archetype() {
        for (Part& p : parts) {
            glDeleteVertexArrays(1, &p.vao);
            GLuint buffers[] = {p.uv_buffer, p.index_buffer, p.pose_buffer};
            glDeleteBuffers(3, buffers);
            glDeleteTextures(1, &p.pose_texture);
        }
        glDeleteVertexArrays(1, &impostor_vao);
        glDeleteBuffers(3, instance_buffers);
        glDeleteBuffers(1, &impostor_sample_buffer);
        glDeleteTextures(GLsizei(diffuse.size()), diffuse.data());
        GLuint textures[] = {outfits, normal_map, uv_map, detail_map, surface_map};
        glDeleteTextures(5, textures);
        for (auto& by_blend : impostor_programs)
            for (GLuint program : by_blend) glDeleteProgram(program);
    }
};

// What every archetype shares: the framebuffer and the mesh program.
struct Renderer::Impl {
    GLuint framebuffer = 0, color = 0, depth = 0;
    GLuint mesh_program = 0;
    MeshUniforms mesh_uniforms;
    GLuint empty_array = 0;  // bound to unused material units so every sampler is complete
    std::vector<ImpostorSamples> nearest_samples;  // for frames built without samples
    MappedInstanceStorage storage;                 // every archetype's instance buffers, by index
    std::vector<std::unique_ptr<Archetype>> archetypes;

    ~Impl() {
        archetypes.clear();
        glDeleteTextures(1, &empty_array);
        glDeleteProgram(mesh_program);
        glDeleteFramebuffers(1, &framebuffer);
        GLuint renderbuffers[] = {color, depth};
        glDeleteRenderbuffers(2, renderbuffers);
    }
};


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

// Binds the per-instance attributes (struct Instance) of `buffer` to the bound VAO.
static void bind_instance_attributes(GLuint buffer) {
    glBindBuffer(GL_ARRAY_BUFFER, buffer);
    glEnableVertexAttribArray(CV_ATTR_INSTANCE_POSE);
    glVertexAttribPointer(CV_ATTR_INSTANCE_POSE, 4, GL_FLOAT, GL_FALSE, sizeof(Instance), (void*)offsetof(Instance, position));
    glVertexAttribDivisor(CV_ATTR_INSTANCE_POSE, 1);
    glEnableVertexAttribArray(CV_ATTR_INSTANCE_IDS);
    glVertexAttribIPointer(CV_ATTR_INSTANCE_IDS, 4, GL_UNSIGNED_SHORT, sizeof(Instance), (void*)offsetof(Instance, frame));
    glVertexAttribDivisor(CV_ATTR_INSTANCE_IDS, 1);
}

std::unique_ptr<Renderer> Renderer::create(const RendererDesc& desc, std::string* error) {
    const std::string fn = "Renderer::create: ";
    if (epoxy_gl_version() < 33) {
        *error = fn + "OpenGL 3.3 is needed, the context offers " + std::to_string(epoxy_gl_version());
        return nullptr;
    }
    g_has_labels = epoxy_gl_version() >= 43 || epoxy_has_gl_extension("GL_KHR_debug");

    std::unique_ptr<Renderer> r(new Renderer());
    r->impl_ = std::make_unique<Impl>();
    Impl& g = *r->impl_;
    r->width_ = desc.width;
    r->height_ = desc.height;
    r->desc_ = desc;
    r->compressed_ = !desc.force_cpu_texture_decode && epoxy_has_gl_extension("GL_EXT_texture_compression_s3tc");

    // The mesh program: shader files by name (niagara style), config.h pasted in.
    std::string shader_error;
    g.mesh_program = build_program(desc.shader_dir, "mesh", "mesh", &shader_error);
    if (!g.mesh_program) {
        *error = fn + shader_error;
        return nullptr;
    }
    g.mesh_uniforms = mesh_uniforms(g.mesh_program);
    // Sampler units are fixed (config.h), so they are set once.
    glUseProgram(g.mesh_program);
    glUniform1i(uniform(g.mesh_program, "u_poses"), CV_UNIT_POSES);
    glUniform1i(uniform(g.mesh_program, "u_outfits"), CV_UNIT_OUTFITS);
    glUniform1i(uniform(g.mesh_program, "u_diffuse"), CV_UNIT_DIFFUSE0);
    Upload upload;
    TextureArray empty;
    empty.width = empty.height = empty.layer_count = 1;
    empty.data.assign(4, 255);
    g.empty_array = upload_texture_array(empty, false, "unused-material", &upload);

    // The framebuffer every frame is drawn into.
    glGenFramebuffers(1, &g.framebuffer);
    glBindFramebuffer(GL_FRAMEBUFFER, g.framebuffer);
    label(GL_FRAMEBUFFER, g.framebuffer, "frame");
    glGenRenderbuffers(1, &g.color);
    glBindRenderbuffer(GL_RENDERBUFFER, g.color);
    glRenderbufferStorage(GL_RENDERBUFFER, GL_RGBA8, desc.width, desc.height);
    label(GL_RENDERBUFFER, g.color, "frame:color");
    glGenRenderbuffers(1, &g.depth);
    glBindRenderbuffer(GL_RENDERBUFFER, g.depth);
    glRenderbufferStorage(GL_RENDERBUFFER, GL_DEPTH_COMPONENT24, desc.width, desc.height);
    label(GL_RENDERBUFFER, g.depth, "frame:depth");
    glFramebufferRenderbuffer(GL_FRAMEBUFFER, GL_COLOR_ATTACHMENT0, GL_RENDERBUFFER, g.color);
    glFramebufferRenderbuffer(GL_FRAMEBUFFER, GL_DEPTH_ATTACHMENT, GL_RENDERBUFFER, g.depth);
    if (glCheckFramebufferStatus(GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE) {
        *error = fn + "the " + std::to_string(desc.width) + "x" + std::to_string(desc.height) + " framebuffer is incomplete";
        return nullptr;
    }
    if (GLenum e = glGetError(); e != GL_NO_ERROR) {
        *error = fn + "OpenGL error 0x" + [](GLenum v) {
            char buf[16];
            std::snprintf(buf, sizeof buf, "%04x", v);
            return std::string(buf);
        }(e) + " while uploading the bundle";
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
    const std::string fn = "Renderer::create: ";
    const RendererDesc& desc = desc_;
    const Manifest& m = bundle.manifest;
    if (m.materials.size() > CV_MAX_MATERIALS) {
        *error = fn + "the bundle has " + std::to_string(m.materials.size()) + " materials, this build draws at most " +
                 std::to_string(CV_MAX_MATERIALS) + " (CV_MAX_MATERIALS)";
        return false;
    }
    if (std::none_of(m.meshes.begin(), m.meshes.end(), [](const MeshInfo& mesh) { return mesh.lod == 0; })) {
        *error = fn + "the bundle has no lod 0 mesh";
        return false;
    }
    if (m.pose_frames > kMaxPoseFrames) {
        *error = fn + "the bundle has " + std::to_string(m.pose_frames) + " pose frames, instances address at most " +
                 std::to_string(kMaxPoseFrames) + " (16-bit frame numbers, crowd.h Instance)";
        return false;
    }

    auto owned = std::make_unique<Archetype>();
    Archetype& g = *owned;
    g.model = character_model(bundle);

    // Impostor programs: shader files by name (niagara style), config.h pasted in.
    // The impostor programs read the UV map in the bundle's format (impostor_uv_map.glsl).
    std::string shader_error;
    const std::string uv_defines =
        std::string("#define CV_UV_MAP_UV32 ") + (bundle.impostor_uv.format == PixelFormat::uv32 ? "1" : "0") + "\n" +
        "#define CV_UV_MAP_UVBLOCK " + (bundle.impostor_uv.format == PixelFormat::uvblock ? "1" : "0") + "\n" +
        "#define CV_NORMAL_VIEW_XY " + (bundle.impostor_normal.format == PixelFormat::bc5 ? "1" : "0") + "\n";
    if (bundle.impostor_normal.format == PixelFormat::bc5 &&
        (m.impostor.azimuths_deg.size() > CV_MAX_AZIMUTHS || m.impostor.elevations_deg.size() > CV_MAX_ELEVATIONS)) {
        // The bc5 normal map is in each tile's view; the shaders rebuild the views from uniform arrays this long.
        *error = fn + "a bc5 normal map needs at most " + std::to_string(CV_MAX_AZIMUTHS) + " azimuths and " +
                 std::to_string(CV_MAX_ELEVATIONS) + " elevations, the bundle has " + std::to_string(m.impostor.azimuths_deg.size()) +
                 " and " + std::to_string(m.impostor.elevations_deg.size());
        return false;
    }
    for (int kind = 0; kind < 2; ++kind)
        for (int blend = 0; blend < kBlendModes; ++blend) {
            const bool warp = ImpostorBlend(blend) == ImpostorBlend::warp;
            const bool all = ImpostorBlend(blend) == ImpostorBlend::full || warp;
            const bool views = ImpostorBlend(blend) == ImpostorBlend::views || all;
            const bool frames = ImpostorBlend(blend) == ImpostorBlend::frames || all;
            const std::string defines = uv_defines + "#define CV_VIEW_SAMPLES " + (views ? "4" : "1") + "\n#define CV_FRAME_SAMPLES " +
                                        (frames ? "2" : "1") + "\n#define CV_WARP " + (warp ? "1" : "0") + "\n";
            const GLuint program = build_program(desc.shader_dir, "impostor", kind == 0 ? "impostor_uv" : "impostor_detail",
                                                 &shader_error, defines);
            if (!program) {
                *error = fn + shader_error;
                return false;
            }
            g.impostor_programs[kind][blend] = program;
            g.impostor_uniforms[kind][blend] = impostor_uniforms(program);
            glUseProgram(program);
            glUniform1i(uniform(program, "u_outfits"), CV_UNIT_OUTFITS);
            glUniform1i(uniform(program, "u_normal_map"), CV_UNIT_IMPOSTOR_NORMAL);
            glUniform1i(uniform(program, "u_uv_map"), CV_UNIT_IMPOSTOR_UV);
            glUniform1i(uniform(program, "u_detail_map"), CV_UNIT_IMPOSTOR_DETAIL);
            glUniform1i(uniform(program, "u_surface_map"), CV_UNIT_IMPOSTOR_SURFACE);
            // The baked views' angles, for the warp shader's per-sample view bases (unused lengths stay 0).
            const std::vector<float>& azimuths = m.impostor.azimuths_deg;
            const std::vector<float>& elevations = m.impostor.elevations_deg;
            glUniform1fv(uniform(program, "u_azimuths_deg"), GLsizei(std::min<size_t>(azimuths.size(), CV_MAX_AZIMUTHS)), azimuths.data());
            glUniform1fv(uniform(program, "u_elevations_deg"), GLsizei(std::min<size_t>(elevations.size(), CV_MAX_ELEVATIONS)),
                         elevations.data());
            for (int k = 0; k < CV_MAX_MATERIALS; ++k)
                glUniform1i(uniform(program, ("u_diffuse[" + std::to_string(k) + "]").c_str()), CV_UNIT_DIFFUSE0 + k);
        }

    // Instance buffers, one per LOD, refilled every frame.
    glGenBuffers(3, g.instance_buffers);
    const char* lod_names[] = {"instances:high", "instances:low", "instances:impostor"};
    for (int i = 0; i < 3; ++i) {
        glBindBuffer(GL_ARRAY_BUFFER, g.instance_buffers[i]);
        label(GL_BUFFER, g.instance_buffers[i], lod_names[i]);
    }

    // Mesh parts: static UVs and indices, every frame's positions and normals in a buffer texture.
    GLint max_texels = 0;
    glGetIntegerv(GL_MAX_TEXTURE_BUFFER_SIZE, &max_texels);
    for (size_t i = 0; i < m.meshes.size(); ++i) {
        const MeshInfo& info = m.meshes[i];
        if (info.lod > 1) continue;  // the runtime draws two mesh levels, as the paper's figure 3
        const PoseCache& pose = bundle.meshes[i];
        const uint64_t texels = uint64_t(pose.frame_count) * pose.vertex_count * 2;
        if (texels > uint64_t(max_texels)) {
            *error = fn + info.file + " needs " + std::to_string(texels) + " buffer texels, the driver allows " +
                     std::to_string(max_texels);
            return false;
        }
        Part p;
        p.index_count = pose.index_count;
        p.vertex_count = pose.vertex_count;
        p.material = info.material;
        p.lod = info.lod == 0 ? Lod::high : Lod::low;
        p.garment = info.kind == "garment";
        const std::string name = info.part + ":lod" + std::to_string(info.lod);
        std::vector<float> interleaved(texels * 4);
        for (uint64_t v = 0; v < uint64_t(pose.frame_count) * pose.vertex_count; ++v) {
            std::memcpy(&interleaved[v * 8], &pose.positions[v * 3], 12);
            interleaved[v * 8 + 3] = 1.0f;
            std::memcpy(&interleaved[v * 8 + 4], &pose.normals[v * 3], 12);
            interleaved[v * 8 + 7] = 0.0f;
        }
        glGenVertexArrays(1, &p.vao);
        glBindVertexArray(p.vao);
        label(GL_VERTEX_ARRAY, p.vao, name);
        glGenBuffers(1, &p.uv_buffer);
        glBindBuffer(GL_ARRAY_BUFFER, p.uv_buffer);
        glBufferData(GL_ARRAY_BUFFER, GLsizeiptr(pose.uvs.size() * 4), pose.uvs.data(), GL_STATIC_DRAW);
        label(GL_BUFFER, p.uv_buffer, name + ":uvs");
        glEnableVertexAttribArray(CV_ATTR_UV);
        glVertexAttribPointer(CV_ATTR_UV, 2, GL_FLOAT, GL_FALSE, 8, nullptr);
        glGenBuffers(1, &p.index_buffer);
        glBindBuffer(GL_ELEMENT_ARRAY_BUFFER, p.index_buffer);
        glBufferData(GL_ELEMENT_ARRAY_BUFFER, GLsizeiptr(pose.indices.size() * 4), pose.indices.data(), GL_STATIC_DRAW);
        label(GL_BUFFER, p.index_buffer, name + ":indices");
        bind_instance_attributes(g.instance_buffers[int(p.lod)]);
        glBindVertexArray(0);
        glGenBuffers(1, &p.pose_buffer);
        glBindBuffer(GL_TEXTURE_BUFFER, p.pose_buffer);
        glBufferData(GL_TEXTURE_BUFFER, GLsizeiptr(interleaved.size() * 4), interleaved.data(), GL_STATIC_DRAW);
        label(GL_BUFFER, p.pose_buffer, name + ":poses");
        glGenTextures(1, &p.pose_texture);
        glBindTexture(GL_TEXTURE_BUFFER, p.pose_texture);
        glTexBuffer(GL_TEXTURE_BUFFER, GL_RGBA32F, p.pose_buffer);
        label(GL_TEXTURE, p.pose_texture, name + ":poses");
        g.memory.meshes += uint64_t(pose.uvs.size() + pose.indices.size() + interleaved.size()) * 4;
        g.parts.push_back(p);
    }
    glGenVertexArrays(1, &g.impostor_vao);
    glBindVertexArray(g.impostor_vao);
    label(GL_VERTEX_ARRAY, g.impostor_vao, "impostors");
    bind_instance_attributes(g.instance_buffers[int(Lod::impostor)]);
    glGenBuffers(1, &g.impostor_sample_buffer);
    glBindBuffer(GL_ARRAY_BUFFER, g.impostor_sample_buffer);
    label(GL_BUFFER, g.impostor_sample_buffer, "instances:impostor-samples");
    const GLsizei stride = sizeof(ImpostorSamples);
    glEnableVertexAttribArray(CV_ATTR_IMPOSTOR_TILES);
    glVertexAttribIPointer(CV_ATTR_IMPOSTOR_TILES, 4, GL_UNSIGNED_SHORT, stride, (void*)offsetof(ImpostorSamples, tiles));
    glEnableVertexAttribArray(CV_ATTR_IMPOSTOR_VIEW_WEIGHTS);
    glVertexAttribPointer(CV_ATTR_IMPOSTOR_VIEW_WEIGHTS, 4, GL_FLOAT, GL_FALSE, stride, (void*)offsetof(ImpostorSamples, view_weights));
    glEnableVertexAttribArray(CV_ATTR_IMPOSTOR_LAYERS);
    glVertexAttribIPointer(CV_ATTR_IMPOSTOR_LAYERS, 2, GL_UNSIGNED_SHORT, stride, (void*)offsetof(ImpostorSamples, layers));
    glEnableVertexAttribArray(CV_ATTR_IMPOSTOR_FRAME_WEIGHT);
    glVertexAttribPointer(CV_ATTR_IMPOSTOR_FRAME_WEIGHT, 1, GL_FLOAT, GL_FALSE, stride, (void*)offsetof(ImpostorSamples, frame_weight));
    for (GLuint a : {CV_ATTR_IMPOSTOR_TILES, CV_ATTR_IMPOSTOR_VIEW_WEIGHTS, CV_ATTR_IMPOSTOR_LAYERS, CV_ATTR_IMPOSTOR_FRAME_WEIGHT})
        glVertexAttribDivisor(a, 1);
    glBindVertexArray(0);

    // Textures.
    Upload upload;
    upload.force_cpu_decode = desc.force_cpu_texture_decode;
    upload.s3tc = !desc.force_cpu_texture_decode && epoxy_has_gl_extension("GL_EXT_texture_compression_s3tc");
    for (size_t k = 0; k < m.materials.size(); ++k) {
        g.diffuse.push_back(upload_texture_array(bundle.diffuse[k], true, "diffuse:" + m.materials[k].name, &upload));
        g.variations.push_back(int(bundle.diffuse[k].layer_count));
        g.has_regions.push_back(bundle.diffuse[k].format != PixelFormat::bc1);
    }
    g.memory.textures = upload.bytes;
    g.normal_map = upload_texture_array(bundle.impostor_normal, false, "impostor:normal", &upload);
    g.uv_map = upload_texture_array(bundle.impostor_uv, false, "impostor:uv", &upload);
    if (bundle.impostor_detail.layer_count > 0)  // stored only by bakes asked for it (--detail-map)
        g.detail_map = upload_texture_array(bundle.impostor_detail, false, "impostor:detail", &upload);
    if (bundle.impostor_surface.layer_count > 0 && m.impostor.azimuths_deg.size() <= CV_MAX_AZIMUTHS &&
        m.impostor.elevations_deg.size() <= CV_MAX_ELEVATIONS) {
        // Depth and motion are smooth and dilated past the silhouette: read bilinearly, within a level.
        g.surface_map = upload_texture_array(bundle.impostor_surface, false, "impostor:surface", &upload);
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
    }
    g.memory.impostors = upload.bytes - g.memory.textures;
    glGenTextures(1, &g.outfits);
    glBindTexture(GL_TEXTURE_2D, g.outfits);
    glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA8, GLsizei(bundle.outfits.width), GLsizei(bundle.outfits.height), 0, GL_RGBA,
                 GL_UNSIGNED_BYTE, bundle.outfits.data.data());
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAX_LEVEL, 0);
    label(GL_TEXTURE, g.outfits, "outfits");
    g.memory.textures += uint64_t(bundle.outfits.width) * bundle.outfits.height * 4;
    g.tile_size = m.impostor.tile_size;
    g.azimuth_count = uint32_t(m.impostor.azimuths_deg.size());
    g.crop = m.impostor.crop;
    if (GLenum e = glGetError(); e != GL_NO_ERROR) {
        *error = fn + "OpenGL error 0x" + [](GLenum v) {
            char buf[16];
            std::snprintf(buf, sizeof buf, "%04x", v);
            return std::string(buf);
        }(e) + " while uploading the bundle";
        return false;
    }
    InstanceBuffers buffers;
    std::copy(owned->instance_buffers, owned->instance_buffers + 3, buffers.by_lod);
    buffers.impostor_samples = owned->impostor_sample_buffer;
    impl_->storage.buffers.push_back(buffers);
    impl_->archetypes.push_back(std::move(owned));
    return true;
}

Renderer::~Renderer() = default;

size_t Renderer::archetype_count() const { return impl_->archetypes.size(); }
const CharacterModel& Renderer::model(size_t archetype) const { return impl_->archetypes.at(archetype)->model; }
ArchetypeMemory Renderer::memory(size_t archetype) const { return impl_->archetypes.at(archetype)->memory; }

uint32_t Renderer::triangles_per_character(Lod lod, size_t archetype) const {
    if (lod == Lod::impostor) return 2;
    uint32_t triangles = 0;
    for (const Part& p : impl_->archetypes.at(archetype)->parts)
        if (p.lod == lod) triangles += p.index_count / 3;
    return triangles;
}

InstanceStorage* Renderer::instance_storage() { return &impl_->storage; }

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
    Impl& shared = *impl_;
    DrawStats stats;
    glBindFramebuffer(GL_FRAMEBUFFER, shared.framebuffer);
    glViewport(0, 0, width_, height_);
    glClearColor(0.62f, 0.70f, 0.78f, 1.0f);  // overcast sky
    glClear(GL_COLOR_BUFFER_BIT | GL_DEPTH_BUFFER_BIT);
    glEnable(GL_DEPTH_TEST);
    glDisable(GL_BLEND);
    const glm::mat4 view_projection = camera.projection(aspect()) * camera.view();
    const glm::vec3 light = glm::normalize(light_dir);
    // Each archetype in turn: its instances, then its meshes and its impostors.
    for (size_t a = 0; a < frame_count && a < shared.archetypes.size(); ++a) {
        const DrawStats s = draw_archetype(*shared.archetypes[a], frames[a], view_projection, camera, impostors, light);
        stats.draw_calls += s.draw_calls;
        stats.triangles += s.triangles;
    }
    glBindVertexArray(0);
    return stats;
}

DrawStats Renderer::draw_archetype(Archetype& g, const FrameInstances& frame, const glm::mat4& view_projection, const Camera& camera,
                                   ImpostorKind impostors, const glm::vec3& light) {
    Impl& shared = *impl_;
    const CharacterModel& model_ = g.model;
    DrawStats stats;
    // 1. This frame's instances, one buffer per LOD, and the impostors' blend samples.
    InstanceBuffers buffers;
    for (int lod = 0; lod < 3; ++lod) buffers.by_lod[lod] = g.instance_buffers[lod];
    buffers.impostor_samples = g.impostor_sample_buffer;
    if (!frame.in_storage) upload_instances(frame, buffers, &shared.nearest_samples);  // else built there
    glActiveTexture(GL_TEXTURE0 + CV_UNIT_OUTFITS);
    glBindTexture(GL_TEXTURE_2D, g.outfits);

    // 2. Meshes: one instanced draw per part per mesh LOD.
    const MeshUniforms& mu = shared.mesh_uniforms;
    glUseProgram(shared.mesh_program);
    glUniformMatrix4fv(mu.view_projection, 1, GL_FALSE, glm::value_ptr(view_projection));
    glUniform3fv(mu.light_dir, 1, glm::value_ptr(light));
    for (const Part& p : g.parts) {
        const GLsizei count = GLsizei(frame.shown[int(p.lod)]);
        if (count == 0) continue;
        // Bodies are closed: skip their back faces. Garments are open cloth, seen from inside too.
        if (p.garment) glDisable(GL_CULL_FACE);
        else glEnable(GL_CULL_FACE);
        glActiveTexture(GL_TEXTURE0 + CV_UNIT_POSES);
        glBindTexture(GL_TEXTURE_BUFFER, p.pose_texture);
        glActiveTexture(GL_TEXTURE0 + CV_UNIT_DIFFUSE0);
        glBindTexture(GL_TEXTURE_2D_ARRAY, g.diffuse[p.material]);
        glUniform1i(mu.vertex_count, GLint(p.vertex_count));
        glUniform1i(mu.variations, g.variations[p.material]);
        glUniform1i(mu.has_regions, g.has_regions[p.material] ? 1 : 0);
        glBindVertexArray(p.vao);
        glDrawElementsInstanced(GL_TRIANGLES, GLsizei(p.index_count), GL_UNSIGNED_INT, nullptr, count);
        ++stats.draw_calls;
        stats.triangles += uint64_t(p.index_count / 3) * uint64_t(count);
    }
    glDisable(GL_CULL_FACE);

    // 3. Impostors: one instanced draw of camera-facing quads.
    const uint32_t quads = frame.shown[int(Lod::impostor)];
    if (quads > 0) {
        const int kind = impostors == ImpostorKind::uv ? 0 : 1, blend = int(archetype_blend(g, frame.blend));
        const ImpostorUniforms& iu = g.impostor_uniforms[kind][blend];
        glUseProgram(g.impostor_programs[kind][blend]);
        glUniformMatrix4fv(iu.view_projection, 1, GL_FALSE, glm::value_ptr(view_projection));
        glUniform3fv(iu.light_dir, 1, glm::value_ptr(light));
        glUniform3fv(iu.camera_position, 1, glm::value_ptr(camera.position));
        glUniform3fv(iu.center, 1, glm::value_ptr(model_.center));
        glUniform1f(iu.radius, model_.radius);
        glUniform1i(iu.tile_size, GLint(g.tile_size));
        glUniform1i(iu.azimuth_count, GLint(g.azimuth_count));
        glUniform4i(iu.crop, GLint(g.crop.x), GLint(g.crop.y), GLint(g.crop.width), GLint(g.crop.height));
        glUniform1i(iu.material_count, GLint(g.diffuse.size()));
        glUniform1i(iu.has_surface, g.surface_map ? 1 : 0);  // its alpha: the silhouette's coverage, in every blend
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
        glBindVertexArray(g.impostor_vao);
        // Soft silhouettes (config.h CV_EDGE_LOW) mix over what is already drawn. Edge pixels still
        // write depth, so an impostor behind one, drawn later, shows the background there instead.
        glEnable(GL_BLEND);
        glBlendFuncSeparate(GL_SRC_ALPHA, GL_ONE_MINUS_SRC_ALPHA, GL_ONE, GL_ONE_MINUS_SRC_ALPHA);
        glDrawArraysInstanced(GL_TRIANGLE_STRIP, 0, 4, GLsizei(quads));
        glDisable(GL_BLEND);
        ++stats.draw_calls;
        stats.triangles += 2 * uint64_t(quads);
    }
    return stats;
}

ImpostorBlend Renderer::archetype_blend(const Archetype& archetype, ImpostorBlend blend) {
    return blend == ImpostorBlend::warp && !archetype.surface_map ? ImpostorBlend::full : blend;
}

ImpostorBlend Renderer::effective_blend(ImpostorBlend blend, size_t archetype) const {
    return archetype_blend(*impl_->archetypes.at(archetype), blend);
}

void Renderer::present(int window_width, int window_height) const {
    glBindFramebuffer(GL_READ_FRAMEBUFFER, impl_->framebuffer);
    glBindFramebuffer(GL_DRAW_FRAMEBUFFER, 0);
    glBlitFramebuffer(0, 0, width_, height_, 0, 0, window_width, window_height, GL_COLOR_BUFFER_BIT, GL_LINEAR);
    glBindFramebuffer(GL_FRAMEBUFFER, impl_->framebuffer);
}

std::vector<uint8_t> Renderer::read_rgba() const {
    std::vector<uint8_t> bottom_up(size_t(width_) * height_ * 4), rgba(bottom_up.size());
    glBindFramebuffer(GL_READ_FRAMEBUFFER, impl_->framebuffer);
    glPixelStorei(GL_PACK_ALIGNMENT, 1);
    glReadPixels(0, 0, width_, height_, GL_RGBA, GL_UNSIGNED_BYTE, bottom_up.data());
    const size_t row = size_t(width_) * 4;
    for (int y = 0; y < height_; ++y) std::memcpy(&rgba[y * row], &bottom_up[(height_ - 1 - y) * row], row);
    return rgba;
}

void Renderer::finish() const { glFinish(); }

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
