// The bundle reader on small in-memory files whose answers are known by construction:
// every header rule of SPEC.md, every strict prefix, block decoding, the path rule, the
// manifest checks and whole-bundle verification order.
#include <array>
#include <cmath>
#include <cstring>
#include <map>

#include <nlohmann/json.hpp>

#include "bundle.h"
#include "check.h"
#include "crowd.h"
#include "pose_codec.h"
#include "synthetic_bundle.h"

using namespace crowdview;
using nlohmann::json;

namespace {

void put_u32(std::vector<uint8_t>& b, size_t at, uint32_t v) { std::memcpy(&b[at], &v, 4); }
void put_f32(std::vector<uint8_t>& b, size_t at, float v) { std::memcpy(&b[at], &v, 4); }

// A unit quad facing +Z, rising 0.25 m per frame: 4 vertices, 2 triangles, 2 frames.
std::vector<uint8_t> quad_pose_cache() {
    const std::vector<float> base = {-0.5f, 0, 0, 0.5f, 0, 0, 0.5f, 1, 0, -0.5f, 1, 0};
    std::vector<float> positions, normals;
    for (int f = 0; f < 2; ++f)
        for (int v = 0; v < 4; ++v) {
            positions.insert(positions.end(), {base[3 * v], base[3 * v + 1] + 0.25f * f, base[3 * v + 2]});
            normals.insert(normals.end(), {0, 0, 1});
        }
    return synthetic::encode_pose_cache({0, 1, 2, 0, 2, 3}, {0, 1, 1, 1, 1, 0, 0, 0}, positions, normals, 2, 24.0f);
}

// 2x2 rgba8, two layers with known bytes.
std::vector<uint8_t> small_texture(uint32_t format = 1, uint32_t w = 2, uint32_t h = 2) {
    std::vector<uint8_t> layers(texture_layer_size(PixelFormat(format), w, h) * 2);
    for (size_t i = 0; i < layers.size(); ++i) layers[i] = uint8_t(i * 7);
    return synthetic::encode_texture_array(w, h, 2, format, layers);
}

ErrorCode pose_code(const std::vector<uint8_t>& bytes) {
    PoseCache cache;
    return parse_pose_cache(bytes.data(), bytes.size(), "p.cbpc", &cache).code;
}

ErrorCode texture_code(const std::vector<uint8_t>& bytes) {
    TextureArray texture;
    return parse_texture_array(bytes.data(), bytes.size(), "t.cbtx", &texture).code;
}

void test_pose_cache() {
    const std::vector<uint8_t> good = quad_pose_cache();
    CHECK(good.size() == 64 + 4 * 6 + 8 * 4 + 24 * 4 * 2);
    PoseCache cache;
    const Status s = parse_pose_cache(good.data(), good.size(), "p.cbpc", &cache);
    CHECK_MSG(s.ok(), s.message);
    CHECK(cache.vertex_count == 4 && cache.index_count == 6 && cache.frame_count == 2);
    CHECK(cache.frames_per_second == 24.0f);
    CHECK(cache.indices == std::vector<uint32_t>({0, 1, 2, 0, 2, 3}));
    // A version-1 file's float frames come back quantized: within half a 16-bit step of the frame's extent.
    float position[3];
    decode_pose_position(cache, 1, 0, position);
    CHECK(cache.version == 1 && cache.position_codes.size() == 24 && cache.normal_codes.size() == 16);
    CHECK(std::fabs(position[1] - 0.25f) <= 1.25f / 65535.0f);  // frame 1, vertex 0, y
    CHECK(cache.bounds_min[1] == 0.0f && cache.bounds_max[1] == 1.25f);

    // Every strict prefix is `truncated`, never a crash or another code (meshoptimizer's habit).
    for (size_t n = 0; n < good.size(); ++n) {
        const std::vector<uint8_t> prefix(good.begin(), good.begin() + long(n));
        CHECK_MSG(pose_code(prefix) == ErrorCode::truncated, "prefix of " + std::to_string(n) + " bytes");
    }

    auto edited = [&](size_t at, uint32_t value) {
        std::vector<uint8_t> b = good;
        put_u32(b, at, value);
        return b;
    };
    auto edited_f = [&](size_t at, float value) {
        std::vector<uint8_t> b = good;
        put_f32(b, at, value);
        return b;
    };
    std::vector<uint8_t> magic = good;
    magic[0] = 'X';
    CHECK(pose_code(magic) == ErrorCode::bad_magic);
    CHECK(pose_code(small_texture()) == ErrorCode::bad_magic);  // a CBTX where a CBPC belongs
    CHECK(pose_code(edited(4, 3)) == ErrorCode::unsupported_version);
    CHECK(pose_code(edited(4, 0)) == ErrorCode::unsupported_version);
    CHECK(pose_code(edited(8, 60)) == ErrorCode::invalid_header);
    std::vector<uint8_t> longer = good;
    longer.push_back(0);
    CHECK(pose_code(longer) == ErrorCode::size_mismatch);
    CHECK(pose_code(edited(16, 0)) == ErrorCode::invalid_header);  // vertex_count 0
    CHECK(pose_code(edited(20, 4)) == ErrorCode::invalid_header);  // index_count not a multiple of 3
    CHECK(pose_code(edited(28, 1)) == ErrorCode::invalid_header);  // flags
    CHECK(pose_code(edited(60, 1)) == ErrorCode::invalid_header);  // reserved
    CHECK(pose_code(edited_f(32, 0.0f)) == ErrorCode::invalid_header);
    CHECK(pose_code(edited_f(32, NAN)) == ErrorCode::invalid_header);
    CHECK(pose_code(edited(16, 5)) == ErrorCode::size_mismatch);  // counts disagree with file_size
    // Hostile counts: the implied size overflows 64 bits, and nothing is allocated for it.
    std::vector<uint8_t> huge = edited(16, 0xFFFFFFFFu);
    put_u32(huge, 24, 0xFFFFFFFFu);
    CHECK(pose_code(huge) == ErrorCode::size_mismatch);
    // Header says 20 bytes, file is 20 bytes: smaller than the header itself.
    std::vector<uint8_t> tiny(good.begin(), good.begin() + 20);
    put_u32(tiny, 12, 20);
    CHECK(pose_code(tiny) == ErrorCode::invalid_header);

    // Payload values.
    CHECK(pose_code(edited(64 + 8, 4)) == ErrorCode::invalid_data);  // an index == vertex_count
    const size_t uvs = 64 + 24, positions = uvs + 32, normals = positions + 96;
    CHECK(pose_code(edited_f(uvs, NAN)) == ErrorCode::invalid_data);
    CHECK(pose_code(edited_f(positions + 4, INFINITY)) == ErrorCode::invalid_data);
    CHECK(pose_code(edited_f(normals + 8, 1.01f)) == ErrorCode::invalid_data);   // |n| = 1.01
    CHECK(pose_code(edited_f(normals + 8, 1.0005f)) == ErrorCode::ok);           // within 1e-3
    CHECK(pose_code(edited_f(positions, -0.6f)) == ErrorCode::invalid_data);     // outside bounds_min.x
    CHECK(pose_code(edited_f(positions, -0.50005f)) == ErrorCode::ok);           // within 1e-4 m
    CHECK(pose_code(edited_f(36, NAN)) == ErrorCode::invalid_data);              // bounds
}

void test_texture_array() {
    const std::vector<uint8_t> good = small_texture();
    TextureArray t;
    const Status s = parse_texture_array(good.data(), good.size(), "t.cbtx", &t);
    CHECK_MSG(s.ok(), s.message);
    CHECK(t.width == 2 && t.height == 2 && t.layer_count == 2 && t.format == PixelFormat::rgba8);
    CHECK(t.layer_size() == 16 && t.layer(1)[0] == uint8_t(16 * 7));
    for (size_t n = 0; n < good.size(); ++n)
        CHECK_MSG(texture_code(std::vector<uint8_t>(good.begin(), good.begin() + long(n))) == ErrorCode::truncated,
                  "prefix of " + std::to_string(n) + " bytes");
    auto edited = [&](size_t at, uint32_t value) {
        std::vector<uint8_t> b = good;
        put_u32(b, at, value);
        return b;
    };
    CHECK(texture_code(edited(28, 9)) == ErrorCode::invalid_header);  // unknown pixel_format
    CHECK(texture_code(edited(28, 0)) == ErrorCode::invalid_header);
    CHECK(texture_code(edited(16, 0)) == ErrorCode::invalid_header);  // width 0
    CHECK(texture_code(edited(24, 0)) == ErrorCode::invalid_header);  // no layers
    CHECK(texture_code(edited(28, 3)) == ErrorCode::invalid_header);  // bc1 at 2x2: not a multiple of 4
    CHECK(texture_code(edited(28, 2)) == ErrorCode::size_mismatch);   // rgba16 needs twice the bytes
    std::vector<uint8_t> huge = edited(16, 0xFFFFFFFCu);
    put_u32(huge, 20, 0xFFFFFFFCu);
    put_u32(huge, 24, 0xFFFFFFFFu);
    CHECK(texture_code(huge) == ErrorCode::size_mismatch);
    CHECK(texture_code(small_texture(3, 8, 4)) == ErrorCode::ok);
    CHECK(texture_code(small_texture(4, 4, 8)) == ErrorCode::ok);
    CHECK(texture_code(small_texture(2, 3, 5)) == ErrorCode::ok);
    CHECK(texture_layer_size(PixelFormat::bc1, 8, 4) == 16 && texture_layer_size(PixelFormat::bc2, 8, 4) == 32);
    CHECK(texture_layer_size(PixelFormat::bc2, 6, 4) == 0);
}

void test_block_decoding() {
    // BC1: colour0 = pure red 565, colour1 = pure blue; c0 > c1 so four colours.
    TextureArray t;
    t.width = 4, t.height = 4, t.layer_count = 1, t.format = PixelFormat::bc1;
    t.data = {0x00, 0xF8, 0x1F, 0x00, 0b11100100, 0, 0, 0};  // texels 0..3: indices 0, 1, 2, 3
    std::vector<uint8_t> rgba = decode_layer_rgba8(t, 0);
    const uint8_t expect[4][4] = {{255, 0, 0, 255}, {0, 0, 255, 255}, {170, 0, 85, 255}, {85, 0, 170, 255}};
    for (int i = 0; i < 4; ++i) CHECK(std::memcmp(&rgba[4 * i], expect[i], 4) == 0);
    CHECK(rgba[4 * 4] == 255 && rgba[4 * 4 + 2] == 0);  // texel 4 (second row): index 0, red
    // c0 <= c1: three colours and black.
    t.data = {0x1F, 0x00, 0x00, 0xF8, 0b11100100, 0, 0, 0};
    rgba = decode_layer_rgba8(t, 0);
    CHECK(rgba[8] == 127 && rgba[10] == 127);                        // index 2: the midpoint
    CHECK(rgba[12] == 0 && rgba[13] == 0 && rgba[14] == 0 && rgba[15] == 255);  // index 3: opaque black (RGB)
    // BC2: explicit alpha nibbles survive as 17 * nibble, so region codes are exact.
    t.format = PixelFormat::bc2;
    t.data = {0x10, 0x32, 0x54, 0x76, 0x98, 0xBA, 0xDC, 0xFE, 0x00, 0xF8, 0x1F, 0x00, 0, 0, 0, 0};
    rgba = decode_layer_rgba8(t, 0);
    for (int i = 0; i < 16; ++i) {
        CHECK(rgba[4 * i + 3] == 17 * i);
        CHECK(region_code(rgba[4 * i + 3]) == uint32_t(i));
        CHECK(rgba[4 * i] == 255);
    }
    // And through the test encoder: region alpha round-trips through compress_bc.
    std::vector<uint8_t> source(8 * 4 * 4);
    for (int i = 0; i < 32; ++i) source[4 * i] = uint8_t(i * 8), source[4 * i + 3] = uint8_t(17 * (i % 16));
    TextureArray packed;
    packed.width = 8, packed.height = 4, packed.layer_count = 1, packed.format = PixelFormat::bc2;
    packed.data = synthetic::compress_bc(source, 8, 4, true);
    rgba = decode_layer_rgba8(packed, 0);
    for (int i = 0; i < 32; ++i) CHECK(rgba[4 * i + 3] == source[4 * i + 3]);
    // Region rounding: r = round(alpha / 17).
    CHECK(region_code(8) == 0 && region_code(9) == 1 && region_code(25) == 1 && region_code(26) == 2 && region_code(255) == 15);
}

void test_paths_and_hash() {
    for (const char* ok : {"a", "poses/body_lod0.cbpc", "a/b/c.d-e_f", "..a", "a..", "manifest.json.bak", "x/manifest.json"})
        CHECK_MSG(is_safe_path(ok), ok);
    for (const char* bad : {"", "/etc/passwd", "../x", "a/../b", "a/./b", ".", "..", "a//b", "a/", "manifest.json",
                            "a\\b", "a b", "C:x", "caf\xc3\xa9"})
        CHECK_MSG(!is_safe_path(bad), bad);
    CHECK(is_safe_path(std::string(200, 'a')) && !is_safe_path(std::string(201, 'a')));
    // FIPS 180-2 test vectors.
    CHECK(sha256_hex(nullptr, 0) == "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    CHECK(sha256_hex(reinterpret_cast<const uint8_t*>("abc"), 3) ==
          "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
}

// ---------------------------------------------------------------------------------------
// Whole bundles in memory

struct MemoryBundle {
    json manifest;
    std::map<std::string, std::vector<uint8_t>> files;

    void add(const std::string& path, const std::string& role, const std::string& media, std::vector<uint8_t> bytes) {
        manifest["files"].push_back({{"path", path},
                                     {"size", bytes.size()},
                                     {"sha256", sha256_hex(bytes.data(), bytes.size())},
                                     {"media_type", media},
                                     {"role", role}});
        files[path] = std::move(bytes);
    }

    Status load(Bundle* out = nullptr) const {
        Bundle scratch;
        const FileSource source = [this](const FileEntry& entry, std::vector<uint8_t>* bytes) {
            auto it = files.find(entry.path);
            if (it == files.end()) return make_error(ErrorCode::missing_file, "test", entry.path, "absent");
            *bytes = it->second;
            return Status{};
        };
        return load_bundle(manifest.dump(), source, out ? out : &scratch);
    }
};

// The smallest bundle that holds every rule: one quad mesh, one 4x4 material, impostor maps
// of one 4x4 tile and two frames.
MemoryBundle tiny_bundle() {
    MemoryBundle b;
    b.manifest = {{"format", "crowdbake-bundle"},
                  {"format_version", 1},
                  {"name", "tiny"},
                  {"version", "0.1.0+test"},
                  {"created", "2026-01-01T00:00:00.5Z"},
                  {"producer", "test_bundle.cpp"},
                  {"frames_per_second", 24},
                  {"cycle",
                   {{"source_start_frame", 3}, {"source_end_frame", 5}, {"frames", 2}, {"closing", "linear"},
                    {"position_jump_ratio", 0.1}, {"velocity_jump_ratio", 0}}},
                  {"materials", {{{"name", "cloth"}, {"diffuse", "t/diffuse.cbtx"}, {"variations", 2}}}},
                  {"outfits", {{"file", "t/outfits.cbtx"}, {"count", 1}, {"regions", 16}}},
                  {"meshes",
                   {{{"part", "body"}, {"kind", "body"}, {"lod", 0}, {"file", "p/body.cbpc"}, {"material", 0},
                     {"vertex_count", 4}, {"triangle_count", 2}}}},
                  {"impostor",
                   {{"tile_size", 4},
                    {"azimuths_deg", {0}},
                    {"elevations_deg", {0}},
                    {"frame_indices", {0, 1}},
                    {"bounds", {{"center", {0, 0.5, 0}}, {"radius", 1}}},
                    {"maps", {{"normal", "i/n.cbtx"}, {"uv", "i/uv.cbtx"}, {"detail", "i/d.cbtx"}}}}},
                  {"files", json::array()}};
    const std::string texture = "application/vnd.crowdbake.texture";
    b.add("p/body.cbpc", "pose-cache", "application/vnd.crowdbake.pose-cache", quad_pose_cache());
    b.add("t/diffuse.cbtx", "diffuse", texture, small_texture(1, 4, 4));
    b.add("t/outfits.cbtx", "outfit-colours", texture, synthetic::encode_texture_array(16, 1, 1, 1, std::vector<uint8_t>(64, 9)));
    b.add("i/n.cbtx", "impostor-normal", texture, small_texture(3, 4, 4));
    b.add("i/uv.cbtx", "impostor-uv", texture, small_texture(2, 4, 4));
    b.add("i/d.cbtx", "impostor-detail", texture, small_texture(4, 4, 4));
    b.add("report.html", "report", "text/html", {'<', 'p', '>'});
    return b;
}

void expect(const MemoryBundle& b, ErrorCode code, const std::string& file, const char* what) {
    const Status s = b.load();
    CHECK_MSG(s.code == code && s.file == file,
              std::string(what) + ": got " + error_code_name(s.code) + " " + s.file + " (" + s.message + ")");
    if (!s.ok()) CHECK_MSG(s.message.rfind("load_bundle", 0) == 0 || s.message.rfind("parse_", 0) == 0 ||
                               s.message.rfind("test", 0) == 0,
                           "message starts with the function: " + s.message);
}

void test_whole_bundle() {
    Bundle bundle;
    const Status ok = tiny_bundle().load(&bundle);
    CHECK_MSG(ok.ok(), ok.message);
    CHECK(bundle.meshes.size() == 1 && bundle.meshes[0].vertex_count == 4);
    CHECK(bundle.diffuse.size() == 1 && bundle.diffuse[0].layer_count == 2);
    CHECK(bundle.impostor_uv.format == PixelFormat::rgba16 && bundle.manifest.clips.size() == 1 && bundle.manifest.clips[0].closing == "linear" && bundle.manifest.clips[0].name == "cycle");
    CHECK(bundle.manifest.impostor.center[1] == 0.5f && bundle.manifest.version == "0.1.0+test");

    // Manifest: JSON, schema, version.
    {
        MemoryBundle b = tiny_bundle();
        b.manifest["format_version"] = kFormatVersion + 1;
        b.manifest.erase("meshes");  // a newer format is named as such before the schema is applied
        expect(b, ErrorCode::unsupported_format_version, "manifest.json", "format_version kFormatVersion + 1");
    }
    const std::vector<std::pair<std::string, json>> schema_breaks = {
        {"/format", "crowdbake"},
        {"/format_version", 0},
        {"/name", "Tiny"},
        {"/version", "-1"},
        {"/created", "2026-01-01 00:00:00"},
        {"/producer", ""},
        {"/frames_per_second", 0},
        {"/cycle/closing", "cubic"},
        {"/cycle/frames", 1.5},
        {"/materials", json::array()},
        {"/materials/0/diffuse", "t\\diffuse.cbtx"},
        {"/outfits/regions", 8},
        {"/meshes/0/kind", "hair"},
        {"/meshes/0/lod", 8},
        {"/meshes/0/file", "manifest.json"},
        {"/impostor/tile_size", 6},
        {"/impostor/azimuths_deg/0", 360},
        {"/impostor/elevations_deg/0", -91},
        {"/impostor/frame_indices", json::array()},
        {"/impostor/bounds/center", {0, 1}},
        {"/impostor/bounds/radius", 0},
        {"/files/0/sha256", std::string(64, 'A')},
        {"/files/0/size", -1},
        {"/files/0/role", "texture"},
        {"/files", "none"},
    };
    for (const auto& [pointer, value] : schema_breaks) {
        MemoryBundle b = tiny_bundle();
        b.manifest[json::json_pointer(pointer)] = value;
        expect(b, ErrorCode::manifest_invalid, "manifest.json", pointer.c_str());
    }
    for (const char* key : {"format", "name", "created", "cycle", "materials", "outfits", "meshes", "impostor", "files"}) {
        MemoryBundle b = tiny_bundle();
        b.manifest.erase(key);
        expect(b, ErrorCode::manifest_invalid, "manifest.json", key);
    }
    {
        MemoryBundle b = tiny_bundle();
        b.manifest["unknown_extra"] = {1, 2};  // additionalProperties: true
        b.manifest["meshes"][0]["note"] = "ok";
        b.manifest["cycle"]["frames"] = 2.0;  // an integer in JSON Schema's sense
        expect(b, ErrorCode::ok, "", "extra properties");
    }

    // File sizes: exact integers in [0, kMaxFileSize], checked before any conversion. 2^64 - 1 read
    // as 0 (a double of 2^64 converted to uint64_t, undefined behaviour), so an empty file matched it.
    {
        const std::vector<std::pair<json, const char*>> bad_sizes = {
            {json(UINT64_MAX), "2^64 - 1"},
            {json(kMaxFileSize + 1), "2^53"},
            {json(1e300), "1e300, an integral double"},
            {json(18446744073709551616.0), "2^64 as a double"},
            {json(-1), "negative"},
            {json(12.5), "a fraction"},
        };
        for (const auto& [size, what] : bad_sizes) {
            MemoryBundle b = tiny_bundle();
            b.manifest["files"][0]["size"] = size;
            expect(b, ErrorCode::manifest_invalid, "manifest.json", what);
            Manifest m;
            const Status s = parse_manifest(b.manifest.dump(), &m);
            CHECK_MSG(s.message.find("at files/0/size: ") != std::string::npos, std::string(what) + ": names the field: " + s.message);
        }
        for (const json& size : {json(kMaxFileSize), json(double(kMaxFileSize)), json(0)}) {
            MemoryBundle b = tiny_bundle();
            b.manifest["files"][0]["size"] = size;
            Manifest m;
            const Status s = parse_manifest(b.manifest.dump(), &m);
            CHECK_MSG(s.ok() && m.files[0].size == size.get<uint64_t>(), "size " + size.dump() + " read exactly: " + s.message);
        }
    }
    // A path holding NUL or another control character: refused in full, the bytes escaped (the
    // message was cut off at the NUL).
    {
        MemoryBundle b = tiny_bundle();
        b.manifest["files"][1]["path"] = std::string("t/a\0b\x1b[31m.cbtx", sizeof "t/a\0b\x1b[31m.cbtx" - 1);
        const Status s = b.load();
        CHECK_MSG(s.code == ErrorCode::unsafe_path && s.file == "t/a\\x00b\\x1b[31m.cbtx", s.file);
        CHECK_MSG(s.message == "load_bundle: t/a\\x00b\\x1b[31m.cbtx: unsafe_path: path holds control characters (written here "
                               "as \\xNN or \\u00NN), which the bundle path rule forbids ([A-Za-z0-9._-] components)",
                  s.message);
        CHECK(std::strlen(s.message.c_str()) == s.message.size());
        CHECK(printable("a\x7f\xc2\x85" "b\xc3\xa9") == "a\\x7f\\u0085b\xc3\xa9");  // DEL, NEL (C1); é stays
    }

    // Files: path rule, duplicates, presence, size, hash, in listing order.
    {
        MemoryBundle b = tiny_bundle();
        b.manifest["files"][1]["path"] = "../../etc/passwd";
        expect(b, ErrorCode::unsafe_path, "../../etc/passwd", "escaping path");
    }
    {
        MemoryBundle b = tiny_bundle();
        b.manifest["files"].push_back(b.manifest["files"][0]);
        expect(b, ErrorCode::manifest_invalid, "p/body.cbpc", "listed twice");
    }
    {
        MemoryBundle b = tiny_bundle();
        b.files.erase("report.html");
        expect(b, ErrorCode::missing_file, "report.html", "missing");
    }
    {
        MemoryBundle b = tiny_bundle();
        b.files["t/diffuse.cbtx"].push_back(0);
        expect(b, ErrorCode::size_mismatch, "t/diffuse.cbtx", "size");
    }
    {
        MemoryBundle b = tiny_bundle();
        b.files["i/d.cbtx"][40] ^= 1;
        expect(b, ErrorCode::sha256_mismatch, "i/d.cbtx", "tampered");
    }
    // Binaries: a valid file of the wrong kind, and cross-checks.
    {
        MemoryBundle b = tiny_bundle();
        const std::vector<uint8_t> texture = small_texture(1, 4, 4);  // valid bytes, wrong kind
        for (json& entry : b.manifest["files"])
            if (entry["path"] == "p/body.cbpc") {
                entry["size"] = texture.size();
                entry["sha256"] = sha256_hex(texture.data(), texture.size());
            }
        b.files["p/body.cbpc"] = texture;
        expect(b, ErrorCode::bad_magic, "p/body.cbpc", "texture as pose cache");
    }
    auto with_manifest = [](const char* pointer, json value) {
        MemoryBundle b = tiny_bundle();
        b.manifest[json::json_pointer(pointer)] = value;
        return b;
    };
    expect(with_manifest("/meshes/0/vertex_count", 5), ErrorCode::invalid_data, "p/body.cbpc", "vertex count");
    expect(with_manifest("/meshes/0/triangle_count", 1), ErrorCode::invalid_data, "p/body.cbpc", "triangle count");
    expect(with_manifest("/cycle/frames", 3), ErrorCode::invalid_data, "p/body.cbpc", "frame count");
    expect(with_manifest("/meshes/0/material", 1), ErrorCode::invalid_data, "p/body.cbpc", "material index");
    expect(with_manifest("/meshes/0/file", "p/other.cbpc"), ErrorCode::invalid_data, "p/other.cbpc", "unlisted mesh");
    expect(with_manifest("/materials/0/variations", 3), ErrorCode::invalid_data, "t/diffuse.cbtx", "variations");
    expect(with_manifest("/outfits/count", 2), ErrorCode::invalid_data, "t/outfits.cbtx", "outfit rows");
    expect(with_manifest("/impostor/frame_indices", {1, 0}), ErrorCode::invalid_data, "manifest.json", "frame order");
    expect(with_manifest("/impostor/frame_indices", {0, 2}), ErrorCode::invalid_data, "manifest.json", "frame range");
    expect(with_manifest("/impostor/tile_size", 8), ErrorCode::invalid_data, "i/d.cbtx", "atlas size");
    expect(with_manifest("/impostor/maps/uv", "i/d.cbtx"), ErrorCode::invalid_data, "i/d.cbtx", "uv map format");
}

// Random byte edits of valid files must give a status, never a crash or a read outside the
// buffer (run under -fsanitize=address to see the second).
void test_mutations() {
    Rng rng(12345);  // reproducible edits
    const std::vector<std::vector<uint8_t>> originals = {quad_pose_cache(), small_texture(1, 4, 4), small_texture(4, 8, 8)};
    int parsed = 0;
    for (int round = 0; round < 3000; ++round) {
        std::vector<uint8_t> bytes = originals[round % originals.size()];
        const int edits = 1 + int(rng.next() % 4);
        for (int e = 0; e < edits; ++e) bytes[rng.next() % bytes.size()] = uint8_t(rng.next());
        if (rng.next() % 4 == 0) bytes.resize(rng.next() % (bytes.size() + 1));
        PoseCache cache;
        TextureArray texture;
        const Status a = parse_pose_cache(bytes.data(), bytes.size(), "m", &cache);
        const Status b = parse_texture_array(bytes.data(), bytes.size(), "m", &texture);
        parsed += a.ok() + b.ok();
        CHECK(a.ok() || !a.message.empty());
        CHECK(b.ok() || !b.message.empty());
        if (b.ok()) decode_layer_rgba8(texture, texture.layer_count - 1);
    }
    // Manifests: random edits of the text parse or fail as manifest_invalid, nothing else.
    const std::string manifest = tiny_bundle().manifest.dump();
    for (int round = 0; round < 500; ++round) {
        std::string text = manifest;
        for (int e = 0; e < 3; ++e) text[rng.next() % text.size()] = char(32 + rng.next() % 95);
        Manifest m;
        const Status s = parse_manifest(text, &m);
        CHECK(s.ok() || s.code == ErrorCode::manifest_invalid || s.code == ErrorCode::unsupported_format_version);
    }
    CHECK(parsed > 0);  // some edits only touch payload bytes and stay valid
}

}  // namespace

// The octahedral code crowdview writes for a version-1 cache's normals keeps SPEC.md's 0.005 degrees
// (crowdbake.formats.pose_codec measures the same of its own), over a spiral of directions, the axes
// and the fold's edges.
void test_octahedral_normals() {
    std::vector<std::array<double, 3>> directions = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1},
                                                     {1, 1, 0}, {1, -1, 0}, {-1, 0, -1}, {0, 1, -1}};
    const int spiral = 20000;  // Fibonacci sphere: even coverage, no randomness
    for (int i = 0; i < spiral; ++i) {
        const double y = 1.0 - 2.0 * (i + 0.5) / spiral, r = std::sqrt(1.0 - y * y), phi = i * 2.399963229728653;
        directions.push_back({r * std::cos(phi), y, r * std::sin(phi)});
    }
    double worst = 0;
    for (const auto& d : directions) {
        const double length = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        const float n[3] = {float(d[0] / length), float(d[1] / length), float(d[2] / length)};
        uint16_t code[2];
        float back[3];
        encode_octahedral(n, code);
        decode_octahedral(code, back);
        const double cx = double(n[1]) * back[2] - double(n[2]) * back[1], cy = double(n[2]) * back[0] - double(n[0]) * back[2],
                     cz = double(n[0]) * back[1] - double(n[1]) * back[0];
        const double dot = double(n[0]) * back[0] + double(n[1]) * back[1] + double(n[2]) * back[2];
        worst = std::max(worst, std::atan2(std::sqrt(cx * cx + cy * cy + cz * cz), dot) * 180.0 / M_PI);
    }
    CHECK_MSG(worst <= 0.005, "octahedral error " + std::to_string(worst) + " degrees");
}

int main() {
    test_pose_cache();
    test_octahedral_normals();
    test_texture_array();
    test_block_decoding();
    test_paths_and_hash();
    test_whole_bundle();
    test_mutations();
    return check::exit_code();
}
