// Bundle textures into GL textures (see texture_upload.h).
#include "texture_upload.h"

#include <vector>

#include "gl_programs.h"

namespace crowdview {

namespace {

bool is_s3tc(PixelFormat format) { return format == PixelFormat::bc1 || format == PixelFormat::bc2; }

// BC5 (RGTC2) is core since OpenGL 3.0; S3TC needs the extension. Either may be decoded here instead.
bool blocks_go_up_as_they_are(PixelFormat format, const TextureUpload& upload) {
    return format == PixelFormat::bc5 ? !upload.force_cpu_decode : is_s3tc(format) && upload.s3tc;
}

// Every layer of a block-compressed `t`, decoded to RGBA8 one after the other.
std::vector<uint8_t> decode_layers_rgba8(const TextureArray& t) {
    std::vector<uint8_t> rgba;
    rgba.reserve(size_t(t.width) * t.height * 4 * t.layer_count);
    for (uint32_t k = 0; k < t.layer_count; ++k) {
        const std::vector<uint8_t> layer = decode_layer_rgba8(t, k);
        rgba.insert(rgba.end(), layer.begin(), layer.end());
    }
    return rgba;
}

// Level 0 of the bound texture array from `t`; returns the GPU bytes it takes.
uint64_t store_level0(const TextureArray& t, const TextureUpload& upload) {
    const GLsizei w = GLsizei(t.width), h = GLsizei(t.height), layers = GLsizei(t.layer_count);
    if (blocks_go_up_as_they_are(t.format, upload)) {
        // bc1 is RGB in the spec (normal and surface maps): the RGB flavour keeps alpha at 1.
        const GLenum format = t.format == PixelFormat::bc5   ? GL_COMPRESSED_RG_RGTC2
                              : t.format == PixelFormat::bc1 ? GL_COMPRESSED_RGB_S3TC_DXT1_EXT
                                                             : GL_COMPRESSED_RGBA_S3TC_DXT3_EXT;
        glCompressedTexImage3D(GL_TEXTURE_2D_ARRAY, 0, format, w, h, layers, 0, GLsizei(t.data.size()), t.data.data());
    } else if (is_s3tc(t.format) || t.format == PixelFormat::bc5) {
        const std::vector<uint8_t> rgba = decode_layers_rgba8(t);
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RGBA8, w, h, layers, 0, GL_RGBA, GL_UNSIGNED_BYTE, rgba.data());
        return rgba.size();
    } else if (t.format == PixelFormat::rgba16) {
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RGBA16, w, h, layers, 0, GL_RGBA, GL_UNSIGNED_SHORT, t.data.data());
    } else if (t.format == PixelFormat::uv32) {  // integer texture: nearest filtering only (set_sampling)
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_R32UI, w, h, layers, 0, GL_RED_INTEGER, GL_UNSIGNED_INT, t.data.data());
    } else if (t.format == PixelFormat::uvblock) {
        // Each 24-byte block is three RG32UI texels in a row: block rows are texture rows, as stored.
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RG32UI, 3 * (w / 4), h / 4, layers, 0, GL_RG_INTEGER, GL_UNSIGNED_INT, t.data.data());
    } else {
        glTexImage3D(GL_TEXTURE_2D_ARRAY, 0, GL_RGBA8, w, h, layers, 0, GL_RGBA, GL_UNSIGNED_BYTE, t.data.data());
    }
    return t.data.size();
}

// Filtering and wrap of the bound texture array; `filtered` also makes its mip chain.
void set_sampling(bool filtered) {
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAG_FILTER, filtered ? GL_LINEAR : GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_WRAP_S, filtered ? GL_REPEAT : GL_CLAMP_TO_EDGE);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_WRAP_T, filtered ? GL_REPEAT : GL_CLAMP_TO_EDGE);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAX_LEVEL, 0);
    if (!filtered) return;
    while (glGetError() != GL_NO_ERROR) {
    }
    glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAX_LEVEL, 1000);  // the levels glGenerateMipmap fills
    glGenerateMipmap(GL_TEXTURE_2D_ARRAY);
    if (glGetError() == GL_NO_ERROR) {
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_LINEAR_MIPMAP_LINEAR);
    } else {  // some drivers cannot mipmap compressed arrays: stay on level 0
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MAX_LEVEL, 0);
        glTexParameteri(GL_TEXTURE_2D_ARRAY, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
    }
}

}  // namespace

GLuint upload_texture_array(const TextureArray& t, bool filtered, const std::string& name, TextureUpload* upload) {
    GLuint texture = 0;
    glGenTextures(1, &texture);
    glBindTexture(GL_TEXTURE_2D_ARRAY, texture);
    glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
    const uint64_t level0 = store_level0(t, *upload);
    upload->bytes += filtered ? level0 * 4 / 3 : level0;  // a mip chain adds a third
    set_sampling(filtered);
    label(GL_TEXTURE, texture, name);
    return texture;
}

GLuint upload_outfit_map(const TextureArray& outfits, TextureUpload* upload) {
    GLuint texture = 0;
    glGenTextures(1, &texture);
    glBindTexture(GL_TEXTURE_2D, texture);
    glTexImage2D(GL_TEXTURE_2D, 0, GL_RGBA8, GLsizei(outfits.width), GLsizei(outfits.height), 0, GL_RGBA, GL_UNSIGNED_BYTE,
                 outfits.data.data());
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    glTexParameteri(GL_TEXTURE_2D, GL_TEXTURE_MAX_LEVEL, 0);
    label(GL_TEXTURE, texture, "outfits");
    upload->bytes += uint64_t(outfits.width) * outfits.height * 4;
    return texture;
}

GLuint upload_unused_material_array() {
    TextureArray white;
    white.width = white.height = white.layer_count = 1;
    white.data.assign(4, 255);
    TextureUpload upload;
    return upload_texture_array(white, false, "unused-material", &upload);
}

}  // namespace crowdview
