// One archetype's GPU resources, uploaded from a bundle (see archetype_gpu.h).
#include "archetype_gpu.h"

#include <algorithm>
#include <cstddef>
#include <cstring>

#include "config.h"
#include "gl_programs.h"
#include "texture_upload.h"

namespace crowdview {

namespace {

// "" where this build can draw `bundle`, else one line saying why not.
std::string bundle_refusal(const Bundle& bundle) {
    const Manifest& m = bundle.manifest;
    if (m.materials.size() > CV_MAX_MATERIALS)
        return "the bundle has " + std::to_string(m.materials.size()) + " materials, this build draws at most " +
               std::to_string(CV_MAX_MATERIALS) + " (CV_MAX_MATERIALS)";
    if (std::none_of(m.meshes.begin(), m.meshes.end(), [](const MeshInfo& mesh) { return mesh.lod == 0; }))
        return "the bundle has no lod 0 mesh";
    if (m.pose_frames > kMaxPoseFrames)
        return "the bundle has " + std::to_string(m.pose_frames) + " pose frames, instances address at most " +
               std::to_string(kMaxPoseFrames) + " (16-bit frame numbers, crowd.h Instance)";
    return impostor_programs_refusal(bundle);
}

bool build_impostor_programs(const Bundle& bundle, const std::string& shader_dir, ArchetypeGpu* g, std::string* error) {
    for (int kind = 0; kind < kImpostorKinds; ++kind)
        for (int blend = 0; blend < kBlendModes; ++blend) {
            g->impostor_programs[kind][blend] = build_impostor_program(shader_dir, bundle, ImpostorKind(kind), ImpostorBlend(blend),
                                                                       &g->impostor_uniforms[kind][blend], error);
            if (!g->impostor_programs[kind][blend]) return false;
        }
    return true;
}

void create_instance_buffers(ArchetypeGpu* g) {
    glGenBuffers(3, g->instance_buffers);
    const char* lod_names[] = {"instances:high", "instances:low", "instances:impostor"};
    for (int i = 0; i < 3; ++i) {
        glBindBuffer(GL_ARRAY_BUFFER, g->instance_buffers[i]);
        label(GL_BUFFER, g->instance_buffers[i], lod_names[i]);
    }
}

// Binds the per-instance attributes (struct Instance) of `buffer` to the bound VAO.
void bind_instance_attributes(GLuint buffer) {
    glBindBuffer(GL_ARRAY_BUFFER, buffer);
    glEnableVertexAttribArray(CV_ATTR_INSTANCE_POSE);
    glVertexAttribPointer(CV_ATTR_INSTANCE_POSE, 4, GL_FLOAT, GL_FALSE, sizeof(Instance), (void*)offsetof(Instance, position));
    glVertexAttribDivisor(CV_ATTR_INSTANCE_POSE, 1);
    glEnableVertexAttribArray(CV_ATTR_INSTANCE_IDS);
    glVertexAttribIPointer(CV_ATTR_INSTANCE_IDS, 4, GL_UNSIGNED_SHORT, sizeof(Instance), (void*)offsetof(Instance, frame));
    glVertexAttribDivisor(CV_ATTR_INSTANCE_IDS, 1);
}

// Each frame's bounds as two RGBA32F texels, minimum then maximum (w unused: GL 3.3 buffer textures
// have no RGB32F).
std::vector<float> frame_bounds_texels(const PoseCache& pose) {
    std::vector<float> texels(size_t(pose.frame_count) * 8, 0.0f);
    for (size_t f = 0; f < pose.frame_count; ++f) {
        std::memcpy(&texels[f * 8], &pose.frame_bounds[f * 6], 12);
        std::memcpy(&texels[f * 8 + 4], &pose.frame_bounds[f * 6 + 3], 12);
    }
    return texels;
}

// A buffer holding `bytes` of `data` and a buffer texture reading it as `format`; returns the bytes.
uint64_t upload_buffer_texture(const void* data, size_t bytes, GLenum format, const std::string& name, GLuint* buffer, GLuint* texture) {
    glGenBuffers(1, buffer);
    glBindBuffer(GL_TEXTURE_BUFFER, *buffer);
    glBufferData(GL_TEXTURE_BUFFER, GLsizeiptr(bytes), data, GL_STATIC_DRAW);
    label(GL_BUFFER, *buffer, name);
    glGenTextures(1, texture);
    glBindTexture(GL_TEXTURE_BUFFER, *texture);
    glTexBuffer(GL_TEXTURE_BUFFER, format, *buffer);
    label(GL_TEXTURE, *texture, name);
    return bytes;
}

// The pose cache's codes as stored, decoded by mesh.vert.glsl: 10 bytes a vertex a frame, where float
// positions and normals would take 32 (two RGBA32F texels). Returns the bytes uploaded.
uint64_t upload_pose_streams(const PoseCache& pose, const std::string& name, MeshPart* p) {
    const std::vector<float> bounds = frame_bounds_texels(pose);
    return upload_buffer_texture(pose.position_codes.data(), pose.position_codes.size() * 2, GL_R16UI, name + ":positions",
                                 &p->pose_buffers[kPosePositions], &p->pose_textures[kPosePositions]) +
           upload_buffer_texture(pose.normal_codes.data(), pose.normal_codes.size() * 2, GL_RG16UI, name + ":normals",
                                 &p->pose_buffers[kPoseNormals], &p->pose_textures[kPoseNormals]) +
           upload_buffer_texture(bounds.data(), bounds.size() * 4, GL_RGBA32F, name + ":frame-bounds", &p->pose_buffers[kPoseFrameBounds],
                                 &p->pose_textures[kPoseFrameBounds]);
}

// A skinned cache as stored, skinned by mesh.vert.glsl (CV_SKINNED): the rest positions and normals (R32F,
// three texels a vertex: GL 3.3 buffer textures have no RGB32F), the joints and weight codes (RGBA16UI, one
// texel a vertex) and the matrices (RGBA32F, a texel a row, three a joint a frame). Returns the bytes uploaded.
uint64_t upload_skin_streams(const PoseSkin& skin, const std::string& name, MeshPart* p) {
    struct Stream {
        const void* data;
        size_t bytes;
        GLenum format;
        const char* what;
    };
    const Stream streams[kPoseStreams] = {
        {skin.rest_positions.data(), skin.rest_positions.size() * 4, GL_R32F, ":rest-positions"},
        {skin.rest_normals.data(), skin.rest_normals.size() * 4, GL_R32F, ":rest-normals"},
        {skin.matrices.data(), skin.matrices.size() * 4, GL_RGBA32F, ":matrices"},
        {skin.joints.data(), skin.joints.size() * 2, GL_RGBA16UI, ":joints"},
        {skin.weight_codes.data(), skin.weight_codes.size() * 2, GL_RGBA16UI, ":weights"},
    };
    uint64_t bytes = 0;
    for (int k = 0; k < kPoseStreams; ++k)
        bytes += upload_buffer_texture(streams[k].data, streams[k].bytes, streams[k].format, name + streams[k].what, &p->pose_buffers[k],
                                       &p->pose_textures[k]);
    return bytes;
}

// The part's VAO (UVs, indices, the instance attributes of its LOD's buffer) and pose textures.
// Adds its bytes to `bytes`.
MeshPart upload_mesh_part(const MeshInfo& info, const PoseCache& pose, const GLuint instance_buffers[3], uint64_t* bytes) {
    MeshPart p;
    p.index_count = pose.index_count;
    p.vertex_count = pose.vertex_count;
    p.material = info.material;
    p.lod = info.lod == 0 ? Lod::high : Lod::low;
    p.garment = info.kind == "garment";
    p.joint_count = pose.skin.joint_count;
    const std::string name = info.part + ":lod" + std::to_string(info.lod);
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
    bind_instance_attributes(instance_buffers[int(p.lod)]);
    glBindVertexArray(0);
    *bytes += uint64_t(pose.uvs.size() + pose.indices.size()) * 4 +
              (pose.skinned() ? upload_skin_streams(pose.skin, name, &p) : upload_pose_streams(pose, name, &p));
    return p;
}

// Texels of the pose cache's largest buffer texture: a quantized cache's position codes, a skinned one's
// rest positions or matrices.
uint64_t largest_pose_stream_texels(const PoseCache& pose) {
    if (!pose.skinned()) return uint64_t(pose.frame_count) * pose.vertex_count * 3;
    return std::max(uint64_t(pose.vertex_count) * 3, uint64_t(pose.frame_count) * pose.skin.joint_count * 3);
}

// The parts of mesh LODs 0 and 1, counted in the body or garment share of g->memory; false and `error`
// where a pose cache outgrows the driver's buffer textures.
bool upload_mesh_parts(const Bundle& bundle, ArchetypeGpu* g, std::string* error) {
    GLint max_texels = 0;
    glGetIntegerv(GL_MAX_TEXTURE_BUFFER_SIZE, &max_texels);
    const Manifest& m = bundle.manifest;
    for (size_t i = 0; i < m.meshes.size(); ++i) {
        const MeshInfo& info = m.meshes[i];
        if (info.lod > 1) continue;  // the runtime draws two mesh levels, as the paper's figure 3
        const PoseCache& pose = bundle.meshes[i];
        const uint64_t texels = largest_pose_stream_texels(pose);
        if (texels > uint64_t(max_texels)) {
            *error = info.file + " needs " + std::to_string(texels) + " buffer texels, the driver allows " + std::to_string(max_texels);
            return false;
        }
        uint64_t* share = info.kind == "garment" ? &g->memory.garments : &g->memory.bodies;
        g->parts.push_back(upload_mesh_part(info, pose, g->instance_buffers, share));
    }
    return true;
}

// Binds the impostors' blend samples (struct ImpostorSamples) of `buffer` to the bound VAO.
void bind_impostor_sample_attributes(GLuint buffer) {
    glBindBuffer(GL_ARRAY_BUFFER, buffer);
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
}

// The impostors' VAO: instance attributes from the impostor LOD's buffer, blend samples from their own.
void create_impostor_vao(ArchetypeGpu* g) {
    glGenVertexArrays(1, &g->impostor_vao);
    glBindVertexArray(g->impostor_vao);
    label(GL_VERTEX_ARRAY, g->impostor_vao, "impostors");
    bind_instance_attributes(g->instance_buffers[int(Lod::impostor)]);
    glGenBuffers(1, &g->impostor_sample_buffer);
    glBindBuffer(GL_ARRAY_BUFFER, g->impostor_sample_buffer);
    label(GL_BUFFER, g->impostor_sample_buffer, "instances:impostor-samples");
    bind_impostor_sample_attributes(g->impostor_sample_buffer);
    glBindVertexArray(0);
}

// The impostor maps; the surface map only where the warp shader's view arrays hold the bake's views.
void upload_impostor_maps(const Bundle& bundle, ArchetypeGpu* g, TextureUpload* upload) {
    const ImpostorInfo& impostor = bundle.manifest.impostor;
    g->normal_map = upload_texture_array(bundle.impostor_normal, false, "impostor:normal", upload);
    g->uv_map = upload_texture_array(bundle.impostor_uv, false, "impostor:uv", upload);
    if (bundle.impostor_detail.layer_count > 0)  // stored only by bakes asked for it (--detail-map)
        g->detail_map = upload_texture_array(bundle.impostor_detail, false, "impostor:detail", upload);
    if (bundle.impostor_surface.layer_count > 0 && impostor.azimuths_deg.size() <= CV_MAX_AZIMUTHS &&
        impostor.elevations_deg.size() <= CV_MAX_ELEVATIONS) {
        // Depth and motion are smooth and dilated past the silhouette: read bilinearly, within a level.
        g->surface_map = upload_texture_array(bundle.impostor_surface, false, "impostor:surface", upload);
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
    }
}

// Diffuse arrays, impostor maps and the outfit map, each counted in its share of `memory`.
void upload_textures(const Bundle& bundle, const RendererDesc& desc, ArchetypeGpu* g) {
    TextureUpload upload;
    upload.force_cpu_decode = desc.force_cpu_texture_decode;
    upload.s3tc = !desc.force_cpu_texture_decode && epoxy_has_gl_extension("GL_EXT_texture_compression_s3tc");
    const std::vector<MaterialInfo>& materials = bundle.manifest.materials;
    for (size_t k = 0; k < materials.size(); ++k) {
        g->diffuse.push_back(upload_texture_array(bundle.diffuse[k], true, "diffuse:" + materials[k].name, &upload));
        g->variations.push_back(int(bundle.diffuse[k].layer_count));
        g->has_regions.push_back(bundle.diffuse[k].format != PixelFormat::bc1);
    }
    g->memory.textures = upload.bytes;
    upload_impostor_maps(bundle, g, &upload);
    g->memory.impostors = upload.bytes - g->memory.textures;
    const uint64_t before_outfits = upload.bytes;
    g->outfits = upload_outfit_map(bundle.outfits, &upload);
    g->memory.textures += upload.bytes - before_outfits;
}

}  // namespace

ArchetypeGpu::~ArchetypeGpu() {
    for (MeshPart& p : parts) {
        glDeleteVertexArrays(1, &p.vao);
        GLuint buffers[] = {p.uv_buffer, p.index_buffer};
        glDeleteBuffers(2, buffers);
        glDeleteBuffers(kPoseStreams, p.pose_buffers);
        glDeleteTextures(kPoseStreams, p.pose_textures);
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

InstanceBuffers ArchetypeGpu::instance_targets() const {
    InstanceBuffers buffers;
    std::copy(instance_buffers, instance_buffers + 3, buffers.by_lod);
    buffers.impostor_samples = impostor_sample_buffer;
    return buffers;
}

void point_instance_attributes(const ArchetypeGpu& g, const InstanceBuffers& buffers) {
    for (const MeshPart& p : g.parts) {
        glBindVertexArray(p.vao);
        bind_instance_attributes(buffers.by_lod[int(p.lod)]);
    }
    glBindVertexArray(g.impostor_vao);
    bind_instance_attributes(buffers.by_lod[int(Lod::impostor)]);
    bind_impostor_sample_attributes(buffers.impostor_samples);
    glBindVertexArray(0);
}

ImpostorBlend ArchetypeGpu::drawn_blend(ImpostorBlend blend) const {
    return blend == ImpostorBlend::warp && !surface_map ? ImpostorBlend::full : blend;
}

std::unique_ptr<ArchetypeGpu> upload_archetype(const Bundle& bundle, const RendererDesc& desc, std::string* error) {
    if (std::string refusal = bundle_refusal(bundle); !refusal.empty()) {
        *error = refusal;
        return nullptr;
    }
    auto g = std::make_unique<ArchetypeGpu>();
    g->model = character_model(bundle);
    if (!build_impostor_programs(bundle, desc.shader_dir, g.get(), error)) return nullptr;
    create_instance_buffers(g.get());
    if (!upload_mesh_parts(bundle, g.get(), error)) return nullptr;
    create_impostor_vao(g.get());
    upload_textures(bundle, desc, g.get());
    const ImpostorInfo& impostor = bundle.manifest.impostor;
    g->tile_size = impostor.tile_size;
    g->azimuth_count = uint32_t(impostor.azimuths_deg.size());
    g->crop = impostor.crop;
    if (GLenum e = glGetError(); e != GL_NO_ERROR) {
        *error = gl_error_text(e) + " while uploading the bundle";
        return nullptr;
    }
    return g;
}

}  // namespace crowdview
