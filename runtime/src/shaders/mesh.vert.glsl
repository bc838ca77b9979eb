#version 330 core
#include "../config.h"
// A keyframed pose (paper section 4): positions and normals of every frame sit in one buffer
// texture, two RGBA32F texels per vertex per frame, indexed by frame and gl_VertexID.

layout(location = CV_ATTR_UV) in vec2 a_uv;
layout(location = CV_ATTR_INSTANCE_POSE) in vec4 i_pose;  // feet position, heading (struct Instance)
layout(location = CV_ATTR_INSTANCE_IDS) in uvec4 i_ids;   // frame, variation, outfit, tile

uniform samplerBuffer u_poses;
uniform int u_vertex_count;
uniform mat4 u_view_projection;

out vec2 v_uv;
out vec3 v_normal;
flat out uint v_variation;
flat out uint v_outfit;

void main() {
    int texel = (int(i_ids.x) * u_vertex_count + gl_VertexID) * 2;
    vec3 position = texelFetch(u_poses, texel).xyz;
    vec3 normal = texelFetch(u_poses, texel + 1).xyz;
    // Heading h about +Y: +Z turns to (sin h, 0, cos h). Columns are the images of x, y, z.
    float c = cos(i_pose.w), s = sin(i_pose.w);
    mat3 heading = mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
    gl_Position = u_view_projection * vec4(heading * position + i_pose.xyz, 1.0);
    v_uv = a_uv;
    v_normal = heading * normal;
    v_variation = i_ids.y;
    v_outfit = i_ids.z;
}
