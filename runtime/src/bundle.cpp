// Bundle reader: SPEC.md's binary files, manifest and verification, in the spec's order.
#include "bundle.h"

#include <nlohmann/json.hpp>
#include <openssl/evp.h>
#include <sys/stat.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <regex>

#if !defined(__BYTE_ORDER__) || __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "bundle.cpp reads the little-endian bundle format with memcpy; add byte swaps for this target"
#endif

namespace crowdview {

using json = nlohmann::json;

const char* error_code_name(ErrorCode code) {
    switch (code) {
    case ErrorCode::ok: return "ok";
    case ErrorCode::manifest_invalid: return "manifest_invalid";
    case ErrorCode::unsupported_format_version: return "unsupported_format_version";
    case ErrorCode::unsafe_path: return "unsafe_path";
    case ErrorCode::missing_file: return "missing_file";
    case ErrorCode::size_mismatch: return "size_mismatch";
    case ErrorCode::sha256_mismatch: return "sha256_mismatch";
    case ErrorCode::truncated: return "truncated";
    case ErrorCode::bad_magic: return "bad_magic";
    case ErrorCode::unsupported_version: return "unsupported_version";
    case ErrorCode::invalid_header: return "invalid_header";
    case ErrorCode::invalid_data: return "invalid_data";
    case ErrorCode::fetch_failed: return "fetch_failed";
    case ErrorCode::not_found: return "not_found";
    case ErrorCode::unauthorized: return "unauthorized";
    case ErrorCode::over_budget: return "over_budget";
    }
    return "unknown";
}

std::string printable(const std::string& text) {
    static const char* hex = "0123456789abcdef";
    std::string out;
    out.reserve(text.size());
    for (size_t i = 0; i < text.size(); ++i) {
        const uint8_t c = uint8_t(text[i]);
        if (c < 0x20 || c == 0x7f) {
            out += "\\x";
            out += hex[c >> 4];
            out += hex[c & 15];
        } else if (c == 0xc2 && i + 1 < text.size() && uint8_t(text[i + 1]) >= 0x80 && uint8_t(text[i + 1]) <= 0x9f) {
            const uint8_t code = uint8_t(text[++i]);  // U+0080..U+009F
            out += "\\u00";
            out += hex[code >> 4];
            out += hex[code & 15];
        } else {
            out += char(c);
        }
    }
    return out;
}

Status make_error(ErrorCode code, const char* function, const std::string& file, const std::string& detail) {
    Status status;
    status.code = code;
    status.file = printable(file);
    status.message = std::string(function) + ": " + status.file + ": " + error_code_name(code) + ": " + printable(detail);
    return status;
}

const char* pixel_format_name(PixelFormat format) {
    switch (format) {
    case PixelFormat::rgba8: return "rgba8";
    case PixelFormat::rgba16: return "rgba16";
    case PixelFormat::bc1: return "bc1";
    case PixelFormat::bc2: return "bc2";
    case PixelFormat::uv32: return "uv32";
    case PixelFormat::uvblock: return "uvblock";
    case PixelFormat::bc5: return "bc5";
    }
    return "unknown";
}

// ---------------------------------------------------------------------------------------
// Binary files

namespace {

uint32_t read_u32(const uint8_t* p) {
    uint32_t v;
    std::memcpy(&v, p, 4);
    return v;
}

float read_f32(const uint8_t* p) {
    float v;
    std::memcpy(&v, p, 4);
    return v;
}

// Bytes of one layer in 128-bit arithmetic, so hostile header fields cannot overflow; 0 for
// an unknown format or a BC size that is not a multiple of 4.
unsigned __int128 layer_bytes_wide(uint32_t format, uint32_t width, uint32_t height) {
    const unsigned __int128 w = width, h = height;
    switch (format) {
    case 1: return 4 * w * h;
    case 2: return 8 * w * h;
    case 3: return (width % 4 || height % 4) ? 0 : 8 * (w / 4) * (h / 4);
    case 4: return (width % 4 || height % 4) ? 0 : 16 * (w / 4) * (h / 4);
    case 5: return 4 * w * h;
    case 6: return (width % 4 || height % 4) ? 0 : 24 * (w / 4) * (h / 4);
    case 7: return (width % 4 || height % 4) ? 0 : 16 * (w / 4) * (h / 4);
    default: return 0;
    }
}

// The common header, in SPEC.md's order: length, magic, version, header_size, file_size.
Status check_common_header(const uint8_t* data, size_t size, const std::string& file, const char* function,
                           const char* magic, uint32_t header_size) {
    if (size < 16)
        return make_error(ErrorCode::truncated, function, file,
                          std::to_string(size) + " bytes is shorter than the 16-byte common header");
    if (std::memcmp(data, magic, 4) != 0) {
        std::string got;
        for (int i = 0; i < 4; ++i) got += (data[i] >= 32 && data[i] < 127) ? char(data[i]) : '?';
        return make_error(ErrorCode::bad_magic, function, file, "magic is '" + got + "', expected '" + magic + "'");
    }
    const uint32_t version = read_u32(data + 4);
    if (version != 1)
        return make_error(ErrorCode::unsupported_version, function, file,
                          "version " + std::to_string(version) + ", this reader supports 1");
    const uint32_t declared_header = read_u32(data + 8);
    if (declared_header != header_size)
        return make_error(ErrorCode::invalid_header, function, file,
                          "header_size is " + std::to_string(declared_header) + ", expected " + std::to_string(header_size));
    const uint32_t file_size = read_u32(data + 12);
    if (size < file_size)
        return make_error(ErrorCode::truncated, function, file,
                          std::to_string(size) + " bytes, header says " + std::to_string(file_size));
    if (size > file_size)
        return make_error(ErrorCode::size_mismatch, function, file,
                          std::to_string(size) + " bytes, header says " + std::to_string(file_size));
    if (file_size < header_size)
        return make_error(ErrorCode::invalid_header, function, file,
                          "file_size " + std::to_string(file_size) + " is smaller than the header");
    return {};
}

}  // namespace

size_t texture_layer_size(PixelFormat format, uint32_t width, uint32_t height) {
    return size_t(layer_bytes_wide(uint32_t(format), width, height));
}

size_t TextureArray::layer_size() const { return texture_layer_size(format, width, height); }

UvBlockTexel unpack_uvblock_texel(const uint8_t* block, uint32_t i) {
    UvBlockTexel t;
    const uint32_t state = (read_u32(block) >> (2 * i)) & 3u;
    if (state == 0) return t;
    const uint64_t headers = uint64_t(read_u32(block + 4)) | uint64_t(read_u32(block + 8)) << 32;
    const uint32_t header = uint32_t(headers >> (21 * (state - 1))) & 0x1FFFFFu;
    // The 96-bit offset stream: 6 bits of texel i at bit 6i, possibly across two words.
    const uint32_t bit = 6 * i, word = bit / 32, shift_in = bit % 32;
    uint64_t pair = read_u32(block + 12 + 4 * word);
    if (word < 2) pair |= uint64_t(read_u32(block + 16 + 4 * word)) << 32;
    const uint32_t field = uint32_t(pair >> shift_in) & 63u;
    const uint32_t shift = (header >> 18) & 7u;
    t.qu = 16 * (header & 255u) + ((field & 7u) << shift);
    t.qv = 16 * ((header >> 8) & 255u) + ((field >> 3) << shift);
    t.material = (header >> 16) & 3u;
    t.covered = true;
    return t;
}

uint32_t pack_uv32(float u, float v, uint32_t material, bool covered) {
    if (!covered) return 0;
    auto quantise = [](float x) { return uint32_t(std::lround(std::clamp(x, 0.0f, 1.0f) * float(kUv32CoordMax))); };
    return quantise(u) | quantise(v) << 14 | (material & 7u) << 28 | 1u << 31;
}

Status parse_pose_cache(const uint8_t* data, size_t size, const std::string& file, PoseCache* out) {
    static const char* fn = "parse_pose_cache";
    if (Status s = check_common_header(data, size, file, fn, "CBPC", kPoseCacheHeaderSize); !s) return s;

    const uint32_t vertex_count = read_u32(data + 16), index_count = read_u32(data + 20);
    const uint32_t frame_count = read_u32(data + 24), flags = read_u32(data + 28);
    const float fps = read_f32(data + 32);
    float bounds[6];
    for (int i = 0; i < 6; ++i) bounds[i] = read_f32(data + 36 + 4 * i);
    const uint32_t reserved = read_u32(data + 60);
    if (vertex_count == 0 || frame_count == 0 || index_count == 0 || index_count % 3)
        return make_error(ErrorCode::invalid_header, fn, file,
                          "vertex_count " + std::to_string(vertex_count) + ", index_count " + std::to_string(index_count) +
                              ", frame_count " + std::to_string(frame_count) +
                              ": all must be positive and index_count a multiple of 3");
    if (flags != 0 || reserved != 0)
        return make_error(ErrorCode::invalid_header, fn, file, "flags and reserved must be 0 in version 1");
    if (!(std::isfinite(fps) && fps > 0))
        return make_error(ErrorCode::invalid_header, fn, file, "frames_per_second " + std::to_string(fps) + " must be positive");
    const unsigned __int128 expected = kPoseCacheHeaderSize + (unsigned __int128)4 * index_count +
                                       (unsigned __int128)8 * vertex_count +
                                       (unsigned __int128)24 * vertex_count * frame_count;
    if (expected != size)
        return make_error(ErrorCode::size_mismatch, fn, file,
                          "counts imply " + std::to_string(uint64_t(expected)) + " bytes, file has " + std::to_string(size));

    // Sizes agree, so every section below lies inside the buffer.
    PoseCache cache;
    cache.vertex_count = vertex_count;
    cache.index_count = index_count;
    cache.frame_count = frame_count;
    cache.frames_per_second = fps;
    std::memcpy(cache.bounds_min, bounds, 12);
    std::memcpy(cache.bounds_max, bounds + 3, 12);
    const size_t value_count = size_t(frame_count) * vertex_count * 3;
    const uint8_t* p = data + kPoseCacheHeaderSize;
    cache.indices.resize(index_count);
    std::memcpy(cache.indices.data(), p, 4 * size_t(index_count));
    p += 4 * size_t(index_count);
    cache.uvs.resize(size_t(vertex_count) * 2);
    std::memcpy(cache.uvs.data(), p, 8 * size_t(vertex_count));
    p += 8 * size_t(vertex_count);
    cache.positions.resize(value_count);
    std::memcpy(cache.positions.data(), p, 4 * value_count);
    p += 4 * value_count;
    cache.normals.resize(value_count);
    std::memcpy(cache.normals.data(), p, 4 * value_count);

    const uint32_t max_index = *std::max_element(cache.indices.begin(), cache.indices.end());
    if (max_index >= vertex_count)
        return make_error(ErrorCode::invalid_data, fn, file,
                          "index " + std::to_string(max_index) + " >= vertex_count " + std::to_string(vertex_count));
    auto all_finite = [](const std::vector<float>& v) {
        return std::all_of(v.begin(), v.end(), [](float x) { return std::isfinite(x); });
    };
    if (!all_finite(cache.uvs)) return make_error(ErrorCode::invalid_data, fn, file, "uvs contain NaN or infinity");
    if (!all_finite(cache.positions)) return make_error(ErrorCode::invalid_data, fn, file, "positions contain NaN or infinity");
    if (!all_finite(cache.normals)) return make_error(ErrorCode::invalid_data, fn, file, "normals contain NaN or infinity");
    if (!std::all_of(bounds, bounds + 6, [](float x) { return std::isfinite(x); }))
        return make_error(ErrorCode::invalid_data, fn, file, "bounds contain NaN or infinity");
    for (size_t i = 0; i < value_count; i += 3) {
        const double x = cache.normals[i], y = cache.normals[i + 1], z = cache.normals[i + 2];
        if (std::fabs(std::sqrt(x * x + y * y + z * z) - 1.0) > kNormalLengthTolerance)
            return make_error(ErrorCode::invalid_data, fn, file,
                              "normal " + std::to_string(i / 3) + " (frame-major) is not unit length");
        for (int axis = 0; axis < 3; ++axis) {
            const double v = cache.positions[i + axis];
            if (v < double(bounds[axis]) - kBoundsTolerance || v > double(bounds[3 + axis]) + kBoundsTolerance)
                return make_error(ErrorCode::invalid_data, fn, file,
                                  "position " + std::to_string(i / 3) + " (frame-major) lies outside the header's bounds");
        }
    }
    *out = std::move(cache);
    return {};
}

Status parse_texture_array(const uint8_t* data, size_t size, const std::string& file, TextureArray* out) {
    static const char* fn = "parse_texture_array";
    if (Status s = check_common_header(data, size, file, fn, "CBTX", kTextureHeaderSize); !s) return s;

    const uint32_t width = read_u32(data + 16), height = read_u32(data + 20);
    const uint32_t layer_count = read_u32(data + 24), format = read_u32(data + 28);
    if (format < 1 || format > 7)
        return make_error(ErrorCode::invalid_header, fn, file, "unknown pixel_format " + std::to_string(format));
    if (width == 0 || height == 0 || layer_count == 0)
        return make_error(ErrorCode::invalid_header, fn, file,
                          "width " + std::to_string(width) + ", height " + std::to_string(height) + ", layer_count " +
                              std::to_string(layer_count) + " must be positive");
    const unsigned __int128 layer = layer_bytes_wide(format, width, height);
    if (layer == 0)
        return make_error(ErrorCode::invalid_header, fn, file,
                          std::string(pixel_format_name(PixelFormat(format))) + " needs sizes that are multiples of 4, got " +
                              std::to_string(width) + "x" + std::to_string(height));
    const unsigned __int128 expected = kTextureHeaderSize + layer * layer_count;
    if (expected != size)
        return make_error(ErrorCode::size_mismatch, fn, file,
                          "sizes imply " + std::to_string(uint64_t(expected)) + " bytes, file has " + std::to_string(size));
    if (format == uint32_t(PixelFormat::uvblock)) {  // SPEC.md: every covered coordinate <= 4095
        const size_t blocks = size_t(layer / kUvBlockBytes) * layer_count;
        for (size_t b = 0; b < blocks; ++b)
            for (uint32_t i = 0; i < 16; ++i) {
                const UvBlockTexel t = unpack_uvblock_texel(data + kTextureHeaderSize + b * kUvBlockBytes, i);
                if (t.qu > kUvBlockCoordMax || t.qv > kUvBlockCoordMax)
                    return make_error(ErrorCode::invalid_data, fn, file,
                                      "uvblock block " + std::to_string(b) + " texel " + std::to_string(i) + ": a coordinate above 4095");
            }
    }
    TextureArray texture;
    texture.width = width;
    texture.height = height;
    texture.layer_count = layer_count;
    texture.format = PixelFormat(format);
    texture.data.assign(data + kTextureHeaderSize, data + size);
    *out = std::move(texture);
    return {};
}

// ---------------------------------------------------------------------------------------
// Block decoding (S3TC as in EXT_texture_compression_s3tc)

namespace {

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

// ---------------------------------------------------------------------------------------
// Manifest: manifest.schema.json written out as checks

namespace {

// Walks a JSON document and records the first schema violation with its location.
class SchemaCheck {
public:
    bool failed() const { return !error_.empty(); }
    const std::string& error() const { return error_; }

    void fail(const std::string& where, const std::string& what) {
        if (error_.empty()) error_ = "at " + where + ": " + what;
    }

    // JSON Schema "integer": any number with no fractional part (draft 2020-12).
    static bool is_integer(const json& v) {
        if (v.is_number_integer()) return true;
        return v.is_number_float() && std::isfinite(v.get<double>()) && std::floor(v.get<double>()) == v.get<double>();
    }

    const json* member(const json& object, const std::string& where, const char* key) {
        auto it = object.find(key);
        if (it == object.end()) {
            fail(where, std::string("'") + key + "' is a required property");
            return nullptr;
        }
        return &*it;
    }

    const json* object(const json& parent, const std::string& where, const char* key) {
        const json* v = member(parent, where, key);
        if (v && !v->is_object()) {
            fail(where + "/" + key, "is not of type 'object'");
            return nullptr;
        }
        return v;
    }

    const json* array(const json& parent, const std::string& where, const char* key, size_t min_items) {
        const json* v = member(parent, where, key);
        if (!v) return nullptr;
        if (!v->is_array()) {
            fail(where + "/" + key, "is not of type 'array'");
            return nullptr;
        }
        if (v->size() < min_items) {
            fail(where + "/" + key, "should be non-empty");
            return nullptr;
        }
        return v;
    }

    // Integer in [minimum, maximum]; stored as uint32 (larger values cannot describe a
    // real bundle and are refused here rather than wrapped).
    uint32_t integer(const json& parent, const std::string& where, const char* key, int64_t minimum,
                     int64_t maximum = UINT32_MAX) {
        const json* v = member(parent, where, key);
        return v ? integer_value(*v, where + "/" + key, minimum, maximum) : 0;
    }

    uint32_t integer_value(const json& v, const std::string& where, int64_t minimum, int64_t maximum = UINT32_MAX) {
        if (!is_integer(v)) {
            fail(where, "is not of type 'integer'");
            return 0;
        }
        const double d = v.get<double>();
        if (d < double(minimum) || d > double(maximum)) {
            fail(where, "is out of range [" + std::to_string(minimum) + ", " + std::to_string(maximum) + "]");
            return 0;
        }
        return uint32_t(d);
    }

    // A file size: an exact integer in [0, kMaxFileSize]. Read exactly, never through a cast that
    // could overflow: 2^64 - 1 as a double is 2^64, and converting that to uint64_t is undefined
    // (it read as 0, and the file then had to be empty).
    uint64_t size_value(const json& v, const std::string& where) {
        const std::string range = "is out of range [0, " + std::to_string(kMaxFileSize) + "]";
        if (v.is_number_unsigned()) {
            const uint64_t n = v.get<uint64_t>();
            if (n > kMaxFileSize) fail(where, range);
            return n <= kMaxFileSize ? n : 0;
        }
        if (v.is_number_integer()) {  // signed, so negative here
            fail(where, range);
            return 0;
        }
        if (!is_integer(v)) {
            fail(where, "is not of type 'integer'");
            return 0;
        }
        const double d = v.get<double>();  // integral and finite; compared before any conversion
        if (d < 0 || d > double(kMaxFileSize)) {
            fail(where, range);
            return 0;
        }
        return uint64_t(d);
    }

    // Number with optional bounds; `exclusive_min` makes the minimum exclusive.
    double number(const json& parent, const std::string& where, const char* key, double minimum = -INFINITY,
                  bool exclusive_min = false) {
        const json* v = member(parent, where, key);
        return v ? number_value(*v, where + "/" + key, minimum, exclusive_min) : 0;
    }

    double number_value(const json& v, const std::string& where, double minimum = -INFINITY, bool exclusive_min = false,
                        double maximum = INFINITY, bool exclusive_max = false) {
        if (!v.is_number()) {
            fail(where, "is not of type 'number'");
            return 0;
        }
        const double d = v.get<double>();
        if ((exclusive_min ? d <= minimum : d < minimum) || (exclusive_max ? d >= maximum : d > maximum))
            fail(where, "is out of range");
        return d;
    }

    std::string string(const json& parent, const std::string& where, const char* key, const char* pattern = nullptr,
                       size_t min_length = 0, size_t max_length = SIZE_MAX) {
        const json* v = member(parent, where, key);
        return v ? string_value(*v, where + "/" + key, pattern, min_length, max_length) : std::string();
    }

    std::string string_value(const json& v, const std::string& where, const char* pattern = nullptr,
                             size_t min_length = 0, size_t max_length = SIZE_MAX) {
        if (!v.is_string()) {
            fail(where, "is not of type 'string'");
            return {};
        }
        const std::string s = v.get<std::string>();
        // JSON Schema lengths count code points, not bytes.
        const size_t length = size_t(std::count_if(s.begin(), s.end(), [](char c) { return (c & 0xC0) != 0x80; }));
        if (length < min_length || length > max_length) fail(where, "has the wrong length");
        if (pattern && !std::regex_search(s, std::regex(pattern))) fail(where, "does not match '" + std::string(pattern) + "'");
        return s;
    }

    std::string enumerated(const json& parent, const std::string& where, const char* key,
                           std::initializer_list<const char*> values) {
        const json* v = member(parent, where, key);
        if (!v) return {};
        for (const char* value : values)
            if (v->is_string() && v->get<std::string>() == value) return value;
        fail(where + "/" + key, "is not one of the allowed values");
        return {};
    }

    // manifest.schema.json's $defs/path.
    std::string path(const json& parent, const std::string& where, const char* key) {
        std::string p = string(parent, where, key, "^[A-Za-z0-9._-]+(/[A-Za-z0-9._-]+)*$", 0, 200);
        if (p == "manifest.json") fail(where + "/" + key, "must not be 'manifest.json'");
        return p;
    }

private:
    std::string error_;
};

}  // namespace

Status parse_manifest(const std::string& text, Manifest* out) {
    static const char* fn = "parse_manifest";
    const std::string file = "manifest.json";
    json doc = json::parse(text, nullptr, /*allow_exceptions=*/false);
    if (doc.is_discarded()) return make_error(ErrorCode::manifest_invalid, fn, file, "not JSON (or not UTF-8)");
    if (!doc.is_object()) return make_error(ErrorCode::manifest_invalid, fn, file, "the manifest is not a JSON object");
    // A newer format is named as such even when the rest would not validate against v1.
    if (auto it = doc.find("format_version");
        it != doc.end() && SchemaCheck::is_integer(*it) && it->get<double>() > kFormatVersion)
        return make_error(ErrorCode::unsupported_format_version, fn, file,
                          "format_version " + it->dump() + ", this reader supports " + std::to_string(kFormatVersion));

    SchemaCheck check;
    Manifest m;
    const std::string top = "(top level)";
    for (const char* key : {"format", "format_version", "name", "version", "created", "producer", "frames_per_second",
                            "cycle", "materials", "outfits", "meshes", "impostor", "files"})
        check.member(doc, top, key);
    if (const json* format = check.member(doc, top, "format"); format && *format != "crowdbake-bundle")
        check.fail("format", "must be 'crowdbake-bundle'");
    m.format_version = check.integer(doc, "", "format_version", 1);
    m.name = check.string(doc, "", "name", "^[a-z0-9][a-z0-9._-]{0,63}$");
    m.version = check.string(doc, "", "version", "^[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}$");
    m.created = check.string(doc, "", "created", "^[0-9]{4}-[0-9]{2}-[0-9]{2}T[0-9]{2}:[0-9]{2}:[0-9]{2}(\\.[0-9]+)?Z$");
    m.producer = check.string(doc, "", "producer", nullptr, 1, 200);
    m.frames_per_second = check.number(doc, "", "frames_per_second", 0, true);

    if (const json* cycle = check.object(doc, "", "cycle")) {
        m.cycle.source_start_frame = check.integer(*cycle, "cycle", "source_start_frame", 0);
        m.cycle.source_end_frame = check.integer(*cycle, "cycle", "source_end_frame", 1);
        m.cycle.frames = check.integer(*cycle, "cycle", "frames", 1);
        m.cycle.closing = check.enumerated(*cycle, "cycle", "closing", {"none", "linear", "hermite", "crossfade"});
        m.cycle.position_jump_ratio = check.number(*cycle, "cycle", "position_jump_ratio", 0);
        m.cycle.velocity_jump_ratio = check.number(*cycle, "cycle", "velocity_jump_ratio", 0);
    }
    if (const json* materials = check.array(doc, "", "materials", 1))
        for (size_t i = 0; i < materials->size() && !check.failed(); ++i) {
            const json& item = (*materials)[i];
            const std::string where = "materials/" + std::to_string(i);
            if (!item.is_object()) {
                check.fail(where, "is not of type 'object'");
                break;
            }
            MaterialInfo material;
            material.name = check.string(item, where, "name", nullptr, 1, 64);
            material.diffuse = check.path(item, where, "diffuse");
            material.variations = check.integer(item, where, "variations", 1);
            m.materials.push_back(material);
        }
    if (const json* outfits = check.object(doc, "", "outfits")) {
        m.outfits_file = check.path(*outfits, "outfits", "file");
        m.outfit_count = check.integer(*outfits, "outfits", "count", 1);
        check.integer(*outfits, "outfits", "regions", 16, 16);
    }
    if (const json* meshes = check.array(doc, "", "meshes", 1))
        for (size_t i = 0; i < meshes->size() && !check.failed(); ++i) {
            const json& item = (*meshes)[i];
            const std::string where = "meshes/" + std::to_string(i);
            if (!item.is_object()) {
                check.fail(where, "is not of type 'object'");
                break;
            }
            MeshInfo mesh;
            mesh.part = check.string(item, where, "part", "^[a-z0-9_-]{1,32}$");
            mesh.kind = check.enumerated(item, where, "kind", {"body", "garment"});
            mesh.lod = check.integer(item, where, "lod", 0, 7);
            mesh.file = check.path(item, where, "file");
            mesh.material = check.integer(item, where, "material", 0);
            mesh.vertex_count = check.integer(item, where, "vertex_count", 1);
            mesh.triangle_count = check.integer(item, where, "triangle_count", 1);
            m.meshes.push_back(mesh);
        }
    if (const json* impostor = check.object(doc, "", "impostor")) {
        ImpostorInfo& info = m.impostor;
        info.tile_size = check.integer(*impostor, "impostor", "tile_size", 4, 4096);
        if (info.tile_size % 4) check.fail("impostor/tile_size", "is not a multiple of 4");
        info.crop = {0, 0, info.tile_size, info.tile_size};
        if (impostor->contains("crop"))
            if (const json* crop = check.object(*impostor, "impostor", "crop")) {
                info.crop.x = check.integer(*crop, "impostor/crop", "x", 0, 4092);
                info.crop.y = check.integer(*crop, "impostor/crop", "y", 0, 4092);
                info.crop.width = check.integer(*crop, "impostor/crop", "width", 4, 4096);
                info.crop.height = check.integer(*crop, "impostor/crop", "height", 4, 4096);
                if ((info.crop.x | info.crop.y | info.crop.width | info.crop.height) % 4)
                    check.fail("impostor/crop", "must lie on 4-texel blocks (x, y, width and height multiples of 4)");
            }
        if (const json* az = check.array(*impostor, "impostor", "azimuths_deg", 1))
            for (size_t i = 0; i < az->size(); ++i)
                info.azimuths_deg.push_back(float(check.number_value((*az)[i], "impostor/azimuths_deg/" + std::to_string(i), 0,
                                                                     false, 360, true)));
        if (const json* el = check.array(*impostor, "impostor", "elevations_deg", 1))
            for (size_t i = 0; i < el->size(); ++i)
                info.elevations_deg.push_back(
                    float(check.number_value((*el)[i], "impostor/elevations_deg/" + std::to_string(i), -90, false, 90, false)));
        if (const json* frames = check.array(*impostor, "impostor", "frame_indices", 1))
            for (size_t i = 0; i < frames->size(); ++i)
                info.frame_indices.push_back(check.integer_value((*frames)[i], "impostor/frame_indices/" + std::to_string(i), 0));
        if (const json* bounds = check.object(*impostor, "impostor", "bounds")) {
            if (const json* center = check.member(*bounds, "impostor/bounds", "center")) {
                if (!center->is_array() || center->size() != 3)
                    check.fail("impostor/bounds/center", "must be an array of 3 numbers");
                else
                    for (int i = 0; i < 3; ++i)
                        info.center[i] = float(check.number_value((*center)[i], "impostor/bounds/center/" + std::to_string(i)));
            }
            info.radius = float(check.number(*bounds, "impostor/bounds", "radius", 0, true));
        }
        if (const json* maps = check.object(*impostor, "impostor", "maps")) {
            info.normal_map = check.path(*maps, "impostor/maps", "normal");
            info.uv_map = check.path(*maps, "impostor/maps", "uv");
            if (maps->contains("detail")) info.detail_map = check.path(*maps, "impostor/maps", "detail");
            if (maps->contains("surface")) info.surface_map = check.path(*maps, "impostor/maps", "surface");
        }
    }
    if (const json* files = check.array(doc, "", "files", 1))
        for (size_t i = 0; i < files->size() && !check.failed(); ++i) {
            const json& item = (*files)[i];
            const std::string where = "files/" + std::to_string(i);
            if (!item.is_object()) {
                check.fail(where, "is not of type 'object'");
                break;
            }
            FileEntry entry;
            entry.path = check.string(item, where, "path", nullptr, 1);
            if (const json* size = check.member(item, where, "size")) entry.size = check.size_value(*size, where + "/size");
            entry.sha256 = check.string(item, where, "sha256", "^[0-9a-f]{64}$");
            entry.media_type = check.string(item, where, "media_type", nullptr, 1);
            entry.role = check.enumerated(item, where, "role",
                                          {"pose-cache", "diffuse", "outfit-colours", "impostor-normal", "impostor-uv",
                                           "impostor-detail", "impostor-surface", "cycle", "fidelity", "texture-memory", "report", "preview"});
            m.files.push_back(entry);
        }
    if (check.failed()) return make_error(ErrorCode::manifest_invalid, fn, file, check.error());
    *out = std::move(m);
    return {};
}

bool is_safe_path(const std::string& path) {
    if (path.empty() || path.size() > 200 || path == "manifest.json") return false;
    size_t start = 0;
    while (true) {
        const size_t end = std::min(path.find('/', start), path.size());
        const std::string part = path.substr(start, end - start);
        if (part.empty() || part == "." || part == "..") return false;
        for (char c : part)
            if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '.' || c == '_' || c == '-'))
                return false;
        if (end == path.size()) return true;
        start = end + 1;
    }
}

// ---------------------------------------------------------------------------------------
// Whole bundles

std::string sha256_hex(const uint8_t* data, size_t size) {
    unsigned char digest[EVP_MAX_MD_SIZE];
    unsigned int length = 0;
    EVP_Digest(data, size, digest, &length, EVP_sha256(), nullptr);
    static const char* hex = "0123456789abcdef";
    std::string out;
    for (unsigned int i = 0; i < length; ++i) {
        out += hex[digest[i] >> 4];
        out += hex[digest[i] & 15];
    }
    return out;
}

bool read_file_bytes(const std::string& path, std::vector<uint8_t>* bytes) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return false;
    in.seekg(0, std::ios::end);
    const std::streamoff size = in.tellg();
    if (size < 0) return false;
    in.seekg(0);
    bytes->resize(size_t(size));
    return size == 0 || bool(in.read(reinterpret_cast<char*>(bytes->data()), size));
}

namespace {

const char* kTextureMediaType = "application/vnd.crowdbake.texture";

// SPEC.md's cross-checks, in the order the Python reader runs them, so both name the same file.
Status cross_check(const Manifest& m, const std::map<std::string, PoseCache>& poses,
                   const std::map<std::string, TextureArray>& textures, Bundle* bundle) {
    static const char* fn = "load_bundle";
    auto bad = [](const std::string& file, const std::string& detail) {
        return make_error(ErrorCode::invalid_data, fn, file, detail);
    };
    for (const MeshInfo& mesh : m.meshes) {
        auto it = poses.find(mesh.file);
        if (it == poses.end()) return bad(mesh.file, "mesh file is not listed as a pose-cache");
        const PoseCache& cache = it->second;
        if (cache.vertex_count != mesh.vertex_count)
            return bad(mesh.file, std::to_string(cache.vertex_count) + " vertices, manifest says " + std::to_string(mesh.vertex_count));
        if (cache.index_count / 3 != mesh.triangle_count)
            return bad(mesh.file, std::to_string(cache.index_count / 3) + " triangles, manifest says " +
                                      std::to_string(mesh.triangle_count));
        if (cache.frame_count != m.cycle.frames)
            return bad(mesh.file, std::to_string(cache.frame_count) + " frames, cycle has " + std::to_string(m.cycle.frames));
        if (mesh.material >= m.materials.size())
            return bad(mesh.file, "material " + std::to_string(mesh.material) + " does not exist");
        bundle->meshes.push_back(cache);
    }
    auto texture = [&](const std::string& path, const TextureArray** out) {
        auto it = textures.find(path);
        if (it == textures.end()) return bad(path, "referenced but not listed as a texture");
        *out = &it->second;
        return Status{};
    };
    for (const MaterialInfo& material : m.materials) {
        const TextureArray* diffuse = nullptr;
        if (Status s = texture(material.diffuse, &diffuse); !s) return s;
        if (diffuse->layer_count != material.variations)
            return bad(material.diffuse, std::to_string(diffuse->layer_count) + " layers, manifest says " +
                                             std::to_string(material.variations) + " variations");
        bundle->diffuse.push_back(*diffuse);
    }
    const TextureArray* outfits = nullptr;
    if (Status s = texture(m.outfits_file, &outfits); !s) return s;
    if (outfits->width != 16 || outfits->height != m.outfit_count || outfits->format != PixelFormat::rgba8)
        return bad(m.outfits_file, "outfit map must be rgba8 16x" + std::to_string(m.outfit_count));
    bundle->outfits = *outfits;

    const ImpostorInfo& imp = m.impostor;
    for (size_t k = 0; k < imp.frame_indices.size(); ++k) {
        if (imp.frame_indices[k] >= m.cycle.frames) return bad("manifest.json", "frame_indices outside the cycle");
        if (k > 0 && imp.frame_indices[k] <= imp.frame_indices[k - 1]) return bad("manifest.json", "frame_indices must ascend");
    }
    if (uint64_t(imp.crop.x) + imp.crop.width > imp.tile_size || uint64_t(imp.crop.y) + imp.crop.height > imp.tile_size)
        return bad("manifest.json", "impostor/crop reaches outside the " + std::to_string(imp.tile_size) + "-texel tile");
    const uint64_t width = uint64_t(imp.crop.width) * imp.azimuths_deg.size();
    const uint64_t height = uint64_t(imp.crop.height) * imp.elevations_deg.size();
    // Sorted by kind, as the canonical manifest (sorted keys) lists them.
    const std::pair<const char*, std::pair<const std::string*, TextureArray*>> maps[] = {
        {"detail", {&imp.detail_map, &bundle->impostor_detail}},
        {"normal", {&imp.normal_map, &bundle->impostor_normal}},
        {"surface", {&imp.surface_map, &bundle->impostor_surface}},
        {"uv", {&imp.uv_map, &bundle->impostor_uv}},
    };
    for (const auto& [kind, target] : maps) {
        if (target.first->empty()) continue;  // an optional map (detail, surface), absent
        const TextureArray* atlas = nullptr;
        if (Status s = texture(*target.first, &atlas); !s) return s;
        if (atlas->width != width || atlas->height != height || atlas->layer_count != imp.frame_indices.size())
            return bad(*target.first, std::string(kind) + " atlas is " + std::to_string(atlas->width) + "x" +
                                          std::to_string(atlas->height) + "x" + std::to_string(atlas->layer_count) +
                                          ", layout needs " + std::to_string(width) + "x" + std::to_string(height) + "x" +
                                          std::to_string(imp.frame_indices.size()));
        *target.second = *atlas;
    }
    if (bundle->impostor_uv.format != PixelFormat::rgba16 && bundle->impostor_uv.format != PixelFormat::uv32 &&
        bundle->impostor_uv.format != PixelFormat::uvblock)
        return bad(imp.uv_map, "the UV map must be rgba16, uv32 or uvblock (8 bits cannot address a 1024-texel texture)");
    if (!imp.surface_map.empty() && bundle->impostor_surface.format != PixelFormat::bc1 &&
        bundle->impostor_surface.format != PixelFormat::rgba8)
        return bad(imp.surface_map, "the surface map must be bc1 or rgba8");
    return {};
}

}  // namespace

Status load_bundle(const std::string& manifest_text, const FileSource& source, Bundle* out) {
    static const char* fn = "load_bundle";
    Manifest manifest;
    if (Status s = parse_manifest(manifest_text, &manifest); !s) return s;

    // Step 2: every file entry, in order.
    std::map<std::string, std::vector<uint8_t>> contents;
    for (const FileEntry& entry : manifest.files) {
        if (printable(entry.path) != entry.path)
            return make_error(ErrorCode::unsafe_path, fn, entry.path,
                              "path holds control characters (written here as \\xNN or \\u00NN), which the bundle path "
                              "rule forbids ([A-Za-z0-9._-] components)");
        if (!is_safe_path(entry.path))
            return make_error(ErrorCode::unsafe_path, fn, entry.path,
                              "path breaks the bundle path rule (relative, no '..', [A-Za-z0-9._-])");
        if (contents.count(entry.path)) return make_error(ErrorCode::manifest_invalid, fn, entry.path, "path listed twice");
        std::vector<uint8_t> bytes;
        if (Status s = source(entry, &bytes); !s) return s;
        if (bytes.size() != entry.size)
            return make_error(ErrorCode::size_mismatch, fn, entry.path,
                              std::to_string(bytes.size()) + " bytes, manifest says " + std::to_string(entry.size));
        if (sha256_hex(bytes.data(), bytes.size()) != entry.sha256)
            return make_error(ErrorCode::sha256_mismatch, fn, entry.path, "bytes differ from the manifest's sha256");
        contents[entry.path] = std::move(bytes);
    }

    // Step 3: parse the binaries (in listing order), then the cross-checks.
    std::map<std::string, PoseCache> poses;
    std::map<std::string, TextureArray> textures;
    for (const FileEntry& entry : manifest.files) {
        const std::vector<uint8_t>& bytes = contents[entry.path];
        if (entry.role == "pose-cache") {
            if (Status s = parse_pose_cache(bytes.data(), bytes.size(), entry.path, &poses[entry.path]); !s) return s;
        } else if (entry.media_type == kTextureMediaType) {
            if (Status s = parse_texture_array(bytes.data(), bytes.size(), entry.path, &textures[entry.path]); !s) return s;
        }
    }
    Bundle bundle;
    if (Status s = cross_check(manifest, poses, textures, &bundle); !s) return s;
    bundle.manifest = std::move(manifest);
    *out = std::move(bundle);
    return {};
}

Status load_bundle_dir(const std::string& dir, Bundle* out) {
    std::vector<uint8_t> manifest_bytes;
    if (!read_file_bytes(dir + "/manifest.json", &manifest_bytes))
        return make_error(ErrorCode::manifest_invalid, "load_bundle_dir", "manifest.json", "no manifest.json in " + dir);
    const FileSource source = [&dir](const FileEntry& entry, std::vector<uint8_t>* bytes) {
        const std::string full = dir + "/" + entry.path;
        struct stat info;
        if (stat(full.c_str(), &info) != 0 || !S_ISREG(info.st_mode))
            return make_error(ErrorCode::missing_file, "load_bundle_dir", entry.path, "listed in the manifest but absent");
        // Refuse a wrong size before reading, so a huge stray file is never loaded whole.
        if (uint64_t(info.st_size) != entry.size)
            return make_error(ErrorCode::size_mismatch, "load_bundle_dir", entry.path,
                              std::to_string(info.st_size) + " bytes, manifest says " + std::to_string(entry.size));
        if (!read_file_bytes(full, bytes))
            return make_error(ErrorCode::missing_file, "load_bundle_dir", entry.path, "cannot be read");
        return Status{};
    };
    return load_bundle(std::string(manifest_bytes.begin(), manifest_bytes.end()), source, out);
}

}  // namespace crowdview
