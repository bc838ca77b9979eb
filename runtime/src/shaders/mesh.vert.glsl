#version 330 core
#include "../config.h"
// A keyframed pose (paper section 4), as a version-2 pose cache stores it (SPEC.md "Pose cache
// version 2"; pose_codec.h): per frame and vertex, three 16-bit position codes within the frame's
// bounds and a 2 x 16-bit octahedral normal, indexed by frame and gl_VertexID.

layout(location = CV_ATTR_UV) in vec2 a_uv;
layout(location = CV_ATTR_INSTANCE_POSE) in vec4 i_pose;  // feet position, heading (struct Instance)
layout(location = CV_ATTR_INSTANCE_IDS) in uvec4 i_ids;   // frame, variation, outfit, tile

uniform usamplerBuffer u_poses;             // R16UI position codes
uniform usamplerBuffer u_pose_normals;      // RG16UI octahedral normal codes
uniform samplerBuffer u_pose_frame_bounds;  // per frame: minimum, then maximum
uniform int u_vertex_count;
uniform mat4 u_view_projection;

out vec2 v_uv;
out vec3 v_normal;
flat out uint v_variation;
flat out uint v_outfit;

const float kCodeMax = 65535.0;  // 16-bit codes (pose_codec.h kPoseCodeMax)

vec2 sign_not_zero(vec2 v) { return vec2(v.x >= 0.0 ? 1.0 : -1.0, v.y >= 0.0 ? 1.0 : -1.0); }

// Meyer et al. 2010, section 3.3: the lower half of the octahedron is folded over the upper's square.
vec3 decode_octahedral(uvec2 code) {
    vec2 e = vec2(code) * (2.0 / kCodeMax) - 1.0;
    float z = 1.0 - abs(e.x) - abs(e.y);
    if (z < 0.0) e = (1.0 - abs(e.yx)) * sign_not_zero(e);
    return normalize(vec3(e, z));
}

void main() {
    int frame = int(i_ids.x);
    int vertex = frame * u_vertex_count + gl_VertexID;
    vec3 lo = texelFetch(u_pose_frame_bounds, 2 * frame).xyz;
    vec3 hi = texelFetch(u_pose_frame_bounds, 2 * frame + 1).xyz;
    uvec3 code = uvec3(texelFetch(u_poses, 3 * vertex).x, texelFetch(u_poses, 3 * vertex + 1).x, texelFetch(u_poses, 3 * vertex + 2).x);
    vec3 position = lo + vec3(code) * ((hi - lo) / kCodeMax);
    vec3 normal = decode_octahedral(texelFetch(u_pose_normals, vertex).xy);
    // Heading h about +Y: +Z turns to (sin h, 0, cos h). Columns are the images of x, y, z.
    float c = cos(i_pose.w), s = sin(i_pose.w);
    mat3 heading = mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
    gl_Position = u_view_projection * vec4(heading * position + i_pose.xyz, 1.0);
    v_uv = a_uv;
    v_normal = heading * normal;
    v_variation = i_ids.y;
    v_outfit = i_ids.z;
}
