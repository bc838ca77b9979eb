// BC1, BC2 and BC5 block decoding to RGBA8 (bundle.h decode_layer_rgba8): the CPU fallback for GL
// drivers without S3TC, and how tests look at block-compressed texels.
#include "bundle.h"

#include <cstring>

namespace crowdview {

// ---------------------------------------------------------------------------------------
// Block decoding (S3TC as in EXT_texture_compression_s3tc)

namespace {

uint32_t read_u32(const uint8_t* p) {
    uint32_t v;
    std::memcpy(&v, p, 4);  // little-endian host (bundle.cpp refuses to build for any other)
    return v;
}

void rgb565(uint16_t c, int* rgb) {
    const int r = (c >> 11) & 31, g = (c >> 5) & 63, b = c & 31;
    rgb[0] = (r << 3) | (r >> 2);
    rgb[1] = (g << 2) | (g >> 4);
    rgb[2] = (b << 3) | (b >> 2);
}

// Writes a 4x4 RGBA8 block from an 8-byte colour block. BC2 colour blocks always use the
// four-colour mode; BC1 switches to three colours plus black when colour0 <= colour1.
void decode_colour_block(const uint8_t* block, bool always_four_colours, uint8_t texels[16][4]) {
    const uint16_t c0 = uint16_t(block[0] | block[1] << 8), c1 = uint16_t(block[2] | block[3] << 8);
    int palette[4][4];
    rgb565(c0, palette[0]);
    rgb565(c1, palette[1]);
    palette[0][3] = palette[1][3] = palette[2][3] = palette[3][3] = 255;
    for (int ch = 0; ch < 3; ++ch) {
        if (always_four_colours || c0 > c1) {
            palette[2][ch] = (2 * palette[0][ch] + palette[1][ch]) / 3;
            palette[3][ch] = (palette[0][ch] + 2 * palette[1][ch]) / 3;
        } else {
            palette[2][ch] = (palette[0][ch] + palette[1][ch]) / 2;
            palette[3][ch] = 0;  // black; bc1 is RGB in this format, so alpha stays opaque
        }
    }
    const uint32_t bits = read_u32(block + 4);
    for (int i = 0; i < 16; ++i) {
        const int index = (bits >> (2 * i)) & 3;
        for (int ch = 0; ch < 4; ++ch) texels[i][ch] = uint8_t(palette[index][ch]);
    }
}

// One BC4 block (RGTC unsigned) to 16 values: endpoints r0 > r1 interpolate six values in sevenths,
// otherwise four in fifths, then 0 and 255; rounded to nearest (crowdbake.bake.compression._decode_bc4).
void decode_bc4_block(const uint8_t* block, uint8_t values[16]) {
    const int r0 = block[0], r1 = block[1];
    int palette[8] = {r0, r1, 0, 0, 0, 0, 0, 0};
    if (r0 > r1) {
        for (int k = 1; k < 7; ++k) palette[k + 1] = ((7 - k) * r0 + k * r1 + 3) / 7;
    } else {
        for (int k = 1; k < 5; ++k) palette[k + 1] = ((5 - k) * r0 + k * r1 + 2) / 5;
        palette[6] = 0, palette[7] = 255;
    }
    uint64_t bits = 0;
    for (int b = 0; b < 6; ++b) bits |= uint64_t(block[2 + b]) << (8 * b);
    for (int i = 0; i < 16; ++i) values[i] = uint8_t(palette[(bits >> (3 * i)) & 7]);
}

}  // namespace

std::vector<uint8_t> decode_layer_rgba8(const TextureArray& texture, uint32_t layer) {
    const uint32_t w = texture.width, h = texture.height;
    std::vector<uint8_t> rgba(size_t(w) * h * 4);
    if (layer >= texture.layer_count) return rgba;
    const uint8_t* src = texture.layer(layer);
    switch (texture.format) {
    case PixelFormat::rgba8:
        std::memcpy(rgba.data(), src, rgba.size());
        break;
    case PixelFormat::rgba16:
        for (size_t i = 0; i < rgba.size(); ++i) rgba[i] = src[2 * i + 1];
        break;
    case PixelFormat::uv32:
        for (size_t i = 0; i < size_t(w) * h; ++i) {
            uint32_t word;
            std::memcpy(&word, src + 4 * i, 4);  // little-endian host, as everywhere here
            const Uv32Texel t = unpack_uv32(word);
            rgba[4 * i + 0] = uint8_t((word & kUv32CoordMax) >> 6);  // the top 8 of 14 bits
            rgba[4 * i + 1] = uint8_t(((word >> 14) & kUv32CoordMax) >> 6);
            rgba[4 * i + 2] = uint8_t(t.material);
            rgba[4 * i + 3] = t.covered ? 255 : 0;
        }
        break;
    case PixelFormat::uvblock:  // (u, v) to 8 bits, material and coverage 255/0, as rgba16 would
        for (uint32_t by = 0; by < h / 4; ++by)
            for (uint32_t bx = 0; bx < w / 4; ++bx)
                for (uint32_t i = 0; i < 16; ++i) {
                    const UvBlockTexel t = unpack_uvblock_texel(src + (size_t(by) * (w / 4) + bx) * kUvBlockBytes, i);
                    uint8_t* texel = &rgba[((size_t(by) * 4 + i / 4) * w + bx * 4 + i % 4) * 4];
                    texel[0] = uint8_t(t.qu >> 4), texel[1] = uint8_t(t.qv >> 4);
                    texel[2] = uint8_t(t.material), texel[3] = t.covered ? 255 : 0;
                }
        break;
    case PixelFormat::bc1:
    case PixelFormat::bc2: {
        const bool bc2 = texture.format == PixelFormat::bc2;
        const size_t block_size = bc2 ? 16 : 8;
        uint8_t texels[16][4];
        for (uint32_t by = 0; by < h / 4; ++by)
            for (uint32_t bx = 0; bx < w / 4; ++bx) {
                const uint8_t* block = src + (size_t(by) * (w / 4) + bx) * block_size;
                decode_colour_block(bc2 ? block + 8 : block, bc2, texels);
                if (bc2)  // explicit 4-bit alpha, expanded by 17 so region codes survive exactly
                    for (int i = 0; i < 16; ++i) texels[i][3] = uint8_t(((block[i / 2] >> (4 * (i % 2))) & 15) * 17);
                for (int i = 0; i < 16; ++i)
                    std::memcpy(&rgba[((size_t(by) * 4 + i / 4) * w + bx * 4 + i % 4) * 4], texels[i], 4);
            }
        break;
    }
    case PixelFormat::bc5: {  // R and G, B = 0, A = 255, as OpenGL returns an RG texture
        uint8_t red[16], green[16];
        for (uint32_t by = 0; by < h / 4; ++by)
            for (uint32_t bx = 0; bx < w / 4; ++bx) {
                const uint8_t* block = src + (size_t(by) * (w / 4) + bx) * 16;
                decode_bc4_block(block, red);
                decode_bc4_block(block + 8, green);
                for (int i = 0; i < 16; ++i) {
                    uint8_t* texel = &rgba[((size_t(by) * 4 + i / 4) * w + bx * 4 + i % 4) * 4];
                    texel[0] = red[i], texel[1] = green[i], texel[2] = 0, texel[3] = 255;
                }
            }
        break;
    }
    }
    return rgba;
}


}  // namespace crowdview
