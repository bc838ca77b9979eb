#version 330 core
#include "../config.h"
// A keyframed pose (paper section 4), as a version-2 pose cache stores it (SPEC.md "Pose cache
// version 2"; pose_codec.h): per frame and vertex, three 16-bit position codes within the frame's
// bounds and a 2 x 16-bit octahedral normal, indexed by frame and gl_VertexID.
// With CV_SKINNED 1 (crowd_programs.cpp defines it, 0 or 1), a skinned pose cache instead (SPEC.md
// "Skinned pose cache"; skinned_pose.h): the rest mesh skinned by four joints a vertex at the frame.

layout(location = CV_ATTR_UV) in vec2 a_uv;
layout(location = CV_ATTR_INSTANCE_POSE) in vec4 i_pose;  // feet position, heading (struct Instance)
layout(location = CV_ATTR_INSTANCE_IDS) in uvec4 i_ids;   // frame, variation, outfit, tile

uniform mat4 u_view_projection;

out vec2 v_uv;
out vec3 v_normal;
flat out uint v_variation;
flat out uint v_outfit;

const float kCodeMax = 65535.0;  // 16-bit codes (pose_codec.h kPoseCodeMax; the weights' unorm16 too)

#if CV_SKINNED
uniform samplerBuffer u_rest_positions;  // R32F: per vertex x, y, z (bind pose)
uniform samplerBuffer u_rest_normals;    // R32F: per vertex x, y, z
uniform samplerBuffer u_joint_matrices;  // RGBA32F: per frame per joint, the three rows of its 3x4 matrix
uniform usamplerBuffer u_joints;         // RGBA16UI: per vertex, four joint indices
uniform usamplerBuffer u_weights;        // RGBA16UI: per vertex, four weight codes (weight = code / 65535)
uniform int u_joint_count;

vec3 fetch_vec3(samplerBuffer buffer, int vertex) {
    return vec3(texelFetch(buffer, 3 * vertex).x, texelFetch(buffer, 3 * vertex + 1).x, texelFetch(buffer, 3 * vertex + 2).x);
}

// Linear blend skinning (SPEC.md): p = sum w_k A_k (rest, 1), n = normalize(sum w_k L_k rest_n), L_k the
// 3x3 block of A_k (the normal turned as the position is: linear in the matrices, so a join that blends
// two poses' matrices turns normals as blending their normals does). Influences of weight 0 are skipped.
void pose_vertex(int frame, out vec3 position, out vec3 normal) {
    vec4 rest = vec4(fetch_vec3(u_rest_positions, gl_VertexID), 1.0);
    vec3 rest_normal = fetch_vec3(u_rest_normals, gl_VertexID);
    uvec4 joints = texelFetch(u_joints, gl_VertexID);
    vec4 weights = vec4(texelFetch(u_weights, gl_VertexID)) / kCodeMax;
    position = vec3(0.0);
    normal = vec3(0.0);
    for (int k = 0; k < 4; ++k) {
        if (weights[k] == 0.0) continue;
        int row = 3 * (frame * u_joint_count + int(joints[k]));
        vec4 r0 = texelFetch(u_joint_matrices, row), r1 = texelFetch(u_joint_matrices, row + 1), r2 = texelFetch(u_joint_matrices, row + 2);
        position += weights[k] * vec3(dot(r0, rest), dot(r1, rest), dot(r2, rest));
        normal += weights[k] * vec3(dot(r0.xyz, rest_normal), dot(r1.xyz, rest_normal), dot(r2.xyz, rest_normal));
    }
    normal = normalize(normal);
}
#else
uniform usamplerBuffer u_poses;             // R16UI position codes
uniform usamplerBuffer u_pose_normals;      // RG16UI octahedral normal codes
uniform samplerBuffer u_pose_frame_bounds;  // per frame: minimum, then maximum
uniform int u_vertex_count;

vec2 sign_not_zero(vec2 v) { return vec2(v.x >= 0.0 ? 1.0 : -1.0, v.y >= 0.0 ? 1.0 : -1.0); }

// Meyer et al. 2010, section 3.3: the lower half of the octahedron is folded over the upper's square.
vec3 decode_octahedral(uvec2 code) {
    vec2 e = vec2(code) * (2.0 / kCodeMax) - 1.0;
    float z = 1.0 - abs(e.x) - abs(e.y);
    if (z < 0.0) e = (1.0 - abs(e.yx)) * sign_not_zero(e);
    return normalize(vec3(e, z));
}

void pose_vertex(int frame, out vec3 position, out vec3 normal) {
    int vertex = frame * u_vertex_count + gl_VertexID;
    vec3 lo = texelFetch(u_pose_frame_bounds, 2 * frame).xyz;
    vec3 hi = texelFetch(u_pose_frame_bounds, 2 * frame + 1).xyz;
    uvec3 code = uvec3(texelFetch(u_poses, 3 * vertex).x, texelFetch(u_poses, 3 * vertex + 1).x, texelFetch(u_poses, 3 * vertex + 2).x);
    position = lo + vec3(code) * ((hi - lo) / kCodeMax);
    normal = decode_octahedral(texelFetch(u_pose_normals, vertex).xy);
}
#endif

void main() {
    int frame = int(i_ids.x);
    vec3 position, normal;
    pose_vertex(frame, position, normal);
    // Heading h about +Y: +Z turns to (sin h, 0, cos h). Columns are the images of x, y, z.
    float c = cos(i_pose.w), s = sin(i_pose.w);
    mat3 heading = mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
    gl_Position = u_view_projection * vec4(heading * position + i_pose.xyz, 1.0);
    v_uv = a_uv;
    v_normal = heading * normal;
    v_variation = i_ids.y;
    v_outfit = i_ids.z;
}
