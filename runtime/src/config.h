// crowdview limits and shared layout, read by C++ (renderer.cpp) and by every shader
// (the shader loader pastes this file in place of `#include "../config.h"`).
// Only #define lines and comments: the file must parse as both C++ and GLSL.
#ifndef CROWDVIEW_CONFIG_H
#define CROWDVIEW_CONFIG_H

// Diffuse texture arrays a UV impostor can address: GLSL 3.30 only indexes sampler arrays
// with constants, so the impostor shader unrolls one branch per material.
#define CV_MAX_MATERIALS 4

// Colour regions: alpha = 17 * r, r in 0..15 (shared_formats/SPEC.md, "Colour regions").
#define CV_REGION_COUNT 16
#define CV_REGION_SCALE 17.0

// Vertex attribute locations. Per-vertex: the static UV of a pose cache (positions and
// normals come from a buffer texture indexed by gl_VertexID). Per-instance: struct Instance.
#define CV_ATTR_UV 0
#define CV_ATTR_INSTANCE_POSE 1   // vec4: position.xyz (metres), heading (radians about +Y)
#define CV_ATTR_INSTANCE_IDS 2    // uvec4 (16-bit): frame or impostor layer, variation, outfit, impostor tile
// Per-impostor blend samples: struct ImpostorSamples (crowd.h), a second instance buffer.
#define CV_ATTR_IMPOSTOR_TILES 3         // uvec4 (16-bit): four atlas tiles
#define CV_ATTR_IMPOSTOR_VIEW_WEIGHTS 4  // vec4: their weights, summing to 1
#define CV_ATTR_IMPOSTOR_LAYERS 5        // uvec2 (16-bit): two atlas layers (baked frames)
#define CV_ATTR_IMPOSTOR_FRAME_WEIGHT 6  // float: weight of the second layer

// Texture units. Mesh draws use POSES, OUTFITS and DIFFUSE0; impostor draws all but POSES.
#define CV_UNIT_POSES 0           // usamplerBuffer R16UI: per frame per vertex, three position codes
#define CV_UNIT_OUTFITS 1         // outfit colour map, 16 x outfit_count
#define CV_UNIT_IMPOSTOR_NORMAL 2
#define CV_UNIT_IMPOSTOR_UV 3
#define CV_UNIT_IMPOSTOR_DETAIL 4
#define CV_UNIT_DIFFUSE0 5        // CV_MAX_MATERIALS consecutive units: units 5..8, under GL 3.3's 16
#define CV_UNIT_IMPOSTOR_SURFACE 9
#define CV_UNIT_POSE_NORMALS 10       // usamplerBuffer RG16UI: per frame per vertex, one octahedral normal code
#define CV_UNIT_POSE_FRAME_BOUNDS 11  // samplerBuffer RGBA32F: per frame, its positions' minimum, then maximum
// A skinned pose cache (SPEC.md "Skinned pose cache"; mesh.vert.glsl with CV_SKINNED 1) reads its rest
// mesh and matrices on the quantized streams' units, its influences on two more.
#define CV_UNIT_SKIN_REST_POSITIONS CV_UNIT_POSES           // samplerBuffer R32F: per vertex, x, y, z
#define CV_UNIT_SKIN_REST_NORMALS CV_UNIT_POSE_NORMALS      // samplerBuffer R32F: per vertex, x, y, z
#define CV_UNIT_SKIN_MATRICES CV_UNIT_POSE_FRAME_BOUNDS     // samplerBuffer RGBA32F: per frame per joint, three rows
#define CV_UNIT_SKIN_JOINTS 12                              // usamplerBuffer RGBA16UI: per vertex, four joints
#define CV_UNIT_SKIN_WEIGHTS 13                             // usamplerBuffer RGBA16UI: per vertex, four weight codes

// Impostor reprojection (shaders/impostor_warp.glsl). The surface map's codes span +-range * radius
// metres (SPEC.md "Impostor maps"; crowdbake.bake.surface_maps DEPTH_RANGE, MOTION_RANGE); the
// fixed-point steps are crowdbake.bake.impostor_warp.DEFAULT_ITERATIONS. A bundle with more views than
// the uniform arrays hold is drawn without reprojection (the bake allows 64 azimuths, 9 rings).
#define CV_SURFACE_DEPTH_RANGE 1.0
#define CV_SURFACE_MOTION_RANGE 0.5
#define CV_WARP_ITERATIONS 4
// Before those steps the pixel's ray is marched through the source view's depth from the camera's side,
// one step for each tile texel its point crosses in the source tile (tile size times the sine of the
// angle between the two views) and at most CV_MARCH_STEPS, then halved CV_MARCH_REFINE times
// (crowdbake.reference.impostor_warp MARCH_STEPS, MARCH_REFINE); steps whose points fall outside the
// source's crop are skipped (march_span: they cannot hit).
#define CV_MARCH_STEPS 48
#define CV_MARCH_REFINE 4
#define CV_MAX_AZIMUTHS 64
#define CV_MAX_ELEVATIONS 9

// Impostor silhouettes (impostor_uv_map.glsl edge_alpha): a pixel whose reprojected samples cover a
// share c of their weight is drawn with opacity smoothstep(LOW, 1 - LOW, c), blended over what is
// behind it. Between baked views and frames the samples' silhouettes disagree by a texel or two; a
// hard cut at c > 0.5 kept only where they agree and thinned the figure (CesiumMan's SSIM between
// views 0.815 with the cut; services/benchmarks/LOG.md "Soft impostor edges").
#define CV_EDGE_LOW 0.1

// Impostor colours between baked views (impostor_uv.frag.glsl): a reprojected sample whose last
// fixed-point step still misses its pixel by more than CV_MISS_LOW target texels found a surface
// its view does not show there (an occluded part); its colour's weight falls to 0 at CV_MISS_HIGH.
// The pixel takes the converged samples' colour where they hold over CV_TRUSTED_SHARE of the
// blended coverage; the silhouette (coverage) counts every sample (services/benchmarks/LOG.md
// "Anti-aliased impostor silhouettes").
#define CV_MISS_LOW 0.5
#define CV_MISS_HIGH 2.0
#define CV_TRUSTED_SHARE 0.05

// Ambient term of the Lambert lighting shared by mesh and impostor shaders, so a mesh and
// its impostor are lit alike at the LOD switch.
#define CV_AMBIENT 0.35

#endif
