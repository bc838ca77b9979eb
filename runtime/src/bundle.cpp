// Bundle reader: SPEC.md's binary files, manifest and verification, in the spec's order.
#include "bundle.h"
#include "pose_codec.h"

#include <nlohmann/json.hpp>
#include <openssl/evp.h>
#include <sys/stat.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>

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

}  // namespace

// The common header, in SPEC.md's order: length, magic, version, header_size, file_size.
Status check_common_header(const uint8_t* data, size_t size, const std::string& file, const char* function,
                           const char* magic, uint32_t header_size, uint32_t max_version) {
    if (size < 16)
        return make_error(ErrorCode::truncated, function, file,
                          std::to_string(size) + " bytes is shorter than the 16-byte common header");
    if (std::memcmp(data, magic, 4) != 0) {
        std::string got;
        for (int i = 0; i < 4; ++i) got += (data[i] >= 32 && data[i] < 127) ? char(data[i]) : '?';
        return make_error(ErrorCode::bad_magic, function, file, "magic is '" + got + "', expected '" + magic + "'");
    }
    const uint32_t version = read_u32(data + 4);
    if (version == 0 || version > max_version)
        return make_error(ErrorCode::unsupported_version, function, file,
                          "version " + std::to_string(version) + ", this reader supports 1 to " + std::to_string(max_version));
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
    if (Status s = check_common_header(data, size, file, fn, "CBPC", kPoseCacheHeaderSize, kQuantizedPoseCacheVersion); !s) return s;

    const uint32_t version = read_u32(data + 4);
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
    if (flags != 0 || reserved != 0) return make_error(ErrorCode::invalid_header, fn, file, "flags and reserved must be 0");
    if (!(std::isfinite(fps) && fps > 0))
        return make_error(ErrorCode::invalid_header, fn, file, "frames_per_second " + std::to_string(fps) + " must be positive");
    // Counts below 2^32 keep this under 2^64.
    const uint64_t expected = pose_cache_file_size(version, index_count, vertex_count, frame_count);
    if (expected != size)
        return make_error(ErrorCode::size_mismatch, fn, file,
                          "counts imply " + std::to_string(expected) + " bytes, file has " + std::to_string(size));

    // Sizes agree, so every section below lies inside the buffer.
    PoseCache cache;
    cache.version = version;
    cache.vertex_count = vertex_count;
    cache.index_count = index_count;
    cache.frame_count = frame_count;
    cache.frames_per_second = fps;
    std::memcpy(cache.bounds_min, bounds, 12);
    std::memcpy(cache.bounds_max, bounds + 3, 12);
    const uint8_t* p = data + kPoseCacheHeaderSize;
    cache.indices.resize(index_count);
    std::memcpy(cache.indices.data(), p, 4 * size_t(index_count));
    p += 4 * size_t(index_count);
    cache.uvs.resize(size_t(vertex_count) * 2);
    std::memcpy(cache.uvs.data(), p, 8 * size_t(vertex_count));
    p += 8 * size_t(vertex_count);

    const uint32_t max_index = *std::max_element(cache.indices.begin(), cache.indices.end());
    if (max_index >= vertex_count)
        return make_error(ErrorCode::invalid_data, fn, file,
                          "index " + std::to_string(max_index) + " >= vertex_count " + std::to_string(vertex_count));
    auto finite = [](float x) { return std::isfinite(x); };
    if (!std::all_of(cache.uvs.begin(), cache.uvs.end(), finite))
        return make_error(ErrorCode::invalid_data, fn, file, "uvs contain NaN or infinity");
    if (!std::all_of(bounds, bounds + 6, finite)) return make_error(ErrorCode::invalid_data, fn, file, "bounds contain NaN or infinity");
    if (Status s = read_pose_frames(version, p, bounds, file, fn, &cache); !s) return s;
    *out = std::move(cache);
    return {};
}

Status parse_mesh_pose_file(const uint8_t* data, size_t size, const std::string& file, PoseCache* out) {
    // A prefix shorter than the magic goes to the CBPC parser, which calls it truncated as the CBSK one would.
    if (size >= 4 && std::memcmp(data, "CBSK", 4) == 0) return parse_skinned_pose_cache(data, size, file, out);
    return parse_pose_cache(data, size, file, out);
}

Status parse_texture_array(const uint8_t* data, size_t size, const std::string& file, TextureArray* out) {
    static const char* fn = "parse_texture_array";
    if (Status s = check_common_header(data, size, file, fn, "CBTX", kTextureHeaderSize, 1); !s) return s;

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

Status invalid(const std::string& file, const std::string& detail) {
    return make_error(ErrorCode::invalid_data, "load_bundle", file, detail);
}

// The texture listed at `path`, or invalid_data naming it.
Status find_texture(const std::map<std::string, TextureArray>& textures, const std::string& path, const TextureArray** out) {
    auto it = textures.find(path);
    if (it == textures.end()) return invalid(path, "referenced but not listed as a texture");
    *out = &it->second;
    return {};
}

// SPEC.md "Version 3" and "Version 4": a CBSK only as a body of a format_version 4 bundle; every CBPC of
// a format_version 3 or 4 bundle quantized, of an older one float.
Status check_pose_cache_kind(const Manifest& m, const MeshInfo& mesh, const PoseCache& cache) {
    const std::string bundle_version = "a format_version " + std::to_string(m.format_version) + " bundle";
    if (cache.skinned()) {
        if (m.format_version < kSkinnedFormatVersion)
            return invalid(mesh.file, "a skinned pose cache (CBSK) in " + bundle_version + ", which holds CBPC only");
        if (mesh.kind != "body") return invalid(mesh.file, "a skinned pose cache (CBSK) as a " + mesh.kind + "; only bodies are skinned");
        return {};
    }
    const uint32_t cache_version = m.format_version >= 3 ? kQuantizedPoseCacheVersion : 1;
    if (cache.version != cache_version)
        return invalid(mesh.file, "pose cache version " + std::to_string(cache.version) + ", " + bundle_version + " holds version " +
                                      std::to_string(cache_version));
    return {};
}

// Each mesh's pose cache against the manifest's counts and materials; into bundle->meshes.
Status check_meshes(const Manifest& m, const std::map<std::string, PoseCache>& poses, Bundle* bundle) {
    for (const MeshInfo& mesh : m.meshes) {
        auto it = poses.find(mesh.file);
        if (it == poses.end()) return invalid(mesh.file, "mesh file is not listed as a pose-cache");
        const PoseCache& cache = it->second;
        if (cache.vertex_count != mesh.vertex_count)
            return invalid(mesh.file, std::to_string(cache.vertex_count) + " vertices, manifest says " + std::to_string(mesh.vertex_count));
        if (cache.index_count / 3 != mesh.triangle_count)
            return invalid(mesh.file, std::to_string(cache.index_count / 3) + " triangles, manifest says " +
                                          std::to_string(mesh.triangle_count));
        if (cache.frame_count != m.pose_frames)
            return invalid(mesh.file, std::to_string(cache.frame_count) + " frames, the manifest has " + std::to_string(m.pose_frames) +
                                          " pose frames");
        if (Status s = check_pose_cache_kind(m, mesh, cache); !s) return s;
        if (cache.frames_per_second != float(m.frames_per_second))
            return invalid(mesh.file, "frames_per_second " + std::to_string(cache.frames_per_second) + ", the manifest says " +
                                          std::to_string(m.frames_per_second));
        if (mesh.material >= m.materials.size())
            return invalid(mesh.file, "material " + std::to_string(mesh.material) + " does not exist");
        bundle->meshes.push_back(cache);
    }
    return {};
}

// Each material's diffuse array (one layer per variation) and the outfit map; into the bundle.
Status check_materials_and_outfits(const Manifest& m, const std::map<std::string, TextureArray>& textures, Bundle* bundle) {
    for (const MaterialInfo& material : m.materials) {
        const TextureArray* diffuse = nullptr;
        if (Status s = find_texture(textures, material.diffuse, &diffuse); !s) return s;
        if (diffuse->layer_count != material.variations)
            return invalid(material.diffuse, std::to_string(diffuse->layer_count) + " layers, manifest says " +
                                                 std::to_string(material.variations) + " variations");
        bundle->diffuse.push_back(*diffuse);
    }
    const TextureArray* outfits = nullptr;
    if (Status s = find_texture(textures, m.outfits_file, &outfits); !s) return s;
    if (outfits->width != 16 || outfits->height != m.outfit_count || outfits->format != PixelFormat::rgba8)
        return invalid(m.outfits_file, "outfit map must be rgba8 16x" + std::to_string(m.outfit_count));
    bundle->outfits = *outfits;
    return {};
}

// The baked frames ascend within the pose frames, and every range can be drawn as an impostor: a
// clip needs one baked frame, a transition (played once, not wrapped) its own first and last frame,
// so its ends are exact.
Status check_baked_frames(const Manifest& m) {
    const std::vector<uint32_t>& baked_frames = m.impostor.frame_indices;
    for (size_t k = 0; k < baked_frames.size(); ++k) {
        if (baked_frames[k] >= m.pose_frames) return invalid("manifest.json", "frame_indices outside the pose frames");
        if (k > 0 && baked_frames[k] <= baked_frames[k - 1]) return invalid("manifest.json", "frame_indices must ascend");
    }
    auto baked = [&](uint32_t frame) { return std::binary_search(baked_frames.begin(), baked_frames.end(), frame); };
    for (size_t i = 0; i < m.clips.size(); ++i) {
        const ClipInfo& c = m.clips[i];
        const auto first = std::lower_bound(baked_frames.begin(), baked_frames.end(), c.first_frame);
        if (first == baked_frames.end() || *first >= uint64_t(c.first_frame) + c.frames)
            return invalid("manifest.json", "clip " + std::to_string(i) + " ('" + c.name + "') has no baked impostor frame");
    }
    for (size_t i = 0; i < m.transitions.size(); ++i) {
        const TransitionInfo& t = m.transitions[i];
        if (!baked(t.first_frame) || !baked(t.first_frame + t.frames - 1))
            return invalid("manifest.json", "transition " + std::to_string(i) + " lacks a baked impostor frame at its first (" +
                                                std::to_string(t.first_frame) + ") or last (" + std::to_string(t.first_frame + t.frames - 1) +
                                                ") frame");
    }
    return {};
}

// The crop within the tile, each impostor atlas the layout's size with one layer per baked frame,
// and the UV and surface maps in formats that can hold them; into the bundle.
Status check_impostor_maps(const Manifest& m, const std::map<std::string, TextureArray>& textures, Bundle* bundle) {
    const ImpostorInfo& imp = m.impostor;
    if (uint64_t(imp.crop.x) + imp.crop.width > imp.tile_size || uint64_t(imp.crop.y) + imp.crop.height > imp.tile_size)
        return invalid("manifest.json", "impostor/crop reaches outside the " + std::to_string(imp.tile_size) + "-texel tile");
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
        if (Status s = find_texture(textures, *target.first, &atlas); !s) return s;
        if (atlas->width != width || atlas->height != height || atlas->layer_count != imp.frame_indices.size())
            return invalid(*target.first, std::string(kind) + " atlas is " + std::to_string(atlas->width) + "x" +
                                              std::to_string(atlas->height) + "x" + std::to_string(atlas->layer_count) +
                                              ", layout needs " + std::to_string(width) + "x" + std::to_string(height) + "x" +
                                              std::to_string(imp.frame_indices.size()));
        *target.second = *atlas;
    }
    if (bundle->impostor_uv.format != PixelFormat::rgba16 && bundle->impostor_uv.format != PixelFormat::uv32 &&
        bundle->impostor_uv.format != PixelFormat::uvblock)
        return invalid(imp.uv_map, "the UV map must be rgba16, uv32 or uvblock (8 bits cannot address a 1024-texel texture)");
    if (!imp.surface_map.empty() && bundle->impostor_surface.format != PixelFormat::bc1 &&
        bundle->impostor_surface.format != PixelFormat::bc2 && bundle->impostor_surface.format != PixelFormat::rgba8)
        return invalid(imp.surface_map, "the surface map must be bc1, bc2 or rgba8");
    return {};
}

// SPEC.md's cross-checks, in the order the Python reader runs them, so both name the same file.
Status cross_check(const Manifest& m, const std::map<std::string, PoseCache>& poses,
                   const std::map<std::string, TextureArray>& textures, Bundle* bundle) {
    if (Status s = check_meshes(m, poses, bundle); !s) return s;
    if (Status s = check_materials_and_outfits(m, textures, bundle); !s) return s;
    if (Status s = check_baked_frames(m); !s) return s;
    return check_impostor_maps(m, textures, bundle);
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
            if (Status s = parse_mesh_pose_file(bytes.data(), bytes.size(), entry.path, &poses[entry.path]); !s) return s;
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
