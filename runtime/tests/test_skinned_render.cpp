// Skinned bodies on the GPU (EGL surfaceless; exit 77 = skipped where no OpenGL context exists), from the
// shared vectors' v4 bundle (shared_formats/vectors/v4/good, its bodies CBSK, its cape a quantized CBPC):
//   1. it draws: a character at each mesh LOD covers pixels (in some view: the low body is one triangle), with no GL error;
//   2. mesh.vert.glsl's skinning (CV_SKINNED) draws what the CPU's does: the same bundle with each skinned
//      body replaced by a quantized cache of its CPU-skinned frames (decode_pose_position, decode_pose_normal)
//      renders the same pixels, at several frames and headings;
//   3. the archetype's GPU memory counts the skinned buffers' real bytes.
#include <algorithm>
#include <cmath>
#include <filesystem>

#include "check.h"
#include "crowd.h"
#include "gl_context.h"
#include "pose_codec.h"
#include "renderer.h"

#include <epoxy/gl.h>

#ifndef CROWDVIEW_VECTORS_DIR
#error "CMake sets CROWDVIEW_VECTORS_DIR to shared_formats/vectors"
#endif

using namespace crowdview;
namespace fs = std::filesystem;

namespace {

// Skinned and quantized renders differ by the quantization (a 16-bit step of a frame 2 m across: 0.03 mm)
// and float rounding: a few pixels at the silhouette, and shading by a level (llvmpipe: mean 0.0008, at
// most 1). Lighting the skinned bodies with their rest normals instead gives a mean of 0.6 to 2.
constexpr double kSameMeanAbsDiff = 0.1;        // 0..255 per channel, averaged over the pixels either covers
constexpr int kSameOutlierLevel = 4;            // a pixel off by more than this in some channel is an outlier
constexpr double kSameOutlierFraction = 0.005;  // of the pixels either covers

// A version-2 cache holding `skinned`'s frames as the CPU skins them: what the bake would have written.
PoseCache quantized_copy(const PoseCache& skinned) {
    PoseCache q = skinned;
    q.version = kQuantizedPoseCacheVersion;
    q.skin = PoseSkin();
    const size_t vertices = skinned.vertex_count;
    q.frame_bounds.assign(size_t(skinned.frame_count) * 6, 0.0f);
    q.position_codes.assign(skinned.frame_count * vertices * 3, 0);
    q.normal_codes.assign(skinned.frame_count * vertices * 2, 0);
    for (uint32_t f = 0; f < skinned.frame_count; ++f) {
        std::vector<float> positions(vertices * 3);
        for (uint32_t v = 0; v < vertices; ++v) {
            decode_pose_position(skinned, f, v, &positions[v * 3]);
            float normal[3];
            decode_pose_normal(skinned, f, v, normal);
            encode_octahedral(normal, &q.normal_codes[(f * vertices + v) * 2]);
        }
        float* bounds = &q.frame_bounds[size_t(f) * 6];
        for (int axis = 0; axis < 3; ++axis) {
            bounds[axis] = bounds[3 + axis] = positions[axis];
            for (size_t v = 0; v < vertices; ++v)
                bounds[axis] = std::min(bounds[axis], positions[v * 3 + axis]), bounds[3 + axis] = std::max(bounds[3 + axis], positions[v * 3 + axis]);
            const double extent = double(bounds[3 + axis]) - bounds[axis];
            for (size_t v = 0; v < vertices; ++v)
                q.position_codes[(f * vertices + v) * 3 + axis] =
                    extent > 0 ? uint16_t(std::lround((positions[v * 3 + axis] - double(bounds[axis])) / extent * kPoseCodeMax)) : 0;
        }
    }
    return q;
}

std::unique_ptr<Renderer> make_renderer(const Bundle& bundle) {
    RendererDesc desc;
    desc.width = 160, desc.height = 160;
    desc.shader_dir = CROWDVIEW_SHADER_DIR;
    std::string error;
    std::unique_ptr<Renderer> r = Renderer::create(bundle, desc, &error);
    CHECK_MSG(r != nullptr, error);
    return r;
}

// One character at the origin with `heading`, at pose `time_s`, at mesh level `mode`, seen from 2.5 m.
std::vector<uint8_t> render_one(Renderer& r, LodMode mode, float heading, float time_s) {
    Crowd crowd;
    crowd.characters.push_back({glm::vec3(0), heading, 0.0f, 0, 0});
    const Camera camera = look_at(r.model().center + glm::vec3(0.6f, 0.4f, 2.5f), r.model().center);
    LodRule rule;
    rule.impostor_distance = 1e6f;
    rule.has_low = r.model().has_low;
    FrameState state;
    FrameInstances frame;
    build_frame(crowd, r.model(), camera, r.aspect(), mode, rule, time_s, &state, &frame);
    r.draw(frame, camera, ImpostorKind::uv, scene_light_dir());
    return r.read_rgba();
}

// Pixels that differ from the top-left one (the sky).
size_t covered_pixels(const std::vector<uint8_t>& rgba) {
    size_t covered = 0;
    for (size_t i = 0; i < rgba.size(); i += 4) covered += !std::equal(&rgba[i], &rgba[i] + 3, &rgba[0]);
    return covered;
}

struct Difference {
    size_t covered = 0;   // pixels either image covers (not the sky)
    double mean = 0;      // absolute difference per channel, averaged over those
    size_t outliers = 0;  // of those, off by more than kSameOutlierLevel in some channel
};

Difference difference_where_covered(const std::vector<uint8_t>& a, const std::vector<uint8_t>& b) {
    Difference d;
    double total = 0;
    for (size_t i = 0; i < a.size(); i += 4) {
        if (std::equal(&a[i], &a[i] + 3, &a[0]) && std::equal(&b[i], &b[i] + 3, &b[0])) continue;
        ++d.covered;
        int worst = 0;
        for (int c = 0; c < 3; ++c) worst = std::max(worst, std::abs(int(a[i + c]) - int(b[i + c]))), total += std::abs(int(a[i + c]) - int(b[i + c]));
        d.outliers += worst > kSameOutlierLevel;
    }
    d.mean = d.covered ? total / (3.0 * double(d.covered)) : 0;
    return d;
}

// Each body LOD of the skinned bundle draws, and draws as its CPU-skinned quantized copy does.
void test_skinned_draws_as_cpu(const Bundle& skinned) {
    Bundle quantized = skinned;
    for (PoseCache& cache : quantized.meshes)
        if (cache.skinned()) cache = quantized_copy(cache);
    std::unique_ptr<Renderer> gpu = make_renderer(skinned), cpu = make_renderer(quantized);
    if (!gpu || !cpu) return;
    const float seconds = float(skinned.manifest.pose_frames / skinned.manifest.frames_per_second);
    for (LodMode mode : {LodMode::high, LodMode::low}) {
        size_t most_covered = 0;  // the vectors' low body is one triangle: culled where it faces away
        for (int k = 0; k < 4; ++k) {
            const float heading = 1.3f * float(k), time_s = seconds * float(k) / 4.0f;
            const std::vector<uint8_t> a = render_one(*gpu, mode, heading, time_s), b = render_one(*cpu, mode, heading, time_s);
            const std::string where = std::string(mode == LodMode::high ? "high" : "low") + " mesh, view " + std::to_string(k);
            most_covered = std::max(most_covered, covered_pixels(a));
            const Difference d = difference_where_covered(a, b);
            CHECK_MSG(d.mean <= kSameMeanAbsDiff && double(d.outliers) <= kSameOutlierFraction * double(d.covered),
                      where + ": skinned on the GPU differs from the CPU's frames by " + std::to_string(d.mean) + " on average, " +
                          std::to_string(d.outliers) + " of " + std::to_string(d.covered) + " pixels far off");
        }
        CHECK_MSG(most_covered > 200, std::string(mode == LodMode::high ? "high" : "low") + " mesh: the skinned character covers at most " +
                                          std::to_string(most_covered) + " pixels");
    }
    CHECK(glGetError() == GL_NO_ERROR);
}

// The bodies' share of GPU memory: UVs, indices, rest positions and normals (12 bytes a vertex each), joints
// and weights (8 each) and the matrices (48 bytes a joint a frame), for mesh LODs 0 and 1.
void test_skinned_memory(const Bundle& bundle) {
    std::unique_ptr<Renderer> r = make_renderer(bundle);
    if (!r) return;
    uint64_t bodies = 0;
    for (size_t i = 0; i < bundle.meshes.size(); ++i) {
        const PoseCache& cache = bundle.meshes[i];
        if (bundle.manifest.meshes[i].kind != "body" || bundle.manifest.meshes[i].lod > 1) continue;
        CHECK(cache.skinned());
        bodies += 8 * uint64_t(cache.vertex_count) + 4 * uint64_t(cache.index_count) + 40 * uint64_t(cache.vertex_count) +
                  48 * uint64_t(cache.frame_count) * cache.skin.joint_count;
    }
    CHECK_MSG(r->memory(0).bodies == bodies,
              "bodies take " + std::to_string(r->memory(0).bodies) + " bytes on the GPU, their buffers hold " + std::to_string(bodies));
}

}  // namespace

int main() {
    const fs::path good = fs::path(CROWDVIEW_VECTORS_DIR) / "v4" / "good" / "bundle";
    Bundle bundle;
    const Status status = load_bundle_dir(good.string(), &bundle);
    CHECK_MSG(status.ok(), status.message);
    if (!status.ok()) return check::exit_code();
    std::string error;
    GlContextDesc desc;
    desc.width = 64, desc.height = 64;
    std::unique_ptr<GlContext> context = GlContext::create(desc, &error);
    if (!context) {
        std::fprintf(stderr, "SKIP: no OpenGL context here: %s\n", error.c_str());
        return 77;
    }
    std::fprintf(stderr, "%s\n", context->describe().c_str());
    test_skinned_draws_as_cpu(bundle);
    test_skinned_memory(bundle);
    return check::exit_code();
}
