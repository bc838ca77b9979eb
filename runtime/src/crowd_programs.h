// The crowd's GL programs and the uniform locations draws set: the mesh program every archetype
// shares, and each archetype's impostor programs, one per ImpostorKind and ImpostorBlend. Each
// blend mode is its own shader variant with constant sample counts, so blending off costs what
// the paper's lookup does; the defines also follow the bundle's map formats, and the uniform
// arrays hold its baked views. Sampler units are fixed (config.h), so they are set here, once.
// Needs a current context (gl_context.h). Errors: one line without a function prefix.
#pragma once

#include <epoxy/gl.h>

#include <string>

#include "bundle.h"
#include "config.h"
#include "renderer.h"

namespace crowdview {

static_assert(int(ImpostorBlend::off) == 0 && int(ImpostorBlend::warp) == 4, "impostor programs are indexed by ImpostorBlend");
static_assert(int(ImpostorKind::uv) == 0 && int(ImpostorKind::detail) == 1, "impostor programs are indexed by ImpostorKind");
constexpr int kBlendModes = 5;
constexpr int kImpostorKinds = 2;  // ImpostorKind::uv, ImpostorKind::detail

// Uniform locations, looked up once when a program is linked (-1: the program has no such
// uniform, which glUniform* ignores).
struct MeshUniforms {
    GLint view_projection = -1, light_dir = -1, vertex_count = -1, variations = -1, has_regions = -1;
    GLint joint_count = -1;  // the skinned program's
};

struct ImpostorUniforms {
    GLint view_projection = -1, light_dir = -1, camera_position = -1, center = -1, radius = -1, tile_size = -1,
          azimuth_count = -1, crop = -1, material_count = -1, has_surface = -1;
    GLint variations[CV_MAX_MATERIALS], has_regions[CV_MAX_MATERIALS];
};

// The mesh program (mesh.vert.glsl, mesh.frag.glsl) with its sampler units set: `skinned` builds the
// variant that skins a CBSK's rest mesh (CV_SKINNED 1), else the one that decodes quantized frames.
// 0 and `error` when it does not build.
GLuint build_mesh_program(const std::string& shader_dir, bool skinned, MeshUniforms* uniforms, std::string* error);

// "" where the impostor programs can draw `bundle`, else one line saying why not: a bc5 normal map
// is in each tile's view, and the shaders rebuild the views from uniform arrays of at most
// CV_MAX_AZIMUTHS x CV_MAX_ELEVATIONS.
std::string impostor_programs_refusal(const Bundle& bundle);

// The impostor program of `kind` and `blend` for `bundle`'s map formats and baked views, with its
// sampler units and view angles set; 0 and `error` when it does not build.
GLuint build_impostor_program(const std::string& shader_dir, const Bundle& bundle, ImpostorKind kind, ImpostorBlend blend,
                              ImpostorUniforms* uniforms, std::string* error);

}  // namespace crowdview
