// The shared vectors (shared_formats/vectors/v1, v1-uv32, v1-uvblock, v1-crop, v1-surface, v1-hostile, v2, v2-hostile-fps,
// v3 and v4), which
// the Python tests read too: the good bundle decodes to expected.json's values (v1-uv32, v1-uvblock: its UV map's
// texels too; v1-surface: its bc2 surface map's texels, alpha included), every bad bundle fails with its
// expect.json code and file, and every strict prefix of every binary file of the good bundle is `truncated`.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <map>

#include <nlohmann/json.hpp>

#include "bundle.h"
#include "check.h"
#include "pose_codec.h"
#include "synthetic_bundle.h"

#ifndef CROWDVIEW_VECTORS_DIR
#error "CMake sets CROWDVIEW_VECTORS_DIR to shared_formats/vectors"
#endif

using namespace crowdview;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

std::string hex(const uint8_t* data, size_t n) {
    static const char* digits = "0123456789abcdef";
    std::string out;
    for (size_t i = 0; i < n; ++i) out += digits[data[i] >> 4], out += digits[data[i] & 15];
    return out;
}

template <typename T>
void check_array(const json& expected, const std::vector<T>& actual, const std::string& what) {
    CHECK_MSG(expected.size() == actual.size(), what + ": length");
    if (expected.size() != actual.size()) return;
    for (size_t i = 0; i < actual.size(); ++i)
        // Values are float32 written as JSON numbers: the nearest float is exact.
        if (T(expected[i].get<double>()) != actual[i]) {
            CHECK_MSG(false, what + "[" + std::to_string(i) + "]");
            return;
        }
}

// The decoded frames against expected.json's float positions and normals: a version-1 file's are
// quantized on parse (pose_codec.h), so each position lies within half a 16-bit step of its frame's
// largest extent (plus float32 rounding) and each normal within the octahedral code's 0.005 degrees;
// a version-2 file's expected values are its own decoded codes.
void check_pose_frames(const json& values, const PoseCache& cache, const std::string& path) {
    const json& positions = values["positions"];
    const json& normals = values["normals"];
    CHECK_MSG(positions.size() == size_t(cache.frame_count) * cache.vertex_count * 3 && normals.size() == positions.size(), path);
    if (positions.size() != size_t(cache.frame_count) * cache.vertex_count * 3 || normals.size() != positions.size()) return;
    for (uint32_t f = 0; f < cache.frame_count; ++f) {
        const float* b = &cache.frame_bounds[size_t(f) * 6];
        const float extent = std::max({b[3] - b[0], b[4] - b[1], b[5] - b[2]});
        const double position_bound = extent / (2.0 * kPoseCodeMax) + 1e-6;
        for (uint32_t v = 0; v < cache.vertex_count; ++v) {
            float p[3], n[3];
            decode_pose_position(cache, f, v, p);
            decode_pose_normal(cache, f, v, n);
            double cosine = 0;
            const size_t at = (size_t(f) * cache.vertex_count + v) * 3;
            for (int axis = 0; axis < 3; ++axis) {
                CHECK_MSG(std::fabs(p[axis] - positions[at + axis].get<double>()) <= position_bound,
                          path + " frame " + std::to_string(f) + " vertex " + std::to_string(v));
                cosine += n[axis] * normals[at + axis].get<double>();
            }
            CHECK_MSG(cosine >= std::cos(0.005 * M_PI / 180.0) - 1e-6, path + " normal at frame " + std::to_string(f) + " vertex " + std::to_string(v));
        }
    }
}

void test_good(const fs::path& good) {
    Bundle bundle;
    const Status s = load_bundle_dir((good / "bundle").string(), &bundle);
    CHECK_MSG(s.ok(), s.message);
    const json expected = json::parse(synthetic::read_text((good / "expected.json").string()));
    CHECK(bundle.manifest.name == expected["name"]);
    CHECK(bundle.manifest.version == expected["version"]);
    CHECK(bundle.manifest.format_version == expected["format_version"].get<uint32_t>());

    for (const auto& [path, values] : expected["pose_caches"].items()) {
        std::vector<uint8_t> bytes;
        CHECK_MSG(read_file_bytes((good / "bundle" / path).string(), &bytes), path);
        PoseCache cache;
        const Status p = parse_pose_cache(bytes.data(), bytes.size(), path, &cache);
        CHECK_MSG(p.ok(), p.message);
        CHECK_MSG(cache.vertex_count == values["vertex_count"].get<uint32_t>(), path);
        CHECK_MSG(cache.index_count / 3 == values["triangle_count"].get<uint32_t>(), path);
        CHECK_MSG(cache.frame_count == values["frame_count"].get<uint32_t>(), path);
        CHECK_MSG(cache.frames_per_second == values["frames_per_second"].get<float>(), path);
        check_array(values["indices"], cache.indices, path + " indices");
        check_array(values["uvs"], cache.uvs, path + " uvs");
        check_pose_frames(values, cache, path);
        // The bundle's decoded mesh is this same file.
        for (size_t i = 0; i < bundle.manifest.meshes.size(); ++i)
            if (bundle.manifest.meshes[i].file == path) CHECK_MSG(bundle.meshes[i].position_codes == cache.position_codes, path);
    }
    for (const auto& [path, values] : expected["textures"].items()) {
        std::vector<uint8_t> bytes;
        CHECK_MSG(read_file_bytes((good / "bundle" / path).string(), &bytes), path);
        TextureArray t;
        const Status p = parse_texture_array(bytes.data(), bytes.size(), path, &t);
        CHECK_MSG(p.ok(), p.message);
        CHECK_MSG(t.width == values["width"].get<uint32_t>() && t.height == values["height"].get<uint32_t>(), path);
        CHECK_MSG(pixel_format_name(t.format) == values["pixel_format"].get<std::string>(), path);
        CHECK_MSG(t.layer_count == values["layer_count"].get<uint32_t>(), path);
        for (uint32_t k = 0; k < t.layer_count && k < values["layers_sha256"].size(); ++k)
            CHECK_MSG(sha256_hex(t.layer(k), t.layer_size()) == values["layers_sha256"][k].get<std::string>(),
                      path + " layer " + std::to_string(k));
        CHECK_MSG(hex(t.layer(0), std::min<size_t>(8, t.layer_size())) == values["first_bytes_hex"].get<std::string>(), path);
    }
}

// v1-uv32: the UV map's words and their decoded fields at the texels expected.json lists.
void test_uv32_texels(const fs::path& good) {
    Bundle bundle;
    const Status s = load_bundle_dir((good / "bundle").string(), &bundle);
    CHECK_MSG(s.ok(), s.message);
    if (!s.ok()) return;
    const json expected = json::parse(synthetic::read_text((good / "expected.json").string()));
    const TextureArray& t = bundle.impostor_uv;
    CHECK(t.format == PixelFormat::uv32 && t.layer_size() == size_t(4) * t.width * t.height);
    int checked = 0;
    for (const json& want : expected["uv32_texels"]["texels"]) {
        const uint32_t layer = want["layer"], row = want["row"], column = want["column"];
        uint32_t word = 0;
        std::memcpy(&word, t.layer(layer) + 4 * (size_t(row) * t.width + column), 4);
        const std::string where = "uv32 texel " + want.dump();
        CHECK_MSG(word == want["word"].get<uint32_t>(), where);
        const Uv32Texel texel = unpack_uv32(word);
        // The shader divides in float too: exact for the 14-bit integers, to float rounding after.
        CHECK_MSG(std::abs(texel.u - want["u"].get<double>()) < 1e-6 && std::abs(texel.v - want["v"].get<double>()) < 1e-6, where);
        CHECK_MSG(texel.material == want["material"].get<uint32_t>() && texel.covered == want["coverage"].get<bool>(), where);
        CHECK_MSG(pack_uv32(texel.u, texel.v, texel.material, texel.covered) == word, where + " re-packs");
        ++checked;
    }
    CHECK(checked >= 4);
}

// v1-uvblock: every texel of the block-coded UV map decodes to expected.json's integers.
void test_uvblock_texels(const fs::path& good) {
    Bundle bundle;
    const Status s = load_bundle_dir((good / "bundle").string(), &bundle);
    CHECK_MSG(s.ok(), s.message);
    if (!s.ok()) return;
    const json expected = json::parse(synthetic::read_text((good / "expected.json").string()));
    const TextureArray& t = bundle.impostor_uv;
    CHECK(t.format == PixelFormat::uvblock && t.layer_size() == size_t(kUvBlockBytes) * (t.width / 4) * (t.height / 4));
    int checked = 0;
    for (const json& want : expected["uvblock_texels"]["texels"]) {
        const uint32_t layer = want["layer"], row = want["row"], column = want["column"];
        const uint8_t* block = t.layer(layer) + (size_t(row / 4) * (t.width / 4) + column / 4) * kUvBlockBytes;
        const UvBlockTexel texel = unpack_uvblock_texel(block, (row % 4) * 4 + column % 4);
        const std::string where = "uvblock texel " + want.dump();
        CHECK_MSG(texel.covered == want["coverage"].get<bool>() && texel.material == want["material"].get<uint32_t>(), where);
        CHECK_MSG(texel.qu == want["qu"].get<uint32_t>() && texel.qv == want["qv"].get<uint32_t>(), where);
        ++checked;
    }
    CHECK(checked == int(t.width * t.height * t.layer_count));
    // The CPU decode keeps the top 8 of the 12 bits and coverage, as for uv32.
    const std::vector<uint8_t> rgba = decode_layer_rgba8(t, 0);
    const UvBlockTexel first = unpack_uvblock_texel(t.layer(0), 0);
    CHECK(rgba[0] == uint8_t(first.qu >> 4) && rgba[3] == (first.covered ? 255 : 0));
}

// v1-surface: every texel of the bc2 surface map, as the renderer's CPU path decodes it (decode_layer_rgba8),
// equals expected.json's r, g, b (depth and motion codes) and a (the share of the texel the character covers).
void test_surface_texels(const fs::path& good) {
    Bundle bundle;
    const Status s = load_bundle_dir((good / "bundle").string(), &bundle);
    CHECK_MSG(s.ok(), s.message);
    if (!s.ok()) return;
    const json expected = json::parse(synthetic::read_text((good / "expected.json").string()))["surface_texels"];
    const TextureArray& t = bundle.impostor_surface;
    CHECK(bundle.manifest.impostor.surface_map == expected["file"].get<std::string>());
    CHECK(pixel_format_name(t.format) == expected["pixel_format"].get<std::string>() && t.format == PixelFormat::bc2);
    CHECK(t.width == bundle.impostor_uv.width && t.height == bundle.impostor_uv.height && t.layer_count == bundle.impostor_uv.layer_count);
    std::vector<std::vector<uint8_t>> layers;
    for (uint32_t k = 0; k < t.layer_count; ++k) layers.push_back(decode_layer_rgba8(t, k));
    int checked = 0, partial = 0;
    for (const json& want : expected["texels"]) {
        const uint32_t layer = want["layer"], x = want["x"], y = want["y"];
        CHECK_MSG(layer < t.layer_count && x < t.width && y < t.height, "surface texel " + want.dump() + " outside the map");
        if (layer >= t.layer_count || x >= t.width || y >= t.height) continue;
        const uint8_t* texel = &layers[layer][(size_t(y) * t.width + x) * 4];
        const std::string got = std::to_string(texel[0]) + "," + std::to_string(texel[1]) + "," + std::to_string(texel[2]) + "," +
                                std::to_string(texel[3]);
        CHECK_MSG(texel[0] == want["r"].get<int>() && texel[1] == want["g"].get<int>() && texel[2] == want["b"].get<int>() &&
                      texel[3] == want["a"].get<int>(),
                  "surface texel " + want.dump() + ": decoded " + got);
        partial += texel[3] > 0 && texel[3] < 255;
        ++checked;
    }
    CHECK(checked == int(t.width * t.height * t.layer_count));
    CHECK(partial > 0);  // the anti-aliased silhouette: texels the character covers in part
}

// Vectors are never edited, so an expectation a newer reader no longer meets is restated here
// (services/tests/repo_paths.py alike). v1's future_format_version claims format_version 2, written
// when 2 was the future: a reader of v2 reads it as a v2 manifest holding v1's cycle and no clips,
// manifest_invalid. v2's claims 3: a reader of v3 reads it as a v3 bundle holding version-1 pose
// caches, invalid_data at the first (SPEC.md "Version 3"). v3/bad/future_format_version is the
// future case now.
// v3's claims 4: a reader of v4 reads it as the v3 bundle it is, which a v4 bundle may be (every mesh a
// quantized CBPC), so it loads ("ok", no file). v4/bad/future_format_version is the future case now.
const std::map<std::string, json> kSuperseded = {
    {"v1/future_format_version", {{"error", "manifest_invalid"}, {"file", "manifest.json"}}},
    {"v2/future_format_version", {{"error", "invalid_data"}, {"file", "poses/body_lod0.cbpc"}}},
    {"v3/future_format_version", {{"error", "ok"}, {"file", ""}}},
};

void test_bad(const fs::path& bad_root, int min_cases) {
    int cases = 0;
    for (const auto& entry : fs::directory_iterator(bad_root)) {
        if (!entry.is_directory()) continue;
        json expect = json::parse(synthetic::read_text((entry.path() / "expect.json").string()));
        const std::string key = bad_root.parent_path().filename().string() + "/" + entry.path().filename().string();
        if (auto it = kSuperseded.find(key); it != kSuperseded.end()) expect = it->second;
        Bundle bundle;
        const Status s = load_bundle_dir((entry.path() / "bundle").string(), &bundle);
        const std::string name = entry.path().filename().string();
        CHECK_MSG(error_code_name(s.code) == expect["error"].get<std::string>() && s.file == expect["file"].get<std::string>(),
                  name + ": expected " + expect.dump() + ", got " + error_code_name(s.code) + " " + s.file + " (" + s.message + ")");
        ++cases;
    }
    CHECK_MSG(cases >= min_cases, "found " + std::to_string(cases) + " bad cases");
}

// v2 (generate_vectors_v2.py): two clips and two transitions, read as expected.json lists them.
void test_good_v2(const fs::path& good) {
    Bundle bundle;
    const Status s = load_bundle_dir((good / "bundle").string(), &bundle);
    CHECK_MSG(s.ok(), s.message);
    if (!s.ok()) return;
    const json expected = json::parse(synthetic::read_text((good / "expected.json").string()));
    const Manifest& m = bundle.manifest;
    CHECK(m.format_version == 2 && m.name == expected["name"] && m.version == expected["version"]);
    CHECK(m.pose_frames == expected["pose_frames"].get<uint32_t>());
    CHECK(m.frames_per_second == expected["frames_per_second"].get<double>());
    CHECK_MSG(m.clips.size() == expected["clips"].size(), "clip count");
    for (size_t i = 0; i < m.clips.size() && i < expected["clips"].size(); ++i) {
        const json& e = expected["clips"][i];
        const ClipInfo& c = m.clips[i];
        CHECK_MSG(c.name == e["name"] && c.first_frame == e["first_frame"].get<uint32_t>() && c.frames == e["frames"].get<uint32_t>() &&
                      c.source_start_frame == e["source_start_frame"].get<uint32_t>() &&
                      c.source_end_frame == e["source_end_frame"].get<uint32_t>() && c.closing == e["closing"] &&
                      c.position_jump_ratio == e["position_jump_ratio"].get<double>() &&
                      c.velocity_jump_ratio == e["velocity_jump_ratio"].get<double>(),
                  "clip " + std::to_string(i));
    }
    CHECK_MSG(m.transitions.size() == expected["transitions"].size(), "transition count");
    for (size_t i = 0; i < m.transitions.size() && i < expected["transitions"].size(); ++i) {
        const json& e = expected["transitions"][i];
        const TransitionInfo& t = m.transitions[i];
        CHECK_MSG(t.from_clip == e["from_clip"].get<uint32_t>() && t.to_clip == e["to_clip"].get<uint32_t>() &&
                      t.leave_frame == e["leave_frame"].get<uint32_t>() && t.arrive_frame == e["arrive_frame"].get<uint32_t>() &&
                      t.first_frame == e["first_frame"].get<uint32_t>() && t.frames == e["frames"].get<uint32_t>() &&
                      t.source_start_frame == e["source_start_frame"].get<uint32_t>() &&
                      t.source_end_frame == e["source_end_frame"].get<uint32_t>() &&
                      t.position_jump_ratio == e["position_jump_ratio"].get<double>() &&
                      t.velocity_jump_ratio == e["velocity_jump_ratio"].get<double>(),
                  "transition " + std::to_string(i));
    }
    check_array(expected["frame_indices"], m.impostor.frame_indices, "frame_indices");
    for (size_t i = 0; i < m.meshes.size(); ++i)
        CHECK_MSG(bundle.meshes[i].frame_count == expected["pose_cache_frame_count"][m.meshes[i].file].get<uint32_t>(), m.meshes[i].file);
}

// v3 (generate_vectors_v3.py): v2's ranges with quantized pose caches. The stored codes and frame bounds
// come back exactly, and decode to expected.json's floats (the Python reader's) up to float32 rounding.
void test_good_v3(const fs::path& good) {
    Bundle bundle;
    const Status s = load_bundle_dir((good / "bundle").string(), &bundle);
    CHECK_MSG(s.ok(), s.message);
    if (!s.ok()) return;
    const json expected = json::parse(synthetic::read_text((good / "expected.json").string()));
    CHECK(bundle.manifest.format_version == 3 && bundle.manifest.clips.size() == expected["clips"].size());
    CHECK(bundle.manifest.pose_frames == expected["pose_frames"].get<uint32_t>());
    for (size_t i = 0; i < bundle.manifest.meshes.size(); ++i) {
        const std::string& path = bundle.manifest.meshes[i].file;
        const json& values = expected["pose_caches"][path];
        const PoseCache& cache = bundle.meshes[i];
        CHECK_MSG(cache.version == 2 && cache.vertex_count == values["vertex_count"].get<uint32_t>(), path);
        check_array(values["frame_bounds"], cache.frame_bounds, path + " frame_bounds");
        check_array(values["position_codes"], cache.position_codes, path + " position_codes");
        check_array(values["normal_codes"], cache.normal_codes, path + " normal_codes");
        double worst_position = 0, worst_normal = 0;
        for (uint32_t f = 0; f < cache.frame_count; ++f)
            for (uint32_t v = 0; v < cache.vertex_count; ++v) {
                float p[3], n[3];
                decode_pose_position(cache, f, v, p);
                decode_pose_normal(cache, f, v, n);
                const size_t at = (size_t(f) * cache.vertex_count + v) * 3;
                for (int axis = 0; axis < 3; ++axis) {
                    worst_position = std::max(worst_position, std::fabs(p[axis] - values["positions"][at + axis].get<double>()));
                    worst_normal = std::max(worst_normal, std::fabs(n[axis] - values["normals"][at + axis].get<double>()));
                }
            }
        CHECK_MSG(worst_position <= 1e-6 && worst_normal <= 1e-6,
                  path + ": decoded differs by " + std::to_string(worst_position) + " m, normals by " + std::to_string(worst_normal));
    }
}

// Every strict prefix of every binary file (CBPC, CBSK, CBTX) under `bundle_dir` is `truncated`, read as the
// bundle reader reads it (a pose file by its magic, parse_mesh_pose_file).
// A nested JSON array (matrices [frame][joint][12], positions [frame][vertex][3], ...) as its leaves in order.
json flattened(const json& nested) {
    if (!nested.is_array()) return json::array({nested});
    json flat = json::array();
    for (const json& item : nested)
        for (const json& leaf : flattened(item)) flat.push_back(leaf);
    return flat;
}

// The largest difference between expected.json's `values` ([frame][vertex][3]) and what decode(frame, vertex) gives.
template <typename Decode>
double worst_difference(const json& values, const PoseCache& cache, Decode decode) {
    const json flat = flattened(values);
    if (flat.size() != size_t(cache.frame_count) * cache.vertex_count * 3) return INFINITY;
    double worst = 0;
    for (uint32_t f = 0; f < cache.frame_count; ++f)
        for (uint32_t v = 0; v < cache.vertex_count; ++v) {
            float got[3];
            decode(cache, f, v, got);
            for (int axis = 0; axis < 3; ++axis)
                worst = std::max(worst, std::fabs(got[axis] - flat[(size_t(f) * cache.vertex_count + v) * 3 + axis].get<double>()));
        }
    return worst;
}

// v4 (generate_vectors_v4.py): v3's bundle with its bodies skinned. Each CBSK's stored arrays come back exactly,
// and the CPU's skinning (decode_pose_position, decode_pose_normal) gives expected.json's frames: positions
// within 1e-5 m, normals within 1e-4. The garment stays a quantized CBPC.
void test_good_v4(const fs::path& good) {
    Bundle bundle;
    const Status s = load_bundle_dir((good / "bundle").string(), &bundle);
    CHECK_MSG(s.ok(), s.message);
    if (!s.ok()) return;
    const json expected = json::parse(synthetic::read_text((good / "expected.json").string()));
    CHECK(bundle.manifest.format_version == 4 && bundle.manifest.format_version == expected["format_version"].get<uint32_t>());
    int skinned = 0;
    for (size_t i = 0; i < bundle.manifest.meshes.size(); ++i) {
        const std::string& path = bundle.manifest.meshes[i].file;
        const PoseCache& cache = bundle.meshes[i];
        CHECK_MSG(cache.skinned() == expected["skinned"].contains(path), path + ": skinned where expected.json lists it");
        if (!cache.skinned()) CHECK_MSG(cache.version == kQuantizedPoseCacheVersion && bundle.manifest.meshes[i].kind == "garment", path);
        if (!cache.skinned() || !expected["skinned"].contains(path)) continue;
        ++skinned;
        const json& want = expected["skinned"][path];
        CHECK_MSG(cache.vertex_count == want["vertex_count"].get<uint32_t>() && cache.index_count == want["index_count"].get<uint32_t>() &&
                      cache.frame_count == want["frame_count"].get<uint32_t>() && cache.skin.joint_count == want["joint_count"].get<uint32_t>() &&
                      cache.frames_per_second == want["frames_per_second"].get<float>(),
                  path + ": counts");
        check_array(want["bounds_min"], std::vector<float>(cache.bounds_min, cache.bounds_min + 3), path + " bounds_min");
        check_array(want["bounds_max"], std::vector<float>(cache.bounds_max, cache.bounds_max + 3), path + " bounds_max");
        check_array(flattened(want["joints"]), cache.skin.joints, path + " joints");
        check_array(flattened(want["weight_codes"]), cache.skin.weight_codes, path + " weight_codes");
        check_array(flattened(want["matrices"]), cache.skin.matrices, path + " matrices");
        const double position = worst_difference(want["positions"], cache, decode_pose_position);
        const double normal = worst_difference(want["normals"], cache, decode_pose_normal);
        CHECK_MSG(position <= 1e-5 && normal <= 1e-4,
                  path + ": skinned differs by " + std::to_string(position) + " m, normals by " + std::to_string(normal));
    }
    CHECK_MSG(skinned == int(expected["skinned"].size()) && skinned >= 2, "skinned meshes: " + std::to_string(skinned));
}

void test_prefixes(const fs::path& bundle_dir) {
    int files = 0;
    for (const auto& entry : fs::recursive_directory_iterator(bundle_dir)) {
        const std::string ext = entry.path().extension().string();
        if (ext != ".cbpc" && ext != ".cbsk" && ext != ".cbtx") continue;
        std::vector<uint8_t> bytes;
        CHECK(read_file_bytes(entry.path().string(), &bytes));
        ++files;
        for (size_t n = 0; n < bytes.size(); ++n) {
            Status s;
            if (ext != ".cbtx") {
                PoseCache cache;
                s = parse_mesh_pose_file(bytes.data(), n, entry.path().filename().string(), &cache);
            } else {
                TextureArray texture;
                s = parse_texture_array(bytes.data(), n, entry.path().filename().string(), &texture);
            }
            if (s.code != ErrorCode::truncated) {
                CHECK_MSG(false, entry.path().string() + ": prefix of " + std::to_string(n) + " bytes gave " + error_code_name(s.code));
                break;
            }
        }
    }
    CHECK_MSG(files >= 2, "binary files in the good bundle");
}

}  // namespace

int main() {
    const fs::path v1 = fs::path(CROWDVIEW_VECTORS_DIR) / "v1";
    if (!fs::is_directory(v1 / "good")) {
        std::fprintf(stderr, "SKIP: no shared vectors at %s\n", v1.string().c_str());
        return 77;
    }
    test_good(v1 / "good");
    test_bad(v1 / "bad", 10);
    test_prefixes(v1 / "good" / "bundle");
    const fs::path uv32 = fs::path(CROWDVIEW_VECTORS_DIR) / "v1-uv32";
    CHECK_MSG(fs::is_directory(uv32 / "good"), "no uv32 vectors at " + uv32.string());
    if (fs::is_directory(uv32 / "good")) {
        test_good(uv32 / "good");
        test_uv32_texels(uv32 / "good");
        test_bad(uv32 / "bad", 3);
        test_prefixes(uv32 / "good" / "bundle");
    }
    const fs::path uvblock = fs::path(CROWDVIEW_VECTORS_DIR) / "v1-uvblock";
    CHECK_MSG(fs::is_directory(uvblock / "good"), "no uvblock vectors at " + uvblock.string());
    if (fs::is_directory(uvblock / "good")) {
        test_good(uvblock / "good");
        test_uvblock_texels(uvblock / "good");
        test_bad(uvblock / "bad", 3);
        test_prefixes(uvblock / "good" / "bundle");
    }
    // The crop (generate_vectors_v1_crop.py): v1's maps read as the 4x4 crop at (4, 0) of 8-texel tiles.
    const fs::path crop = fs::path(CROWDVIEW_VECTORS_DIR) / "v1-crop";
    CHECK_MSG(fs::is_directory(crop / "good"), "no crop vectors at " + crop.string());
    if (fs::is_directory(crop / "good")) {
        test_good(crop / "good");
        Bundle bundle;
        CHECK(load_bundle_dir((crop / "good" / "bundle").string(), &bundle).ok());
        const json want = json::parse(synthetic::read_text((crop / "good" / "expected.json").string()))["crop"];
        const ImpostorInfo& imp = bundle.manifest.impostor;
        CHECK(imp.tile_size == want["tile_size"].get<uint32_t>() && imp.crop.x == want["x"].get<uint32_t>() &&
              imp.crop.y == want["y"].get<uint32_t>() && imp.crop.width == want["width"].get<uint32_t>() &&
              imp.crop.height == want["height"].get<uint32_t>());
        test_bad(crop / "bad", 3);
    }
    // The surface map (generate_vectors_v1_surface.py): v1's maps plus a bc2 surface map of chosen texels.
    const fs::path surface = fs::path(CROWDVIEW_VECTORS_DIR) / "v1-surface";
    CHECK_MSG(fs::is_directory(surface / "good"), "no surface vectors at " + surface.string());
    if (fs::is_directory(surface / "good")) {
        test_good(surface / "good");
        test_surface_texels(surface / "good");
        test_bad(surface / "bad", 6);
        test_prefixes(surface / "good" / "bundle");
    }
    // v1 has no crop: the whole tile.
    {
        Bundle bundle;
        CHECK(load_bundle_dir((v1 / "good" / "bundle").string(), &bundle).ok());
        const ImpostorInfo& imp = bundle.manifest.impostor;
        CHECK(imp.crop.x == 0 && imp.crop.y == 0 && imp.crop.width == imp.tile_size && imp.crop.height == imp.tile_size);
    }
    // Format v2: clips and transitions; every strict prefix of its binaries is truncated too.
    const fs::path v2 = fs::path(CROWDVIEW_VECTORS_DIR) / "v2";
    CHECK_MSG(fs::is_directory(v2 / "good"), "no v2 vectors at " + v2.string());
    if (fs::is_directory(v2 / "good")) {
        test_good_v2(v2 / "good");
        test_bad(v2 / "bad", 14);
        test_prefixes(v2 / "good" / "bundle");
    }
    // Format v3: quantized pose caches; bad bounds, versions and every strict prefix of the quantized caches.
    const fs::path v3 = fs::path(CROWDVIEW_VECTORS_DIR) / "v3";
    CHECK_MSG(fs::is_directory(v3 / "good"), "no v3 vectors at " + v3.string());
    if (fs::is_directory(v3 / "good")) {
        test_good_v3(v3 / "good");
        test_bad(v3 / "bad", 10);
        test_prefixes(v3 / "good" / "bundle");
    }
    // Format v4: skinned bodies (CBSK); bad joints, weights, matrices, bounds, headers, placements and versions.
    const fs::path v4 = fs::path(CROWDVIEW_VECTORS_DIR) / "v4";
    CHECK_MSG(fs::is_directory(v4 / "good"), "no v4 vectors at " + v4.string());
    if (fs::is_directory(v4 / "good")) {
        test_good_v4(v4 / "good");
        test_bad(v4 / "bad", 12);
        test_prefixes(v4 / "good" / "bundle");
    }
    // Manifests a hostile server could send (generate_vectors_v1_hostile.py): sizes past 2^53 - 1,
    // paths holding control characters.
    const fs::path hostile = fs::path(CROWDVIEW_VECTORS_DIR) / "v1-hostile";
    CHECK_MSG(fs::is_directory(hostile / "bad"), "no hostile vectors at " + hostile.string());
    if (fs::is_directory(hostile / "bad")) test_bad(hostile / "bad", 4);
    // Frame rates (generate_vectors_v2_hostile_fps.py): 1000 everywhere reads; 1e300, 0.5 and 1000.5
    // are refused, and so is a manifest whose rate differs from its pose caches'.
    const fs::path fps = fs::path(CROWDVIEW_VECTORS_DIR) / "v2-hostile-fps";
    CHECK_MSG(fs::is_directory(fps / "bad"), "no frame-rate vectors at " + fps.string());
    if (fs::is_directory(fps / "bad")) {
        Bundle bundle;
        const Status s = load_bundle_dir((fps / "good" / "bundle").string(), &bundle);
        const json expected = json::parse(synthetic::read_text((fps / "good" / "expected.json").string()));
        CHECK_MSG(s.ok() && bundle.manifest.frames_per_second == expected["frames_per_second"].get<double>(), s.message);
        test_bad(fps / "bad", 4);
    }
    return check::exit_code();
}
