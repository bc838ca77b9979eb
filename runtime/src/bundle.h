// Bundle reader: shared_formats/SPEC.md (format versions 1 to 4), without any GL.
//
// Every function returns a Status; none throws or aborts on bad input. A failing Status
// carries one of the spec's error codes, the bundle path of the file concerned, and a
// message that starts with the function that found the problem, e.g.
//   "parse_pose_cache: poses/body_lod0.cbpc: truncated: 300 bytes, header says 312".
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

namespace crowdview {

// SPEC.md "Error codes", plus the fetch's own codes for what the spec cannot know about; a
// fetch never reports those as a bundle fault:
//   fetch_failed  transport errors (connection refused, HTTP 500, a download past its deadline)
//   not_found     no bundle at the URL (HTTP 404 or 410 for the manifest, no such file://)
//   unauthorized  the server wants a key, or refused the one sent (HTTP 401 or 403)
//   over_budget   the manifest lists more bytes than the cache budget allows
enum class ErrorCode {
    ok = 0,
    manifest_invalid,
    unsupported_format_version,
    unsafe_path,
    missing_file,
    size_mismatch,
    sha256_mismatch,
    truncated,
    bad_magic,
    unsupported_version,
    invalid_header,
    invalid_data,
    fetch_failed,
    not_found,
    unauthorized,
    over_budget,
};

// The spec's spelling of `code` ("size_mismatch"); "ok" for ErrorCode::ok.
const char* error_code_name(ErrorCode code);

struct Status {
    ErrorCode code = ErrorCode::ok;
    std::string file;     // bundle path the error concerns ("manifest.json" for the manifest), printable()
    std::string message;  // "<function>: <file>: <code>: <detail>", printable()

    bool ok() const { return code == ErrorCode::ok; }
    explicit operator bool() const { return ok(); }
};

// Builds a failing Status; `function` leads the message. `file` and `detail` may come from a
// hostile manifest: both pass through printable(), so the message is whole and on one line.
Status make_error(ErrorCode code, const char* function, const std::string& file, const std::string& detail);

// `text` with every control character written out: C0 bytes and DEL as \xNN, the C1 controls
// (U+0080..U+009F, two bytes in UTF-8) as \u00NN; everything else unchanged. A path holding NUL
// would otherwise cut a C string short, and an escape sequence would reach the terminal.
// crowdbake.formats.errors.printable writes the same.
std::string printable(const std::string& text);

// ---------------------------------------------------------------------------------------
// Binary files

enum class PixelFormat : uint32_t { rgba8 = 1, rgba16 = 2, bc1 = 3, bc2 = 4, uv32 = 5, uvblock = 6, bc5 = 7 };
const char* pixel_format_name(PixelFormat format);

// uv32 (SPEC.md pixel format 5): one little-endian u32 a UV-map texel, u in bits 0..13,
// v in 14..27 (value / 16383), material in 28..30, coverage in bit 31.
struct Uv32Texel {
    float u = 0, v = 0;
    uint32_t material = 0;
    bool covered = false;
};
constexpr uint32_t kUv32CoordMax = (1u << 14) - 1;
inline Uv32Texel unpack_uv32(uint32_t word) {
    return {float(word & kUv32CoordMax) / float(kUv32CoordMax), float((word >> 14) & kUv32CoordMax) / float(kUv32CoordMax),
            (word >> 28) & 7u, (word >> 31) != 0};
}
// u, v in [0, 1] (clamped); material 0..7 (masked); uncovered texels are 0.
uint32_t pack_uv32(float u, float v, uint32_t material, bool covered);

// uvblock (SPEC.md pixel format 6): 4x4 texels in 24 bytes, six little-endian u32 words. w0: a
// 2-bit state per texel (0 outside, 1..3 subset 0..2); w1 | w2 << 32: three 21-bit subset
// headers (u base 8 bits, v base 8 bits in units of 16/4095, material 2 bits, shift 3 bits);
// w3..w5: 3-bit u and v offsets of texel i at stream bits 6i and 6i + 3. A covered texel's
// coordinate is (16 * base + (offset << shift)) / 4095. impostor_uv_map.glsl decodes the same.
constexpr uint32_t kUvBlockBytes = 24;
constexpr uint32_t kUvBlockCoordMax = 4095;
struct UvBlockTexel {
    uint32_t qu = 0, qv = 0;  // coordinates in 1/4095; 0 outside
    uint32_t material = 0;
    bool covered = false;
};
// Texel i (x = i % 4, y = i / 4) of the 24-byte block at `block`.
UvBlockTexel unpack_uvblock_texel(const uint8_t* block, uint32_t i);

constexpr uint32_t kPoseCacheHeaderSize = 64;
// CBPC versions: 1 stores float32 frames, 2 quantized ones (SPEC.md "Pose cache version 2").
constexpr uint32_t kQuantizedPoseCacheVersion = 2;
constexpr uint32_t kTextureHeaderSize = 32;
// SPEC.md: normals are unit length within 1e-3 and bounds enclose positions within 1e-4 m,
// allowances for float32 rounding in the bake.
constexpr float kNormalLengthTolerance = 1e-3f;
constexpr float kBoundsTolerance = 1e-4f;

// CBSK (SPEC.md "Skinned pose cache", format version 4): version 1, the same 64-byte header as CBPC with
// joint_count where CBPC has flags. joint_count is 1 to 1024.
constexpr uint32_t kSkinnedPoseCacheVersion = 1;
constexpr uint32_t kMaxJoints = 1024;
// frame_count x vertex_count of a CBSK at most (SPEC.md): a reader skins every frame to check its bounds.
constexpr uint64_t kMaxSkinnedVertexFrames = uint64_t(1) << 26;
// SPEC.md: every 3x3 block a weighted influence uses is invertible, |det| >= 1e-6.
constexpr double kMinJointDeterminant = 1e-6;

// A skinned body's frames as a CBSK stores them: the rest mesh, four joint influences a vertex and
// every joint's 3x4 skinning matrix per frame (skinned_pose.h skins one vertex). Empty in a CBPC.
struct PoseSkin {
    uint32_t joint_count = 0;            // 0: the cache is not skinned
    std::vector<float> rest_positions;   // vertex_count * 3, the bind pose (metres)
    std::vector<float> rest_normals;     // vertex_count * 3, unit length
    std::vector<uint16_t> joints;        // vertex_count * 4, each < joint_count
    std::vector<uint16_t> weight_codes;  // vertex_count * 4, weight = code / 65535, summing to 65535 a vertex
    std::vector<float> matrices;         // frame_count * joint_count * 12: the top three rows, row-major, frame-major
};

// One mesh part at one LOD over every pose frame of the bundle (CBPC or CBSK). A CBPC's frames are held
// as version 2 stores them, the layout mesh.vert.glsl reads; a version-1 file's float frames are
// quantized on parse. A CBSK keeps its rest mesh, influences and matrices in `skin` and no frame codes.
// pose_codec.h decodes one vertex of either.
struct PoseCache {
    uint32_t version = 0;  // of the file it was parsed from (a CBSK's: kSkinnedPoseCacheVersion)
    uint32_t vertex_count = 0;
    uint32_t index_count = 0;
    uint32_t frame_count = 0;
    float frames_per_second = 0;
    float bounds_min[3] = {0, 0, 0};
    float bounds_max[3] = {0, 0, 0};
    std::vector<uint32_t> indices;  // index_count, counter-clockwise triangles
    std::vector<float> uvs;         // vertex_count * 2
    std::vector<float> frame_bounds;        // frame_count * 6: each frame's position minimum xyz, then maximum xyz
    std::vector<uint16_t> normal_codes;    // frame_count * vertex_count * 2, frame-major, octahedral
    std::vector<uint16_t> position_codes;  // frame_count * vertex_count * 3, frame-major, within the frame's bounds
    PoseSkin skin;                         // a CBSK's; frame_bounds and the codes are then empty

    bool skinned() const { return skin.joint_count > 0; }
};

// A stack of equally sized layers (CBTX); `data` holds layer 0, layer 1, ... as stored.
struct TextureArray {
    uint32_t width = 0;
    uint32_t height = 0;
    uint32_t layer_count = 0;
    PixelFormat format = PixelFormat::rgba8;
    std::vector<uint8_t> data;

    size_t layer_size() const;
    const uint8_t* layer(uint32_t k) const { return data.data() + k * layer_size(); }
};

// SPEC.md's common header, in its order: at least 16 bytes (truncated), `magic` (bad_magic), a version
// from 1 to `max_version` (unsupported_version), `header_size` (invalid_header), the actual size
// against file_size (truncated, size_mismatch). Messages start with `function`.
Status check_common_header(const uint8_t* data, size_t size, const std::string& file, const char* function, const char* magic,
                           uint32_t header_size, uint32_t max_version);

// Bytes of one width x height layer in `format`; 0 for an unknown format or a BC size that
// is not a multiple of 4.
size_t texture_layer_size(PixelFormat format, uint32_t width, uint32_t height);

// Parse a CBPC file of `size` bytes. `file` names it in errors. Checks run in the spec's
// order, so every strict prefix of a valid file is `truncated`. `out` is written only on success.
Status parse_pose_cache(const uint8_t* data, size_t size, const std::string& file, PoseCache* out);
// Same for a CBSK file (SPEC.md "Skinned pose cache"): `out` comes back skinned(). Its payload checks
// skin every vertex of every frame on the CPU, to check the header's bounds.
Status parse_skinned_pose_cache(const uint8_t* data, size_t size, const std::string& file, PoseCache* out);
// A mesh file: a CBSK where its first four bytes say `CBSK`, else a CBPC (whose parse names a wrong magic).
Status parse_mesh_pose_file(const uint8_t* data, size_t size, const std::string& file, PoseCache* out);
// Same for a CBTX file.
Status parse_texture_array(const uint8_t* data, size_t size, const std::string& file, TextureArray* out);

// Decode one layer of a BC1 or BC2 texture into RGBA8 (width * height * 4 bytes, rows top
// first); rgba8 is copied, rgba16 keeps the high byte and uv32 gives (u, v) to 8 bits, the
// material index and coverage 255/0, as rgba16 would. The CPU fallback for GL drivers
// without S3TC, and how tests look at block-compressed texels.
std::vector<uint8_t> decode_layer_rgba8(const TextureArray& texture, uint32_t layer);

// Region code of an alpha value: r = round(alpha / 17) (SPEC.md "Colour regions").
inline uint32_t region_code(uint8_t alpha) { return (alpha * 2u + 17u) / 34u; }

// ---------------------------------------------------------------------------------------
// Manifest

struct FileEntry {
    std::string path, sha256, media_type, role;
    uint64_t size = 0;
};

struct MaterialInfo {
    std::string name, diffuse;
    uint32_t variations = 0;
};

struct MeshInfo {
    std::string part, kind, file;
    uint32_t lod = 0, material = 0, vertex_count = 0, triangle_count = 0;
};

// A looping clip: pose frames [first_frame, first_frame + frames), played as a loop. The figures
// are its loop's (SPEC.md "Cycle"). A v1 manifest's `cycle` reads as one clip named "cycle".
struct ClipInfo {
    std::string name;
    uint32_t first_frame = 0, frames = 0;
    uint32_t source_start_frame = 0, source_end_frame = 0;  // the cache frames it was cut from
    std::string closing;
    double position_jump_ratio = 0, velocity_jump_ratio = 0;
};

// A transition, played once: from loop frame leave_frame of from_clip through pose frames
// [first_frame, first_frame + frames) to loop frame arrive_frame of to_clip (format version 2).
struct TransitionInfo {
    uint32_t from_clip = 0, to_clip = 0;          // indices into Manifest::clips, different
    uint32_t leave_frame = 0, arrive_frame = 0;  // loop frames of from_clip and to_clip
    uint32_t first_frame = 0, frames = 0;
    uint32_t source_start_frame = 0, source_end_frame = 0;
    double position_jump_ratio = 0, velocity_jump_ratio = 0;  // the worse of its two joins
};

// Most clips and transitions a v2 manifest may hold (SPEC.md, manifest.schema.json).
constexpr size_t kMaxClips = 64, kMaxTransitions = 256;

// The part of every impostor tile the atlas stores (SPEC.md "Impostor maps"), in tile texels: an atlas
// cell is width x height and holds tile texels [x, x + width) x [y, y + height).
struct ImpostorCrop {
    uint32_t x = 0, y = 0, width = 0, height = 0;
};

struct ImpostorInfo {
    uint32_t tile_size = 0;
    ImpostorCrop crop;  // the whole tile where the manifest has no crop
    std::vector<float> azimuths_deg, elevations_deg;
    std::vector<uint32_t> frame_indices;
    float center[3] = {0, 0, 0};
    float radius = 0;
    std::string normal_map, uv_map, detail_map;
    std::string surface_map;  // optional (SPEC.md "Impostor maps"): "" when the bundle has none
};

struct Manifest {
    uint32_t format_version = 0;
    std::string name, version, created, producer;
    double frames_per_second = 0;
    // Every CBPC holds pose_frames frames, tiled exactly by the clips, then the transitions, in order.
    uint32_t pose_frames = 0;
    std::vector<ClipInfo> clips;              // >= 1
    std::vector<TransitionInfo> transitions;  // none in a v1 bundle
    std::vector<MaterialInfo> materials;
    std::string outfits_file;
    uint32_t outfit_count = 0;
    std::vector<MeshInfo> meshes;
    ImpostorInfo impostor;
    std::vector<FileEntry> files;
};

// The newest manifest format_version read; every older one is read too (1 as one clip).
constexpr uint32_t kFormatVersion = 4;
// The first format_version whose body meshes may be skinned pose caches (SPEC.md "Version 4").
constexpr uint32_t kSkinnedFormatVersion = 4;

// Largest file size a manifest may declare: 2^53 - 1, the largest integer a double (and so every
// JSON reader, JavaScript's included) holds exactly; manifest.schema.json has the same maximum.
// A real bundle is tens of megabytes, and the cache budget refuses far less than this anyway.
constexpr uint64_t kMaxFileSize = (uint64_t(1) << 53) - 1;

// Parse manifest.json's text and check it against manifest.schema.json (the checks are
// written out in manifest.cpp; there is no schema engine), with the rules across fields of a v2
// manifest (ranges tile the pose frames, indices and loop frames in range, clip names unique).
// Returns manifest_invalid or unsupported_format_version. A v1 manifest comes out as one clip
// named "cycle" and no transitions. File paths are checked later, by load_bundle.
Status parse_manifest(const std::string& text, Manifest* out);

// The spec's path rule: relative, '/'-separated, [A-Za-z0-9._-] components, no '.' or '..'
// component, at most 200 characters, not "manifest.json".
bool is_safe_path(const std::string& path);

// ---------------------------------------------------------------------------------------
// Whole bundles

struct Bundle {
    Manifest manifest;
    std::vector<PoseCache> meshes;        // parallel to manifest.meshes
    std::vector<TextureArray> diffuse;    // parallel to manifest.materials
    TextureArray outfits;
    TextureArray impostor_normal, impostor_uv, impostor_detail;
    TextureArray impostor_surface;  // layer_count 0 when the bundle has no surface map
};

// Supplies the bytes of one listed file whose path already passed is_safe_path. Return
// missing_file when it is absent; the size and sha256 are checked by the caller.
using FileSource = std::function<Status(const FileEntry& entry, std::vector<uint8_t>* bytes)>;

// SHA-256 of `size` bytes as 64 lowercase hex digits (OpenSSL EVP).
std::string sha256_hex(const uint8_t* data, size_t size);

// Verify and decode a bundle as SPEC.md's "Verifying a bundle" says: the manifest, then each
// file entry in order (path rule, presence, size, sha256), then every binary file, then the
// cross-checks. Stops at the first problem. `out` is written only on success.
Status load_bundle(const std::string& manifest_text, const FileSource& source, Bundle* out);

// load_bundle over a folder holding manifest.json and the files it lists.
Status load_bundle_dir(const std::string& dir, Bundle* out);

// Reads a whole file; false when it cannot be opened or read.
bool read_file_bytes(const std::string& path, std::vector<uint8_t>* bytes);

}  // namespace crowdview
