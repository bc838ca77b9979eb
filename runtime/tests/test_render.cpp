// Headless rendering (EGL surfaceless; exit 77 = skipped where no OpenGL context exists):
//   1. a small crowd showing all three LODs against a committed reference image;
//   2. a mesh and its UV impostor at the 1:1 switch distance agree (SSIM);
//   3. the UV impostor follows texture variations that a detail-mapped impostor cannot;
//   4. the CPU block decoder renders what the S3TC upload renders;
//   5. the same bundle with its rgba16 UV map packed as uv32 renders the same impostors;
//   6. the instance upload puts every list's bytes in its buffer, samples made for a frame without;
//   7. frames built straight into mapped buffers hold the bytes of frames built into vectors, and
//      draw the same pixels.
// CROWDVIEW_UPDATE_REFERENCES=1 rewrites tests/data/crowd_reference.png (then inspect it).
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>

#include "check.h"
#include "crowd.h"
#include "gl_context.h"
#include "instance_upload.h"
#include "renderer.h"

#include <epoxy/gl.h>
#include "synthetic_bundle.h"

using namespace crowdview;
namespace fs = std::filesystem;

namespace {

// Reference image tolerances: llvmpipe is deterministic, other Mesa versions or GPUs round
// differently at edges, so a few stray pixels may differ a lot but the mean must stay close.
constexpr double kReferenceMeanAbsDiff = 2.0;      // 0..255 per channel, averaged over the image
constexpr double kReferenceOutlierFraction = 0.01;  // pixels off by more than 48 in some channel
constexpr int kReferenceOutlierLevel = 48;
// A mesh and its UV impostor at the switch distance, from a baked view and a baked frame:
// the same pixels up to the bake's resampling and BC1/BC2 compression (SSIM 1 = identical).
constexpr double kSwitchSsim = 0.80;
// Half way between baked views or frames, blending the neighbours must bring the impostor
// nearer the mesh than the nearest one alone by at least this much SSIM (averaged over six
// headings and variations; llvmpipe: 0.015 to 0.09); elsewhere it must not be worse by more
// than the slack (rounding at the silhouette).
constexpr double kBlendSsimGain = 0.005;
constexpr double kBlendSsimSlack = 0.002;
// uv32 against rgba16: the same coverage and materials, coordinates 14- rather than 16-bit
// (within 1/32 texel of a 1024² texture), so only the filtered diffuse lookups may move a little.
constexpr double kUv32MeanAbsDiff = 0.05;  // 0..255 per channel, averaged over the image (llvmpipe: 0.0000)
constexpr int kUv32MaxDiff = 4;            // any channel of any pixel (llvmpipe: 1)

struct Image {
    int width = 0, height = 0;
    std::vector<uint8_t> rgba;
};

// Mean SSIM (Wang et al. 2004) of luminance over 7x7 windows inside [x0, x1) x [y0, y1).
double ssim(const Image& a, const Image& b, int x0, int y0, int x1, int y1) {
    auto luma = [](const Image& im, int x, int y) {
        const uint8_t* p = &im.rgba[(size_t(y) * im.width + x) * 4];
        return 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2];
    };
    const double c1 = std::pow(0.01 * 255, 2), c2 = std::pow(0.03 * 255, 2);
    const int w = 7;
    double total = 0;
    int windows = 0;
    for (int y = std::max(y0, 0); y + w <= std::min(y1, a.height); ++y)
        for (int x = std::max(x0, 0); x + w <= std::min(x1, a.width); ++x) {
            double ma = 0, mb = 0, vaa = 0, vbb = 0, vab = 0;
            for (int j = 0; j < w; ++j)
                for (int i = 0; i < w; ++i) {
                    const double pa = luma(a, x + i, y + j), pb = luma(b, x + i, y + j);
                    ma += pa, mb += pb, vaa += pa * pa, vbb += pb * pb, vab += pa * pb;
                }
            const double n = w * w;
            ma /= n, mb /= n;
            vaa = vaa / n - ma * ma, vbb = vbb / n - mb * mb, vab = vab / n - ma * mb;
            total += ((2 * ma * mb + c1) * (2 * vab + c2)) / ((ma * ma + mb * mb + c1) * (vaa + vbb + c2));
            ++windows;
        }
    return windows ? total / windows : 0;
}

struct Scene {
    const Bundle* bundle;
    std::string shaders;
};

std::unique_ptr<Renderer> make_renderer(const Scene& scene, int w, int h, bool cpu_decode = false) {
    RendererDesc desc;
    desc.width = w, desc.height = h;
    desc.shader_dir = scene.shaders;
    desc.force_cpu_texture_decode = cpu_decode;
    std::string error;
    std::unique_ptr<Renderer> r = Renderer::create(*scene.bundle, desc, &error);
    CHECK_MSG(r != nullptr, error);
    return r;
}

Image render(Renderer& r, const Crowd& crowd, const Camera& camera, LodMode mode, ImpostorKind kind, float time_s,
             FrameInstances* frame_out = nullptr, ImpostorBlend blend = ImpostorBlend::full) {
    LodRule rule;
    rule.impostor_distance = impostor_switch_distance(camera.fov_y, float(r.height()), r.model().radius, r.model().tile_size);
    rule.has_low = r.model().has_low;
    FrameState state;
    FrameInstances frame;
    build_frame(crowd, r.model(), camera, r.aspect(), mode, rule, time_s, &state, &frame, blend);
    r.draw(frame, camera, kind, scene_light_dir());
    if (frame_out) *frame_out = frame;
    return Image{r.width(), r.height(), r.read_rgba()};
}

// The 30 characters (seed 5) of the reference crowd image.
Crowd reference_crowd() {
    CrowdDesc desc;
    desc.count = 30;
    desc.seed = 5;
    return make_crowd(desc, 2, 4, 1.0f);
}

void test_reference_crowd(const Scene& scene, const std::string& data_dir) {
    std::unique_ptr<Renderer> r = make_renderer(scene, 320, 240);
    if (!r) return;
    const Crowd crowd = reference_crowd();
    Camera camera;
    camera.position = glm::vec3(0.3f, 2.0f, 6.5f);
    camera.pitch = -0.17f;
    camera.far_m = 100;
    FrameInstances frame;
    // Blending off: the paper's impostors, which the reference image was made with.
    const Image image = render(*r, crowd, camera, LodMode::automatic, ImpostorKind::uv, 0.3f, &frame, ImpostorBlend::off);
    CHECK_MSG(!frame.by_lod[0].empty() && !frame.by_lod[1].empty() && !frame.by_lod[2].empty(),
              "the reference view shows all three LODs: " + std::to_string(frame.by_lod[0].size()) + " high, " +
                  std::to_string(frame.by_lod[1].size()) + " low, " + std::to_string(frame.by_lod[2].size()) + " impostor");
    // Image statistics that hold whatever the driver: characters cover part of the view.
    size_t sky = 0;
    for (size_t i = 0; i < image.rgba.size(); i += 4)
        sky += std::abs(image.rgba[i] - 158) <= 2 && std::abs(image.rgba[i + 1] - 179) <= 2 && std::abs(image.rgba[i + 2] - 199) <= 2;
    const double covered = 1.0 - double(sky) / (image.rgba.size() / 4);
    CHECK_MSG(covered > 0.05 && covered < 0.8, "covered fraction " + std::to_string(covered));

    const std::string reference = data_dir + "/crowd_reference.png";
    const char* update = std::getenv("CROWDVIEW_UPDATE_REFERENCES");
    if (update && std::string(update) == "1") {
        CHECK(write_png(reference, image.width, image.height, image.rgba));
        std::fprintf(stderr, "wrote %s\n", reference.c_str());
        return;
    }
    Image expected;
    if (!read_png(reference, &expected.width, &expected.height, &expected.rgba)) {
        CHECK_MSG(false, "missing " + reference + " (run with CROWDVIEW_UPDATE_REFERENCES=1)");
        return;
    }
    CHECK(expected.width == image.width && expected.height == image.height);
    if (expected.rgba.size() != image.rgba.size()) return;
    double sum = 0;
    size_t outliers = 0;
    for (size_t i = 0; i < image.rgba.size(); i += 4) {
        int worst = 0;
        for (int c = 0; c < 3; ++c) {
            const int d = std::abs(int(image.rgba[i + c]) - int(expected.rgba[i + c]));
            sum += d;
            worst = std::max(worst, d);
        }
        outliers += worst > kReferenceOutlierLevel;
    }
    const double pixels = double(image.rgba.size() / 4);
    const double mean = sum / (3 * pixels), outlier_fraction = outliers / pixels;
    std::fprintf(stderr, "reference image: mean abs diff %.3f, outliers %.4f\n", mean, outlier_fraction);
    CHECK(mean <= kReferenceMeanAbsDiff);
    CHECK(outlier_fraction <= kReferenceOutlierFraction);
    if (mean > kReferenceMeanAbsDiff || outlier_fraction > kReferenceOutlierFraction)
        write_png(fs::temp_directory_path().string() + "/crowd_reference_actual.png", image.width, image.height, image.rgba);
}

// One character at the origin seen from a baked view at the switch distance.
struct SwitchView {
    Image mesh, uv_impostor, detail_impostor;
    int x0, y0, x1, y1;  // the impostor quad on screen, plus a margin
};

SwitchView render_at_switch(Renderer& r, float heading_deg, float azimuth_deg, float elevation_deg, uint32_t variation,
                            uint32_t outfit, float time_s, ImpostorBlend blend = ImpostorBlend::full) {
    const CharacterModel& m = r.model();
    Crowd crowd;
    crowd.characters.push_back({glm::vec3(0), glm::radians(heading_deg), 0.0f, variation, outfit});
    const float fov = Camera().fov_y;
    const float d = impostor_switch_distance(fov, float(r.height()), m.radius, m.tile_size);
    const float world = glm::radians(azimuth_deg + heading_deg), el = glm::radians(elevation_deg);
    const glm::vec3 dir(std::sin(world) * std::cos(el), std::sin(el), std::cos(world) * std::cos(el));
    const Camera camera = look_at(m.center + dir * d, m.center);
    SwitchView v;
    v.mesh = render(r, crowd, camera, LodMode::high, ImpostorKind::uv, time_s);
    v.uv_impostor = render(r, crowd, camera, LodMode::impostor, ImpostorKind::uv, time_s, nullptr, blend);
    v.detail_impostor = render(r, crowd, camera, LodMode::impostor, ImpostorKind::detail, time_s, nullptr, blend);
    const int half = int(m.tile_size / 2) + 4;  // at 1:1 the quad is tile_size pixels across
    v.x0 = r.width() / 2 - half, v.x1 = r.width() / 2 + half;
    v.y0 = r.height() / 2 - half, v.y1 = r.height() / 2 + half;
    return v;
}

void test_switch_distance_fidelity(const Scene& scene) {
    std::unique_ptr<Renderer> r = make_renderer(scene, 256, 256);
    if (!r) return;
    const CharacterModel& m = r->model();
    const float baked_time = float(m.frame_indices[1]) / m.frames_per_second;  // a baked frame
    double worst = 1, detail_v0 = 0, uv_v1 = 0, detail_v1 = 0;
    int cases = 0, uv_wins = 0;
    for (float heading : {0.0f, 100.0f})
        for (size_t a = 0; a < m.azimuths_deg.size(); a += 3)
            for (size_t e = 0; e < m.elevations_deg.size(); ++e) {
                const uint32_t outfit = uint32_t(a / 3) % 4;
                for (uint32_t variation : {0u, 1u}) {
                    const SwitchView v = render_at_switch(*r, heading, m.azimuths_deg[a], m.elevations_deg[e], variation, outfit,
                                                          baked_time);
                    const double s_uv = ssim(v.mesh, v.uv_impostor, v.x0, v.y0, v.x1, v.y1);
                    const double s_detail = ssim(v.mesh, v.detail_impostor, v.x0, v.y0, v.x1, v.y1);
                    worst = std::min(worst, s_uv);
                    if (variation == 0) detail_v0 += s_detail;
                    else uv_v1 += s_uv, detail_v1 += s_detail, uv_wins += s_uv > s_detail;
                    cases += variation == 0;
                    CHECK_MSG(s_uv >= kSwitchSsim, "SSIM " + std::to_string(s_uv) + " at azimuth " +
                                                       std::to_string(m.azimuths_deg[a]) + ", elevation " +
                                                       std::to_string(m.elevations_deg[e]) + ", variation " + std::to_string(variation));
                }
            }
    detail_v0 /= cases, uv_v1 /= cases, detail_v1 /= cases;
    std::fprintf(stderr, "mesh vs UV impostor at the switch distance: worst SSIM %.3f over %d views\n", worst, 2 * cases);
    std::fprintf(stderr, "mean SSIM against the mesh: detail impostor %.3f (variation 0), %.3f (variation 1); UV impostor %.3f (variation 1)\n",
                 detail_v0, detail_v1, uv_v1);
    // The detail map holds variation 0 only (paper section 4): it matches a variation-0 mesh
    // and falls behind the UV impostor once the mesh wears another variation.
    CHECK(detail_v0 >= kSwitchSsim);
    CHECK(uv_v1 > detail_v1 + 0.02);
    CHECK_MSG(uv_wins == cases, "UV impostor nearer the variation-1 mesh in " + std::to_string(uv_wins) + " of " +
                                    std::to_string(cases) + " views");
    if (const char* dump = std::getenv("CROWDVIEW_DUMP_DIR")) {  // for looking at the pairs by eye
        const SwitchView v = render_at_switch(*r, 0, 30, 0, 1, 1, baked_time);
        write_png(std::string(dump) + "/switch_mesh.png", v.mesh.width, v.mesh.height, v.mesh.rgba);
        write_png(std::string(dump) + "/switch_uv.png", v.mesh.width, v.mesh.height, v.uv_impostor.rgba);
        write_png(std::string(dump) + "/switch_detail.png", v.mesh.width, v.mesh.height, v.detail_impostor.rgba);
    }

    // Between two baked views the paper shows the nearest one: still close, but less so.
    const SwitchView between = render_at_switch(*r, 0, 15, 15, 0, 0, baked_time, ImpostorBlend::off);
    const double s_between = ssim(between.mesh, between.uv_impostor, between.x0, between.y0, between.x1, between.y1);
    std::fprintf(stderr, "half way between baked views (azimuth 15, elevation 15): SSIM %.3f\n", s_between);
    CHECK(s_between > 0.5 && s_between < worst + 0.05);
}

// Half way between baked views (and frames), blending the neighbours beats the nearest one.
// Each case: the mesh against the impostor with blending off and with `blend`, at the switch
// distance, summed over several headings, variations and outfits.
void test_blending_between_views(const Scene& scene) {
    std::unique_ptr<Renderer> r = make_renderer(scene, 256, 256);
    if (!r) return;
    const CharacterModel& m = r->model();
    const float baked_time = float(m.frame_indices[1]) / m.frames_per_second;
    // Frame 1 of the 8-frame cycle lies half way between baked frames 0 and 2.
    const float between_frames = (float(m.frame_indices[0] + m.frame_indices[1]) * 0.5f) / m.frames_per_second;
    struct Case {
        const char* what;
        float azimuth, elevation, time_s;
        ImpostorBlend blend;
        bool half_way;  // an exact tie for the nearest choice: where blending must gain most
    };
    const Case cases[] = {
        {"views, half way in azimuth and elevation", 15, 15, baked_time, ImpostorBlend::views, true},
        {"views, half way in azimuth", 45, 0, baked_time, ImpostorBlend::views, true},
        {"views, a third of the way in azimuth", 100, 0, baked_time, ImpostorBlend::views, false},
        {"frames, half way between baked frames (at a baked view)", 60, 0, between_frames, ImpostorBlend::frames, true},
        {"full, between views and frames", 75, 10, between_frames, ImpostorBlend::full, true},
    };
    for (const Case& c : cases) {
        double nearest = 0, blended = 0, worst_gain = 1;
        int n = 0;
        for (float heading : {0.0f, 70.0f, 200.0f})
            for (uint32_t variation : {0u, 1u}) {
                const SwitchView off = render_at_switch(*r, heading, c.azimuth, c.elevation, variation, 1, c.time_s, ImpostorBlend::off);
                const SwitchView on = render_at_switch(*r, heading, c.azimuth, c.elevation, variation, 1, c.time_s, c.blend);
                const double s_off = ssim(off.mesh, off.uv_impostor, off.x0, off.y0, off.x1, off.y1);
                const double s_on = ssim(on.mesh, on.uv_impostor, on.x0, on.y0, on.x1, on.y1);
                nearest += s_off, blended += s_on, worst_gain = std::min(worst_gain, s_on - s_off), ++n;
            }
        nearest /= n, blended /= n;
        std::fprintf(stderr, "blending %s: mean SSIM against the mesh %.3f nearest, %.3f blended (worst gain %+.3f)\n", c.what,
                     nearest, blended, worst_gain);
        const std::string detail = std::string(c.what) + ": blended " + std::to_string(blended) + " vs nearest " + std::to_string(nearest);
        CHECK_MSG(blended >= nearest - kBlendSsimSlack, detail);
        if (c.half_way) CHECK_MSG(blended > nearest + kBlendSsimGain, detail);
        CHECK_MSG(blended >= kSwitchSsim - 0.1, c.what);
    }
    if (const char* dump = std::getenv("CROWDVIEW_DUMP_DIR")) {
        const SwitchView off = render_at_switch(*r, 0, 15, 15, 0, 1, baked_time, ImpostorBlend::off);
        const SwitchView on = render_at_switch(*r, 0, 15, 15, 0, 1, baked_time, ImpostorBlend::full);
        write_png(std::string(dump) + "/between_mesh.png", off.mesh.width, off.mesh.height, off.mesh.rgba);
        write_png(std::string(dump) + "/between_nearest.png", off.mesh.width, off.mesh.height, off.uv_impostor.rgba);
        write_png(std::string(dump) + "/between_blended.png", off.mesh.width, off.mesh.height, on.uv_impostor.rgba);
    }
}

void test_cpu_decode(const Scene& scene) {
    std::unique_ptr<Renderer> s3tc = make_renderer(scene, 200, 150);
    std::unique_ptr<Renderer> cpu = make_renderer(scene, 200, 150, true);
    if (!s3tc || !cpu) return;
    CHECK(!cpu->compressed_textures());
    const SwitchView a = render_at_switch(*s3tc, 30, 60, 0, 1, 2, 0.25f);
    const SwitchView b = render_at_switch(*cpu, 30, 60, 0, 1, 2, 0.25f);
    for (auto pair : {std::make_pair(&a.mesh, &b.mesh), std::make_pair(&a.uv_impostor, &b.uv_impostor),
                      std::make_pair(&a.detail_impostor, &b.detail_impostor)}) {
        double sum = 0;
        for (size_t i = 0; i < pair.first->rgba.size(); ++i) sum += std::abs(int(pair.first->rgba[i]) - int(pair.second->rgba[i]));
        const double mean = sum / pair.first->rgba.size();
        CHECK_MSG(mean < 1.0, "S3TC and CPU decode differ by " + std::to_string(mean) + " on average");
    }
}

// The synthetic bundle's rgba16 UV map as uv32 (SPEC.md pixel format 5), texel by texel.
TextureArray uv_map_as_uv32(const TextureArray& rgba16) {
    TextureArray out = rgba16;
    out.format = PixelFormat::uv32;
    const size_t texels = size_t(rgba16.width) * rgba16.height * rgba16.layer_count;
    out.data.assign(texels * 4, 0);
    for (size_t i = 0; i < texels; ++i) {
        uint16_t c[4];
        std::memcpy(c, rgba16.data.data() + 8 * i, 8);  // little-endian host
        const uint32_t word = pack_uv32(c[0] / 65535.0f, c[1] / 65535.0f, c[2], c[3] >= 32768);
        std::memcpy(out.data.data() + 4 * i, &word, 4);
    }
    return out;
}

void test_uv32_renders_like_rgba16(const Scene& scene) {
    CHECK(scene.bundle->impostor_uv.format == PixelFormat::rgba16);
    Bundle packed = *scene.bundle;
    packed.impostor_uv = uv_map_as_uv32(scene.bundle->impostor_uv);
    CHECK(packed.impostor_uv.data.size() * 2 == scene.bundle->impostor_uv.data.size());
    const Scene packed_scene{&packed, scene.shaders};
    std::unique_ptr<Renderer> wide = make_renderer(scene, 200, 150);
    std::unique_ptr<Renderer> narrow = make_renderer(packed_scene, 200, 150);
    if (!wide || !narrow) return;
    for (float azimuth : {60.0f, 200.0f}) {
        const SwitchView a = render_at_switch(*wide, 30, azimuth, 0, 1, 2, 0.25f);
        const SwitchView b = render_at_switch(*narrow, 30, azimuth, 0, 1, 2, 0.25f);
        for (auto pair : {std::make_pair(&a.uv_impostor, &b.uv_impostor), std::make_pair(&a.detail_impostor, &b.detail_impostor)}) {
            double sum = 0;
            int worst = 0;
            size_t lit = 0;
            for (size_t i = 0; i < pair.first->rgba.size(); ++i) {
                const int d = std::abs(int(pair.first->rgba[i]) - int(pair.second->rgba[i]));
                sum += d, worst = std::max(worst, d);
            }
            for (size_t i = 0; i < pair.first->rgba.size(); i += 4)  // not the sky: the impostor drew here
                lit += std::abs(pair.first->rgba[i] - 158) > 2 || std::abs(pair.first->rgba[i + 2] - 199) > 2;
            const double mean = sum / pair.first->rgba.size();
            std::fprintf(stderr, "uv32 vs rgba16 at azimuth %.0f: mean |diff| %.4f, max %d, %zu impostor pixels\n", azimuth, mean, worst, lit);
            CHECK_MSG(lit > 100, "the impostor is on screen");
            CHECK_MSG(mean < kUv32MeanAbsDiff && worst <= kUv32MaxDiff,
                      "uv32 and rgba16 differ by " + std::to_string(mean) + " on average, " + std::to_string(worst) + " at most");
        }
    }
}

// The renderer draws frames built into its own buffers (Renderer::instance_storage, as crowdview's
// loop does) exactly as frames built into vectors and uploaded: the same pixels, frame after frame,
// the meshes' counts and the impostors' samples from the buffers.
void test_drawn_from_mapped_buffers(const Scene& scene) {
    std::unique_ptr<Renderer> r = make_renderer(scene, 320, 240);
    if (!r) return;
    const Crowd crowd = reference_crowd();
    LodRule rule;
    rule.has_low = r->model().has_low;
    FrameState state_vectors, state_mapped;
    FrameInstances in_vectors, in_buffers;
    for (int frame = 0; frame < 2; ++frame) {
        Camera camera;
        camera.position = glm::vec3(0.3f, 2.0f, 6.5f + 3.0f * float(frame));  // then back: lists shrink and grow
        camera.pitch = -0.17f;
        camera.far_m = 100;
        rule.impostor_distance = impostor_switch_distance(camera.fov_y, float(r->height()), r->model().radius, r->model().tile_size);
        const float time_s = 0.3f + float(frame) * kFixedTimeStep;
        build_frame(crowd, r->model(), camera, r->aspect(), LodMode::automatic, rule, time_s, &state_vectors, &in_vectors, ImpostorBlend::full);
        r->draw(in_vectors, camera, ImpostorKind::uv, scene_light_dir());
        const std::vector<uint8_t> uploaded = r->read_rgba();
        build_frames({ArchetypeFrame{&crowd, &r->model(), &rule, &state_mapped, &in_buffers}}, camera, r->aspect(), LodMode::automatic,
                     time_s, ImpostorBlend::full, 2, r->instance_storage());
        r->draw(in_buffers, camera, ImpostorKind::uv, scene_light_dir());
        CHECK(in_buffers.in_storage && in_buffers.by_lod[2].empty() && in_buffers.shown[2] == in_vectors.by_lod[2].size());
        CHECK(in_vectors.by_lod[0].size() + in_vectors.by_lod[1].size() > 0 && !in_vectors.by_lod[2].empty());
        CHECK_MSG(r->read_rgba() == uploaded, "frame " + std::to_string(frame) + ": mapped and uploaded instances draw alike");
    }
}

// A GL buffer's first `bytes`, checked to be all it holds (`exact`) or at most.
std::vector<uint8_t> read_buffer(GLuint buffer, size_t bytes, bool exact = true) {
    std::vector<uint8_t> data(bytes);
    glBindBuffer(GL_ARRAY_BUFFER, buffer);
    GLint64 size = -1;
    glGetBufferParameteri64v(GL_ARRAY_BUFFER, GL_BUFFER_SIZE, &size);
    const bool fits = exact ? size == GLint64(bytes) : size >= GLint64(bytes);
    CHECK_MSG(fits, "buffer size " + std::to_string(size) + ", want " + std::to_string(bytes));
    if (fits && bytes) glGetBufferSubData(GL_ARRAY_BUFFER, 0, GLsizeiptr(bytes), data.data());
    return data;
}

// upload_instances: each buffer holds its list's bytes; a frame built without samples (sizes differ)
// gets one per impostor from its Instance, the nearest view and frame alone.
void test_instance_upload() {
    FrameInstances frame;
    for (uint16_t k = 0; k < 5; ++k) {
        const Instance inst{{float(k), 0.5f, -float(k)}, 0.25f * k, uint16_t(10 + k), k, uint16_t(2 * k), uint16_t(40 + k)};
        frame.by_lod[k % 3].push_back(inst);
    }
    InstanceBuffers buffers;
    glGenBuffers(3, buffers.by_lod);
    glGenBuffers(1, &buffers.impostor_samples);
    std::vector<ImpostorSamples> scratch;
    const auto read = [](GLuint buffer, size_t bytes) { return read_buffer(buffer, bytes); };
    const uint64_t bytes = upload_instances(frame, buffers, &scratch);
    CHECK(bytes == 5 * sizeof(Instance) + frame.by_lod[2].size() * sizeof(ImpostorSamples));
    for (int lod = 0; lod < 3; ++lod) {
        const std::vector<uint8_t> got = read(buffers.by_lod[lod], frame.by_lod[lod].size() * sizeof(Instance));
        CHECK(std::memcmp(got.data(), frame.by_lod[lod].data(), got.size()) == 0);
    }
    const std::vector<uint8_t> samples = read(buffers.impostor_samples, frame.by_lod[2].size() * sizeof(ImpostorSamples));
    for (size_t i = 0; i < frame.by_lod[2].size(); ++i) {
        ImpostorSamples s;
        std::memcpy(&s, samples.data() + i * sizeof s, sizeof s);
        const Instance& inst = frame.by_lod[2][i];
        CHECK(s.tiles[0] == inst.tile && s.tiles[3] == inst.tile && s.layers[0] == inst.frame && s.layers[1] == inst.frame);
        CHECK(s.view_weights[0] == 1.0f && s.view_weights[1] == 0.0f && s.frame_weight == 0.0f);
    }
    // With samples: uploaded as they are.
    frame.impostor_samples.assign(frame.by_lod[2].size(), ImpostorSamples{{7, 8, 9, 10}, {0.4f, 0.3f, 0.2f, 0.1f}, {3, 4}, 0.75f});
    upload_instances(frame, buffers, &scratch);
    const std::vector<uint8_t> given = read(buffers.impostor_samples, frame.impostor_samples.size() * sizeof(ImpostorSamples));
    CHECK(std::memcmp(given.data(), frame.impostor_samples.data(), given.size()) == 0);
    CHECK(glGetError() == GL_NO_ERROR);
    glDeleteBuffers(3, buffers.by_lod);
    glDeleteBuffers(1, &buffers.impostor_samples);
}

// MappedInstanceStorage: two archetypes (one several chunks long, one without views, whose samples
// the storage asks for all the same) built on 2 threads into mapped buffers, frame after frame, and
// into vectors, while the camera moves (lists grow and shrink): each buffer starts with the vector
// path's list, or upload_instances' samples made from it; the frames built into the buffers keep no
// lists of their own.
void test_mapped_instances() {
    std::vector<Crowd> crowds(2);
    std::vector<CharacterModel> models(2);
    for (size_t a = 0; a < 2; ++a) {
        const int count = a == 0 ? 5000 : 300;
        for (int i = 0; i < count; ++i)
            crowds[a].characters.push_back({glm::vec3(float(i % 20) - 10.0f, 0, -2.0f - float(i / 20) * 3.0f), 0.3f * float(i), 0.1f * float(a), uint32_t(i % 8), 0});
        models[a].center = glm::vec3(0, 0.9f, 0);
        models[a].radius = 1;
        models[a].frame_count = 24, models[a].frames_per_second = 24;
        models[a].frame_indices = {0, 6, 12, 18};
        models[a].has_low = true;
    }
    models[0].azimuths_deg = {0, 45, 90, 135, 180, 225, 270, 315}, models[0].elevations_deg = {0, 20, 40};
    LodRule rule;
    rule.impostor_distance = 12;
    std::vector<FrameState> state_vectors(2), state_mapped(2);
    std::vector<FrameInstances> in_vectors(2), in_buffers(2);
    std::vector<ArchetypeFrame> vector_builds, mapped_builds;
    for (size_t a = 0; a < 2; ++a) {
        vector_builds.push_back({&crowds[a], &models[a], &rule, &state_vectors[a], &in_vectors[a]});
        mapped_builds.push_back({&crowds[a], &models[a], &rule, &state_mapped[a], &in_buffers[a]});
    }
    MappedInstanceStorage storage;
    storage.buffers.resize(2);
    for (InstanceBuffers& b : storage.buffers) glGenBuffers(3, b.by_lod), glGenBuffers(1, &b.impostor_samples);
    InstanceBuffers copied;  // upload_instances' samples for the archetype without views
    glGenBuffers(3, copied.by_lod), glGenBuffers(1, &copied.impostor_samples);
    std::vector<ImpostorSamples> scratch;
    uint64_t impostors = 0, meshes = 0;
    for (int frame = 0; frame < 3; ++frame) {
        Camera camera;
        camera.position = glm::vec3(2.0f * float(frame), 3, 5 - 4.0f * float(frame));
        camera.far_m = 500;
        const float time_s = 0.7f + float(frame) * kFixedTimeStep;
        build_frames(vector_builds, camera, 1.5f, LodMode::automatic, time_s, ImpostorBlend::warp, 2);
        build_frames(mapped_builds, camera, 1.5f, LodMode::automatic, time_s, ImpostorBlend::warp, 2, &storage);
        for (size_t a = 0; a < 2; ++a) {
            const FrameInstances& want = in_vectors[a];
            const FrameInstances& got = in_buffers[a];
            CHECK(got.in_storage && !want.in_storage && got.culled == want.culled);
            for (int l = 0; l < 3; ++l) {
                CHECK(got.by_lod[l].empty() && got.shown[l] == want.by_lod[l].size() && want.shown[l] == want.by_lod[l].size());
                const std::vector<uint8_t> bytes = read_buffer(storage.buffers[a].by_lod[l], want.by_lod[l].size() * sizeof(Instance), false);
                CHECK_MSG(std::memcmp(bytes.data(), want.by_lod[l].data(), bytes.size()) == 0,
                          "archetype " + std::to_string(a) + " list " + std::to_string(l) + " frame " + std::to_string(frame));
            }
            const size_t quads = want.by_lod[int(Lod::impostor)].size();
            const std::vector<uint8_t> samples = read_buffer(storage.buffers[a].impostor_samples, quads * sizeof(ImpostorSamples), false);
            if (a == 0) {
                CHECK(want.impostor_samples.size() == quads);
                CHECK(std::memcmp(samples.data(), want.impostor_samples.data(), samples.size()) == 0);
            } else {
                CHECK(want.impostor_samples.empty());  // no views: the vector path leaves them to the upload
                upload_instances(want, copied, &scratch);
                CHECK(std::memcmp(samples.data(), read_buffer(copied.impostor_samples, samples.size()).data(), samples.size()) == 0);
            }
            impostors += quads, meshes += want.by_lod[0].size() + want.by_lod[1].size();
        }
    }
    CHECK(impostors > 100 && meshes > 100);  // the frames hold every kind
    CHECK(storage.failed_maps() == 0 && storage.lost_unmaps() == 0 && glGetError() == GL_NO_ERROR);
    for (InstanceBuffers* b : {&storage.buffers[0], &storage.buffers[1], &copied}) glDeleteBuffers(3, b->by_lod), glDeleteBuffers(1, &b->impostor_samples);
}

}  // namespace

int main() {
    std::string error;
    GlContextDesc desc;
    desc.width = 64, desc.height = 64;
    std::unique_ptr<GlContext> context = GlContext::create(desc, &error);
    if (!context) {
        std::fprintf(stderr, "SKIP: no OpenGL context here: %s\n", error.c_str());
        return 77;
    }
    std::fprintf(stderr, "%s\n", context->describe().c_str());
    test_instance_upload();
    test_mapped_instances();
    const std::string work = synthetic::temp_dir("render");
    error = synthetic::write_bundle(work + "/bundle");
    CHECK_MSG(error.empty(), error);
    Bundle bundle;
    const Status status = load_bundle_dir(work + "/bundle", &bundle);
    CHECK_MSG(status.ok(), status.message);
    if (status.ok()) {
        const Scene scene{&bundle, CROWDVIEW_SHADER_DIR};
        test_reference_crowd(scene, CROWDVIEW_TEST_DATA_DIR);
        test_drawn_from_mapped_buffers(scene);
        test_switch_distance_fidelity(scene);
        test_blending_between_views(scene);
        test_cpu_decode(scene);
        test_uv32_renders_like_rgba16(scene);
    }
    fs::remove_all(work);
    return check::exit_code();
}
