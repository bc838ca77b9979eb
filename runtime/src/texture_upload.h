// Bundle textures into GL textures, counting the GPU bytes each takes (ArchetypeMemory).
// A CBTX (bundle.h TextureArray) goes up as a GL_TEXTURE_2D_ARRAY: BC blocks untouched where the
// driver takes them, decoded to RGBA8 here otherwise; rgba16 stays 16-bit; uv32 goes up as one
// unsigned integer a texel (R32UI) for the shader to unpack (UV maps need the bits, SPEC.md);
// uvblock goes up as its blocks, three RG32UI texels each, decoded in impostor_uv_map.glsl.
// Needs a current context (gl_context.h). Each call leaves its texture bound to its target.
#pragma once

#include <epoxy/gl.h>

#include <cstdint>
#include <string>

#include "bundle.h"

namespace crowdview {

// How textures go up, and the bytes they took so far.
struct TextureUpload {
    bool s3tc = false;              // the driver takes S3TC blocks as they are
    bool force_cpu_decode = false;  // RendererDesc::force_cpu_texture_decode: every block format decoded here
    uint64_t bytes = 0;             // GPU bytes uploaded so far: blocks as they are, a CPU decode as RGBA8
};

// `t` as a texture array labelled `name`. `filtered`: trilinear with a mip chain where the driver
// can make one (diffuse maps; counted as a third more bytes); otherwise nearest, base level only.
GLuint upload_texture_array(const TextureArray& t, bool filtered, const std::string& name, TextureUpload* upload);

// The outfit map (rgba8, one row per outfit) as a GL_TEXTURE_2D, nearest, base level only.
GLuint upload_outfit_map(const TextureArray& outfits, TextureUpload* upload);

// A one-texel white RGBA8 array, for units no material uses: every sampler stays complete.
GLuint upload_unused_material_array();

}  // namespace crowdview
