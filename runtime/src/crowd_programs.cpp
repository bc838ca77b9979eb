// The mesh and impostor programs (see crowd_programs.h).
#include "crowd_programs.h"

#include <algorithm>
#include <vector>

#include "gl_programs.h"

namespace crowdview {

namespace {

const char* flag(bool on) { return on ? "1" : "0"; }

MeshUniforms mesh_uniforms(GLuint program) {
    MeshUniforms u;
    u.view_projection = uniform(program, "u_view_projection");
    u.light_dir = uniform(program, "u_light_dir");
    u.vertex_count = uniform(program, "u_vertex_count");
    u.variations = uniform(program, "u_variations");
    u.has_regions = uniform(program, "u_has_regions");
    u.joint_count = uniform(program, "u_joint_count");
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

// The impostor programs read the UV map in the bundle's format (impostor_uv_map.glsl), and a
// bc5 normal map as each tile's view-space XY.
std::string format_defines(const Bundle& bundle) {
    return std::string("#define CV_UV_MAP_UV32 ") + flag(bundle.impostor_uv.format == PixelFormat::uv32) + "\n" +
           "#define CV_UV_MAP_UVBLOCK " + flag(bundle.impostor_uv.format == PixelFormat::uvblock) + "\n" +
           "#define CV_NORMAL_VIEW_XY " + flag(bundle.impostor_normal.format == PixelFormat::bc5) + "\n";
}

// The sample counts of `blend`: views and frames mixed, and whether samples are reprojected.
std::string blend_defines(ImpostorBlend blend) {
    const bool warp = blend == ImpostorBlend::warp;
    const bool all = blend == ImpostorBlend::full || warp;
    const bool views = blend == ImpostorBlend::views || all;
    const bool frames = blend == ImpostorBlend::frames || all;
    return std::string("#define CV_VIEW_SAMPLES ") + (views ? "4" : "1") + "\n#define CV_FRAME_SAMPLES " + (frames ? "2" : "1") +
           "\n#define CV_WARP " + flag(warp) + "\n";
}

// Sampler units, and the baked views' angles for the warp shader's per-sample view bases (unused
// lengths stay 0). Leaves `program` in use.
void set_impostor_constants(GLuint program, const ImpostorInfo& impostor) {
    glUseProgram(program);
    glUniform1i(uniform(program, "u_outfits"), CV_UNIT_OUTFITS);
    glUniform1i(uniform(program, "u_normal_map"), CV_UNIT_IMPOSTOR_NORMAL);
    glUniform1i(uniform(program, "u_uv_map"), CV_UNIT_IMPOSTOR_UV);
    glUniform1i(uniform(program, "u_detail_map"), CV_UNIT_IMPOSTOR_DETAIL);
    glUniform1i(uniform(program, "u_surface_map"), CV_UNIT_IMPOSTOR_SURFACE);
    const std::vector<float>& azimuths = impostor.azimuths_deg;
    const std::vector<float>& elevations = impostor.elevations_deg;
    glUniform1fv(uniform(program, "u_azimuths_deg"), GLsizei(std::min<size_t>(azimuths.size(), CV_MAX_AZIMUTHS)), azimuths.data());
    glUniform1fv(uniform(program, "u_elevations_deg"), GLsizei(std::min<size_t>(elevations.size(), CV_MAX_ELEVATIONS)),
                 elevations.data());
    for (int k = 0; k < CV_MAX_MATERIALS; ++k)
        glUniform1i(uniform(program, ("u_diffuse[" + std::to_string(k) + "]").c_str()), CV_UNIT_DIFFUSE0 + k);
}

}  // namespace

GLuint build_mesh_program(const std::string& shader_dir, bool skinned, MeshUniforms* uniforms, std::string* error) {
    const GLuint program = build_program(shader_dir, "mesh", "mesh", error, std::string("#define CV_SKINNED ") + flag(skinned) + "\n");
    if (!program) return 0;
    if (skinned) label(GL_PROGRAM, program, "mesh:skinned");
    *uniforms = mesh_uniforms(program);
    glUseProgram(program);
    // Each program has the samplers of its variant; glUniform ignores the other's (location -1).
    glUniform1i(uniform(program, "u_poses"), CV_UNIT_POSES);
    glUniform1i(uniform(program, "u_pose_normals"), CV_UNIT_POSE_NORMALS);
    glUniform1i(uniform(program, "u_pose_frame_bounds"), CV_UNIT_POSE_FRAME_BOUNDS);
    glUniform1i(uniform(program, "u_rest_positions"), CV_UNIT_SKIN_REST_POSITIONS);
    glUniform1i(uniform(program, "u_rest_normals"), CV_UNIT_SKIN_REST_NORMALS);
    glUniform1i(uniform(program, "u_joint_matrices"), CV_UNIT_SKIN_MATRICES);
    glUniform1i(uniform(program, "u_joints"), CV_UNIT_SKIN_JOINTS);
    glUniform1i(uniform(program, "u_weights"), CV_UNIT_SKIN_WEIGHTS);
    glUniform1i(uniform(program, "u_outfits"), CV_UNIT_OUTFITS);
    glUniform1i(uniform(program, "u_diffuse"), CV_UNIT_DIFFUSE0);
    return program;
}

std::string impostor_programs_refusal(const Bundle& bundle) {
    const ImpostorInfo& impostor = bundle.manifest.impostor;
    if (bundle.impostor_normal.format != PixelFormat::bc5 ||
        (impostor.azimuths_deg.size() <= CV_MAX_AZIMUTHS && impostor.elevations_deg.size() <= CV_MAX_ELEVATIONS))
        return "";
    return "a bc5 normal map needs at most " + std::to_string(CV_MAX_AZIMUTHS) + " azimuths and " +
           std::to_string(CV_MAX_ELEVATIONS) + " elevations, the bundle has " + std::to_string(impostor.azimuths_deg.size()) +
           " and " + std::to_string(impostor.elevations_deg.size());
}

GLuint build_impostor_program(const std::string& shader_dir, const Bundle& bundle, ImpostorKind kind, ImpostorBlend blend,
                              ImpostorUniforms* uniforms, std::string* error) {
    const GLuint program = build_program(shader_dir, "impostor", kind == ImpostorKind::uv ? "impostor_uv" : "impostor_detail",
                                         error, format_defines(bundle) + blend_defines(blend));
    if (!program) return 0;
    *uniforms = impostor_uniforms(program);
    set_impostor_constants(program, bundle.manifest.impostor);
    return program;
}

}  // namespace crowdview
