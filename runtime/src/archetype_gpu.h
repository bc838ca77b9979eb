// One archetype's GPU resources: its mesh parts (static UVs and indices, every pose frame's
// positions and normals in buffer textures, or a skinned body's rest mesh, influences and matrices),
// one instance buffer per LOD refilled every frame,
// the impostors' blend-sample buffer, its textures and its impostor programs.
// upload_archetype() makes them all from a bundle or none: on a refusal whatever it made is freed.
// Destroying an ArchetypeGpu frees its GL objects, so it needs the context that made it.
#pragma once

#include <epoxy/gl.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "bundle.h"
#include "crowd.h"
#include "crowd_programs.h"
#include "instance_upload.h"
#include "renderer.h"

namespace crowdview {

// What a part's pose buffer textures hold: a quantized cache's codes and frame bounds as a version-2 CBPC
// stores them (pose_codec.h), or a skinned cache's rest mesh, influences and matrices as a CBSK stores them
// (skinned_pose.h). Stream k is bound to the same texture unit either way (renderer_draw.cpp).
enum PoseStream { kPosePositions = 0, kPoseNormals = 1, kPoseFrameBounds = 2 };
enum SkinStream { kSkinRestPositions = 0, kSkinRestNormals = 1, kSkinMatrices = 2, kSkinJoints = 3, kSkinWeights = 4 };
constexpr int kPoseStreams = 5;  // the most a part holds (a skinned one); a quantized part's last two are 0

// One mesh part at one mesh LOD: drawn instanced from the instance buffer of its LOD.
struct MeshPart {
    GLuint vao = 0, uv_buffer = 0, index_buffer = 0;
    // The pose cache as stored, each stream a buffer and its buffer texture.
    GLuint pose_buffers[kPoseStreams] = {}, pose_textures[kPoseStreams] = {};  // by PoseStream, or SkinStream where skinned
    uint32_t index_count = 0, vertex_count = 0, material = 0;
    uint32_t joint_count = 0;  // > 0: skinned, drawn with the skinned mesh program
    Lod lod = Lod::high;
    bool garment = false;  // open cloth: drawn without back-face culling
};

struct ArchetypeGpu {
    CharacterModel model;
    ArchetypeMemory memory;
    // By ImpostorKind and ImpostorBlend (crowd_programs.h).
    GLuint impostor_programs[kImpostorKinds][kBlendModes] = {};
    ImpostorUniforms impostor_uniforms[kImpostorKinds][kBlendModes];
    std::vector<MeshPart> parts;
    GLuint impostor_vao = 0;
    GLuint instance_buffers[3] = {0, 0, 0};  // by Lod
    GLuint impostor_sample_buffer = 0;       // struct ImpostorSamples, one per impostor
    std::vector<GLuint> diffuse;             // by material
    std::vector<int> variations;             // diffuse layers, by material
    std::vector<bool> has_regions;           // by material: the diffuse map's alpha holds colour regions
    GLuint outfits = 0, normal_map = 0, uv_map = 0, detail_map = 0;
    GLuint surface_map = 0;  // 0: the bundle has none (or more views than the warp shader holds), warp draws as full
    uint32_t tile_size = 0, azimuth_count = 0;
    ImpostorCrop crop;

    ArchetypeGpu() = default;
    ArchetypeGpu(const ArchetypeGpu&) = delete;
    ArchetypeGpu& operator=(const ArchetypeGpu&) = delete;
    ~ArchetypeGpu();

    // Where its frames' instances go (instance_upload.h).
    InstanceBuffers instance_targets() const;
    // The blend a frame built for `blend` is drawn with: warp needs the surface map.
    ImpostorBlend drawn_blend(ImpostorBlend blend) const;
};

// `bundle` uploaded as an archetype drawn with `desc`'s shaders and texture path. nullptr and one
// line in `error` (without a function prefix) when it needs more than this build or driver draws:
// more than CV_MAX_MATERIALS materials, no lod 0 mesh, more than kMaxPoseFrames pose frames, views
// the impostor programs cannot hold, a pose cache over the driver's buffer texture size, a shader
// that does not build, or a GL error while uploading.
std::unique_ptr<ArchetypeGpu> upload_archetype(const Bundle& bundle, const RendererDesc& desc, std::string* error);

// Points every VAO of `g` at the instances in `buffers`: several renderer archetypes drawn from one
// bundle share its uploads, each with its own instance buffers (Renderer::add_archetype_like).
void point_instance_attributes(const ArchetypeGpu& g, const InstanceBuffers& buffers);

}  // namespace crowdview
