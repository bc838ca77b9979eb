#version 330 core
#include "../config.h"
// A camera-facing quad of 2*radius metres around the character's bounds centre, framed like
// the bake's orthographic views (SPEC.md "Impostor maps"): right = up x to_camera, +Y up.
// The (view, frame) samples to blend come from the CPU (view_blend.h) and pass through flat.

layout(location = CV_ATTR_INSTANCE_POSE) in vec4 i_pose;  // feet position, heading
layout(location = CV_ATTR_INSTANCE_IDS) in uvec4 i_ids;   // nearest layer, variation, outfit, nearest tile
layout(location = CV_ATTR_IMPOSTOR_TILES) in uvec4 i_tiles;
layout(location = CV_ATTR_IMPOSTOR_VIEW_WEIGHTS) in vec4 i_view_weights;
layout(location = CV_ATTR_IMPOSTOR_LAYERS) in uvec2 i_layers;
layout(location = CV_ATTR_IMPOSTOR_FRAME_WEIGHT) in float i_frame_weight;

uniform mat4 u_view_projection;
uniform vec3 u_camera_position;
uniform vec3 u_center;  // bounds centre in the character's frame
uniform float u_radius;
uniform int u_tile_size;
uniform int u_azimuth_count;
uniform ivec4 u_crop;  // the stored part of every tile: x, y, width, height (impostor_warp.glsl)

out vec2 v_tile_uv;          // 0..1 across the tile, (0, 0) top-left like the atlas rows
flat out ivec4 v_tile_x;     // the four tiles' origin texels, x (see below)
flat out ivec4 v_tile_y;     // and y
flat out vec4 v_view_weights;
flat out ivec2 v_layers;
flat out float v_frame_weight;
flat out float v_heading;
flat out uint v_variation;
flat out uint v_outfit;
flat out vec3 v_to_camera;   // model space (the bake's views' frame), unit

void main() {
    // Triangle strip corners (-1,-1), (1,-1), (-1,1), (1,1).
    vec2 corner = vec2(float(gl_VertexID & 1), float(gl_VertexID >> 1)) * 2.0 - 1.0;
    float c = cos(i_pose.w), s = sin(i_pose.w);
    mat3 heading = mat3(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
    vec3 center = i_pose.xyz + heading * u_center;
    vec3 to_camera = normalize(u_camera_position - center);
    vec3 side = cross(vec3(0.0, 1.0, 0.0), to_camera);
    // Straight above or below, the bake's +Y-up framing is undefined; use the character's +X.
    vec3 right = length(side) > 1e-4 ? normalize(side) : heading * vec3(1.0, 0.0, 0.0);
    vec3 up = cross(to_camera, right);
    gl_Position = u_view_projection * vec4(center + (corner.x * right + corner.y * up) * u_radius, 1.0);
    v_tile_uv = vec2(0.5 + 0.5 * corner.x, 0.5 - 0.5 * corner.y);
    ivec4 tiles = ivec4(i_tiles);
    // Where tile texel (0, 0) would lie: the cell's origin less the crop's corner (may be negative).
    v_tile_x = (tiles % u_azimuth_count) * u_crop.z - u_crop.x;
    v_tile_y = (tiles / u_azimuth_count) * u_crop.w - u_crop.y;
    v_view_weights = i_view_weights;
    v_layers = ivec2(i_layers);
    v_frame_weight = i_frame_weight;
    v_heading = i_pose.w;
    v_variation = i_ids.y;
    v_outfit = i_ids.z;
    v_to_camera = transpose(heading) * to_camera;
}
