// A synthetic crowdbake bundle written from C++: a walking figure in a skirt, with impostor
// maps baked by a small CPU rasterizer that follows SPEC.md's view convention on its own
// (not through the renderer it is used to test).
#include "synthetic_bundle.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>

#include <glm/glm.hpp>
#include <glm/gtc/matrix_transform.hpp>
#include <nlohmann/json.hpp>

#define STB_DXT_IMPLEMENTATION
#include <stb/stb_dxt.h>

#include <sys/wait.h>
#include <unistd.h>

#include "bundle.h"

namespace fs = std::filesystem;

namespace synthetic {

namespace {

void put_u32(std::vector<uint8_t>* out, uint32_t v) {
    for (int i = 0; i < 4; ++i) out->push_back(uint8_t(v >> (8 * i)));
}
void put_f32(std::vector<uint8_t>* out, float f) {
    uint32_t v;
    std::memcpy(&v, &f, 4);
    put_u32(out, v);
}

}  // namespace

std::vector<uint8_t> encode_pose_cache(const std::vector<uint32_t>& indices, const std::vector<float>& uvs,
                                       const std::vector<float>& positions, const std::vector<float>& normals,
                                       uint32_t frame_count, float frames_per_second) {
    const uint32_t vertex_count = uint32_t(uvs.size() / 2);
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t i = 0; i < positions.size(); ++i) {
        lo[i % 3] = std::min(lo[i % 3], positions[i]);
        hi[i % 3] = std::max(hi[i % 3], positions[i]);
    }
    std::vector<uint8_t> out;
    out.insert(out.end(), {'C', 'B', 'P', 'C'});
    put_u32(&out, 1);
    put_u32(&out, 64);
    put_u32(&out, uint32_t(64 + 4 * indices.size() + 8 * size_t(vertex_count) + 24 * size_t(vertex_count) * frame_count));
    put_u32(&out, vertex_count);
    put_u32(&out, uint32_t(indices.size()));
    put_u32(&out, frame_count);
    put_u32(&out, 0);
    put_f32(&out, frames_per_second);
    for (float v : lo) put_f32(&out, v);
    for (float v : hi) put_f32(&out, v);
    put_u32(&out, 0);
    for (uint32_t i : indices) put_u32(&out, i);
    for (float v : uvs) put_f32(&out, v);
    for (float v : positions) put_f32(&out, v);
    for (float v : normals) put_f32(&out, v);
    return out;
}

std::vector<uint8_t> encode_texture_array(uint32_t width, uint32_t height, uint32_t layer_count, uint32_t pixel_format,
                                          const std::vector<uint8_t>& layers) {
    std::vector<uint8_t> out;
    out.insert(out.end(), {'C', 'B', 'T', 'X'});
    put_u32(&out, 1);
    put_u32(&out, 32);
    put_u32(&out, uint32_t(32 + layers.size()));
    put_u32(&out, width);
    put_u32(&out, height);
    put_u32(&out, layer_count);
    put_u32(&out, pixel_format);
    out.insert(out.end(), layers.begin(), layers.end());
    return out;
}

std::vector<uint8_t> compress_bc(const std::vector<uint8_t>& rgba, uint32_t width, uint32_t height, bool bc2) {
    std::vector<uint8_t> out;
    for (uint32_t by = 0; by < height / 4; ++by)
        for (uint32_t bx = 0; bx < width / 4; ++bx) {
            unsigned char block[64];
            for (int i = 0; i < 16; ++i)
                std::memcpy(block + 4 * i, &rgba[((size_t(by) * 4 + i / 4) * width + bx * 4 + i % 4) * 4], 4);
            if (bc2) {
                for (int i = 0; i < 16; i += 2)  // explicit 4-bit alpha, low nibble first
                    out.push_back(uint8_t((block[4 * i + 3] >> 4) | (block[4 * (i + 1) + 3] & 0xF0)));
            }
            unsigned char colour[8];
            stb_compress_dxt_block(colour, block, 0, STB_DXT_HIGHQUAL);
            out.insert(out.end(), colour, colour + 8);
        }
    return out;
}

std::string read_text(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

Run run_crowdview(const std::string& crowdview, const std::string& args) {
    // One stderr file per process: the render tests may run side by side (ctest -j).
    const std::string err_file = (fs::temp_directory_path() / ("crowdview-stderr-" + std::to_string(getpid()) + ".txt")).string();
    const std::string command = "'" + crowdview + "' " + args + " 2>'" + err_file + "'";
    Run run;
    FILE* pipe = popen(command.c_str(), "r");
    if (!pipe) return run;
    char buffer[4096];
    size_t n;
    while ((n = fread(buffer, 1, sizeof buffer, pipe)) > 0) run.out.append(buffer, n);
    const int raw = pclose(pipe);
    run.status = WIFEXITED(raw) ? WEXITSTATUS(raw) : -1;
    run.err = read_text(err_file);
    fs::remove(err_file);
    return run;
}

bool write_bytes(const std::string& path, const std::vector<uint8_t>& bytes) {
    std::error_code ec;
    fs::create_directories(fs::path(path).parent_path(), ec);
    std::ofstream out(path, std::ios::binary);
    out.write(reinterpret_cast<const char*>(bytes.data()), std::streamsize(bytes.size()));
    return bool(out);
}

bool copy_tree(const std::string& from, const std::string& to) {
    std::error_code ec;
    fs::copy(from, to, fs::copy_options::recursive, ec);
    return !ec;
}

std::string temp_dir(const std::string& tag) {
    static std::mt19937_64 rng(std::random_device{}());
    const fs::path dir = fs::temp_directory_path() / ("crowdview-" + tag + "-" + std::to_string(rng() % 1000000000));
    fs::remove_all(dir);
    fs::create_directories(dir);
    return dir.string();
}

// ---------------------------------------------------------------------------------------
// The figure

namespace {

struct Mesh {
    std::vector<uint32_t> indices;
    std::vector<float> uvs;
    std::vector<float> positions;  // frames * vertices * 3
    std::vector<float> normals;
    uint32_t vertex_count = 0;
};

// A closed ellipsoid or an open surface of revolution, placed per frame by a rigid transform.
struct Primitive {
    enum Kind { ellipsoid, cone } kind;
    glm::vec3 center;       // ellipsoid centre; cone: top centre
    glm::vec3 semi_axes;    // ellipsoid; cone uses x = top radius, y = height, z = bottom radius
    glm::vec4 uv_rect;      // u0, v0, u1, v1 in the material's texture
    std::function<glm::mat4(float phase, float amplitude)> pose;  // model transform at walk phase (radians) and stride
    float sway = 0;         // cone: hem offset along +Z times amplitude * sin(phase), the skirt's lag
};

// Position and outward unit normal at (u around, v from top) in 0..1, before the pose.
// One pose frame of the walk: its phase (radians) and stride (1: the full walk; smaller: an idle sway).
struct Motion {
    float phase = 0, amplitude = 1;
};

void surface(const Primitive& p, float u, float v, float phase, float amplitude, glm::vec3* position, glm::vec3* normal) {
    const float theta = 2.0f * glm::pi<float>() * u + glm::pi<float>();  // seam at the back, u = 0.5 faces +Z
    if (p.kind == Primitive::ellipsoid) {
        const float polar = glm::pi<float>() * glm::clamp(v, 1e-3f, 1.0f - 1e-3f);
        const glm::vec3 unit(std::sin(polar) * std::sin(theta), std::cos(polar), std::sin(polar) * std::cos(theta));
        *position = p.center + unit * p.semi_axes;
        *normal = glm::normalize(unit / p.semi_axes);  // gradient of the implicit ellipsoid
    } else {
        const float r_top = p.semi_axes.x, height = p.semi_axes.y, r_bottom = p.semi_axes.z;
        const float r = r_top + (r_bottom - r_top) * v;
        *position = p.center + glm::vec3(r * std::sin(theta), -height * v, r * std::cos(theta));
        position->z += p.sway * v * std::sin(phase) * amplitude;
        const float slope = (r_bottom - r_top) / height;  // radius growth per metre down
        *normal = glm::normalize(glm::vec3(std::sin(theta), slope, std::cos(theta)));
    }
}

// Adds a (segments x rings) grid of `p` to `mesh` for every frame, counter-clockwise outside.
void add_primitive(Mesh* mesh, const Primitive& p, uint32_t segments, uint32_t rings, const std::vector<Motion>& motions,
                   std::vector<std::vector<float>>* frame_positions, std::vector<std::vector<float>>* frame_normals) {
    const uint32_t base = mesh->vertex_count;
    for (uint32_t j = 0; j <= rings; ++j)
        for (uint32_t i = 0; i <= segments; ++i) {
            const float u = float(i) / segments, v = float(j) / rings;
            mesh->uvs.push_back(p.uv_rect.x + u * (p.uv_rect.z - p.uv_rect.x));
            mesh->uvs.push_back(p.uv_rect.y + v * (p.uv_rect.w - p.uv_rect.y));
            for (uint32_t f = 0; f < motions.size(); ++f) {
                glm::vec3 position, normal;
                surface(p, u, v, motions[f].phase, motions[f].amplitude, &position, &normal);
                const glm::mat4 m = p.pose(motions[f].phase, motions[f].amplitude);
                const glm::vec3 world = glm::vec3(m * glm::vec4(position, 1.0f));
                const glm::vec3 n = glm::normalize(glm::mat3(m) * normal);
                for (int k = 0; k < 3; ++k) {
                    (*frame_positions)[f].push_back(world[k]);
                    (*frame_normals)[f].push_back(n[k]);
                }
            }
        }
    mesh->vertex_count += (segments + 1) * (rings + 1);
    const std::vector<float>& pos = (*frame_positions)[0];
    const std::vector<float>& nor = (*frame_normals)[0];
    auto vec = [](const std::vector<float>& a, uint32_t i) { return glm::vec3(a[3 * i], a[3 * i + 1], a[3 * i + 2]); };
    for (uint32_t j = 0; j < rings; ++j)
        for (uint32_t i = 0; i < segments; ++i) {
            const uint32_t a = base + j * (segments + 1) + i, b = a + 1, c = a + segments + 1, d = c + 1;
            for (glm::uvec3 t : {glm::uvec3(a, c, b), glm::uvec3(b, c, d)}) {
                // Wind counter-clockwise as seen from outside (SPEC.md: CCW front faces).
                const glm::vec3 face = glm::cross(vec(pos, t.y) - vec(pos, t.x), vec(pos, t.z) - vec(pos, t.x));
                const glm::vec3 outward = vec(nor, t.x) + vec(nor, t.y) + vec(nor, t.z);
                if (glm::dot(face, outward) < 0) std::swap(t.y, t.z);
                mesh->indices.insert(mesh->indices.end(), {t.x, t.y, t.z});
            }
        }
}

Mesh build_part(const std::vector<Primitive>& primitives, uint32_t segments, uint32_t rings, const std::vector<Motion>& motions) {
    Mesh mesh;
    const uint32_t frames = uint32_t(motions.size());
    std::vector<std::vector<float>> positions(frames), normals(frames);
    for (const Primitive& p : primitives) add_primitive(&mesh, p, segments, rings, motions, &positions, &normals);
    for (uint32_t f = 0; f < frames; ++f) {
        mesh.positions.insert(mesh.positions.end(), positions[f].begin(), positions[f].end());
        mesh.normals.insert(mesh.normals.end(), normals[f].begin(), normals[f].end());
    }
    return mesh;
}

glm::mat4 swing(glm::vec3 pivot, float angle) {
    return glm::translate(glm::mat4(1), pivot) * glm::rotate(glm::mat4(1), angle, glm::vec3(1, 0, 0)) *
           glm::translate(glm::mat4(1), -pivot);
}

std::vector<Primitive> body_primitives() {
    auto bob = [](float phase, float amplitude) {
        return glm::translate(glm::mat4(1), glm::vec3(0, 0.015f * std::cos(2 * phase) * amplitude, 0));
    };
    std::vector<Primitive> body = {
        {Primitive::ellipsoid, {0, 1.2f, 0}, {0.19f, 0.30f, 0.12f}, {0.02f, 0.02f, 0.48f, 0.48f}, bob},   // torso: shirt
        {Primitive::ellipsoid, {0, 1.63f, 0.01f}, {0.10f, 0.12f, 0.11f}, {0.52f, 0.02f, 0.98f, 0.48f}, bob},  // head: skin
    };
    for (float side : {1.0f, -1.0f}) {
        // Legs swing 0.45 rad about the hips, arms 0.35 rad the other way: a walk on the spot.
        body.push_back({Primitive::ellipsoid, {0.09f * side, 0.47f, 0}, {0.075f, 0.46f, 0.08f}, {0.02f, 0.52f, 0.48f, 0.98f},
                        [side](float phase, float amplitude) { return swing({0.09f * side, 0.93f, 0}, 0.45f * side * std::sin(phase) * amplitude); }});
        body.push_back({Primitive::ellipsoid, {0.24f * side, 1.14f, 0}, {0.05f, 0.29f, 0.055f}, {0.52f, 0.52f, 0.98f, 0.98f},
                        [side](float phase, float amplitude) { return swing({0.24f * side, 1.42f, 0}, -0.35f * side * std::sin(phase) * amplitude); }});
    }
    return body;
}

std::vector<Primitive> skirt_primitives() {
    Primitive skirt{Primitive::cone, {0, 1.02f, 0}, {0.2f, 0.42f, 0.36f}, {0.0f, 0.0f, 1.0f, 1.0f},
                    [](float, float) { return glm::mat4(1); }};
    skirt.sway = 0.06f;  // the hem lags the walk: pre-simulated cloth in miniature
    return {skirt};
}

// RGBA8 textures; alpha = 17 * region. Body: shirt (1), skin (0), trousers (2), sleeves (1).
std::vector<uint8_t> body_texture(uint32_t size, uint32_t variation) {
    std::vector<uint8_t> rgba(size * size * 4);
    for (uint32_t y = 0; y < size; ++y)
        for (uint32_t x = 0; x < size; ++x) {
            const bool right = x >= size / 2, bottom = y >= size / 2;
            uint8_t* t = &rgba[(y * size + x) * 4];
            uint32_t region;
            int r, g, b;
            if (!right && !bottom) {  // shirt: stripes or checks, light so the outfit colour shows
                region = 1;
                const bool mark = variation == 0 ? (y / 4) % 2 : ((x / 4) + (y / 4)) % 2;
                r = g = b = mark ? 250 : 180;
            } else if (right && !bottom) {  // head: skin with eyes on the front (u 0.5 of the head)
                region = 0;
                const int skin[2][3] = {{224, 172, 140}, {150, 105, 80}};
                r = skin[variation % 2][0], g = skin[variation % 2][1], b = skin[variation % 2][2];
                const int u = int(x) - int(size * 3 / 4), v = int(y) - int(size / 4);
                if ((std::abs(u - 2) <= 1 || std::abs(u + 2) <= 1) && std::abs(v + 1) <= 1) r = g = b = 30;
            } else if (!right && bottom) {  // trousers
                region = 2;
                r = g = b = variation == 0 ? 220 : ((x / 3) % 2 ? 235 : 160);
            } else {  // sleeves
                region = 1;
                r = g = b = variation == 0 ? 230 : 200;
            }
            t[0] = uint8_t(r), t[1] = uint8_t(g), t[2] = uint8_t(b), t[3] = uint8_t(17 * region);
        }
    return rgba;
}

std::vector<uint8_t> skirt_texture(uint32_t size, uint32_t variation) {
    std::vector<uint8_t> rgba(size * size * 4);
    for (uint32_t y = 0; y < size; ++y)
        for (uint32_t x = 0; x < size; ++x) {
            uint8_t* t = &rgba[(y * size + x) * 4];
            const bool mark = variation == 0 ? ((x + y) / 3) % 2 : ((x % 8 < 3) && (y % 8 < 3));
            t[0] = t[1] = t[2] = mark ? 120 : 245;
            t[3] = 17 * 3;  // region 3
        }
    return rgba;
}

// Outfit map rows: colours for regions 1 (shirt), 2 (trousers), 3 (skirt); others white.
std::vector<uint8_t> outfit_map(uint32_t count) {
    const uint8_t colours[4][3][3] = {
        {{200, 40, 40}, {40, 50, 110}, {120, 50, 150}},
        {{40, 90, 200}, {110, 80, 50}, {230, 140, 30}},
        {{40, 160, 70}, {40, 40, 40}, {30, 150, 150}},
        {{230, 200, 40}, {170, 160, 110}, {230, 110, 160}},
    };
    std::vector<uint8_t> rgba(16 * count * 4, 255);
    for (uint32_t o = 0; o < count; ++o)
        for (int r = 1; r <= 3; ++r)
            for (int c = 0; c < 3; ++c) rgba[(o * 16 + r) * 4 + c] = colours[o % 4][r - 1][c];
    return rgba;
}

// ---------------------------------------------------------------------------------------
// The impostor bake: orthographic views per SPEC.md "Impostor maps", rasterised on the CPU.

struct BakeTexel {
    float depth = -INFINITY;  // towards the camera; larger is nearer
    glm::vec3 normal{0};
    glm::vec2 uv{0};
    uint32_t material = 0;
    bool covered = false;
};

struct BakePart {
    const Mesh* mesh;
    uint32_t material;
};

void bake_view(const std::vector<BakePart>& parts, uint32_t frame, glm::vec3 center, float radius, float azimuth_deg,
               float elevation_deg, uint32_t tile, std::vector<BakeTexel>* texels) {
    const float az = glm::radians(azimuth_deg), el = glm::radians(elevation_deg);
    const glm::vec3 to_camera(std::sin(az) * std::cos(el), std::sin(el), std::cos(az) * std::cos(el));
    glm::vec3 right = glm::cross(glm::vec3(0, 1, 0), to_camera);
    right = glm::length(right) > 1e-6f ? glm::normalize(right) : glm::vec3(1, 0, 0);
    const glm::vec3 up = glm::cross(to_camera, right);
    texels->assign(size_t(tile) * tile, BakeTexel());
    for (const BakePart& part : parts) {
        const Mesh& m = *part.mesh;
        const float* positions = &m.positions[size_t(frame) * m.vertex_count * 3];
        const float* normals = &m.normals[size_t(frame) * m.vertex_count * 3];
        for (size_t t = 0; t < m.indices.size(); t += 3) {
            glm::vec3 screen[3];
            for (int k = 0; k < 3; ++k) {
                const uint32_t i = m.indices[t + k];
                const glm::vec3 d = glm::vec3(positions[3 * i], positions[3 * i + 1], positions[3 * i + 2]) - center;
                // Texel space: x right, y down (rows top first), tile texels across 2 * radius.
                screen[k] = glm::vec3((glm::dot(d, right) / radius + 1.0f) * 0.5f * tile,
                                      (1.0f - glm::dot(d, up) / radius) * 0.5f * tile, glm::dot(d, to_camera));
            }
            const float area = (screen[1].x - screen[0].x) * (screen[2].y - screen[0].y) -
                               (screen[2].x - screen[0].x) * (screen[1].y - screen[0].y);
            if (std::fabs(area) < 1e-12f) continue;
            const int x0 = std::max(0, int(std::floor(std::min({screen[0].x, screen[1].x, screen[2].x}))));
            const int x1 = std::min(int(tile) - 1, int(std::ceil(std::max({screen[0].x, screen[1].x, screen[2].x}))));
            const int y0 = std::max(0, int(std::floor(std::min({screen[0].y, screen[1].y, screen[2].y}))));
            const int y1 = std::min(int(tile) - 1, int(std::ceil(std::max({screen[0].y, screen[1].y, screen[2].y}))));
            for (int y = y0; y <= y1; ++y)
                for (int x = x0; x <= x1; ++x) {
                    const float px = float(x) + 0.5f, py = float(y) + 0.5f;
                    float w[3];
                    for (int k = 0; k < 3; ++k) {
                        const glm::vec3& a = screen[(k + 1) % 3];
                        const glm::vec3& b = screen[(k + 2) % 3];
                        w[k] = ((b.x - a.x) * (py - a.y) - (px - a.x) * (b.y - a.y)) / area;
                    }
                    if (w[0] < 0 || w[1] < 0 || w[2] < 0) continue;  // both windings are drawn: no culling
                    const float depth = w[0] * screen[0].z + w[1] * screen[1].z + w[2] * screen[2].z;
                    BakeTexel& texel = (*texels)[size_t(y) * tile + x];
                    if (depth <= texel.depth) continue;
                    texel.depth = depth;
                    texel.covered = true;
                    texel.material = part.material;
                    texel.normal = glm::vec3(0);
                    texel.uv = glm::vec2(0);
                    for (int k = 0; k < 3; ++k) {
                        const uint32_t i = m.indices[t + k];
                        texel.normal += w[k] * glm::vec3(normals[3 * i], normals[3 * i + 1], normals[3 * i + 2]);
                        texel.uv += w[k] * glm::vec2(m.uvs[2 * i], m.uvs[2 * i + 1]);
                    }
                    texel.normal = glm::normalize(texel.normal);
                    // Seen from behind (a garment's inside), the surface faces the other way.
                    if (glm::dot(texel.normal, to_camera) < 0 && part.material == 1) texel.normal = -texel.normal;
                }
        }
    }
}

// Every pose frame's phase and stride: one cycle (v1), or the clips then the transitions (v2). A
// transition eases from the leave frame's (phase, stride) to the arrive frame's, the phase moving
// forward about as fast as in the two clips, so it joins both without a jump.
std::vector<Motion> pose_motions(const Options& o) {
    const float turn = 2.0f * glm::pi<float>();
    std::vector<Motion> motions;
    if (o.clips.empty()) {
        for (uint32_t f = 0; f < o.frames; ++f) motions.push_back({turn * float(f) / float(o.frames), 1.0f});
        return motions;
    }
    for (const Options::Clip& c : o.clips)
        for (uint32_t f = 0; f < c.frames; ++f) motions.push_back({turn * float(f) / float(c.frames), c.stride});
    for (const Options::Transition& t : o.transitions) {
        const Options::Clip &a = o.clips[t.from], &b = o.clips[t.to];
        const float from = turn * float(t.leave) / float(a.frames);
        const float to = turn * float(t.arrive) / float(b.frames) + (o.popping_transitions ? 0.375f * turn : 0.0f);
        const float step = 0.5f * (turn / float(a.frames) + turn / float(b.frames)), want = step * float(t.frames + 1);
        float gap = std::fmod(to - from + 2 * turn, turn);
        gap += turn * std::max(0.0f, std::round((want - gap) / turn));
        for (uint32_t j = 0; j < t.frames; ++j) {
            const float s = float(j + 1) / float(t.frames + 1);
            motions.push_back({from + s * gap, a.stride + s * (b.stride - a.stride)});
        }
    }
    return motions;
}

}  // namespace

std::string write_bundle(const std::string& dir, const Options& o) {
    using crowdview::sha256_hex;
    if (fs::exists(dir)) return "write_bundle: " + dir + " exists";
    const float fps = 8.0f;
    const std::vector<Motion> motions = pose_motions(o);
    const uint32_t frames = uint32_t(motions.size());
    Mesh body_hi = build_part(body_primitives(), o.body_segments[0], o.body_rings[0], motions);
    Mesh body_lo = build_part(body_primitives(), o.body_segments[1], o.body_rings[1], motions);
    Mesh skirt_hi = build_part(skirt_primitives(), o.skirt_segments[0], o.skirt_rings[0], motions);
    Mesh skirt_lo = build_part(skirt_primitives(), o.skirt_segments[1], o.skirt_rings[1], motions);
    if (o.scale != 1.0f)  // a uniform scale keeps the normals
        for (Mesh* m : {&body_hi, &body_lo, &skirt_hi, &skirt_lo})
            for (float& v : m->positions) v *= o.scale;

    // Bounds: the box over every frame of every part, and the sphere around its centre.
    glm::vec3 lo(INFINITY), hi(-INFINITY);
    for (const Mesh* m : {&body_hi, &skirt_hi, &body_lo, &skirt_lo})
        for (size_t i = 0; i < m->positions.size(); i += 3) {
            const glm::vec3 p(m->positions[i], m->positions[i + 1], m->positions[i + 2]);
            lo = glm::min(lo, p), hi = glm::max(hi, p);
        }
    const glm::vec3 center = 0.5f * (lo + hi);
    float radius = 0;
    for (const Mesh* m : {&body_hi, &skirt_hi, &body_lo, &skirt_lo})
        for (size_t i = 0; i < m->positions.size(); i += 3)
            radius = std::max(radius, glm::length(glm::vec3(m->positions[i], m->positions[i + 1], m->positions[i + 2]) - center));
    radius *= 1.02f;  // a texel of margin so silhouettes never touch the tile edge

    // Textures.
    const uint32_t body_size = 64, skirt_size = 32, variations = 2, outfits = 4;
    std::vector<std::vector<uint8_t>> body_rgba, skirt_rgba;
    std::vector<uint8_t> body_layers, skirt_layers;
    for (uint32_t v = 0; v < variations; ++v) {
        body_rgba.push_back(body_texture(body_size, v));
        skirt_rgba.push_back(skirt_texture(skirt_size, v));
        const std::vector<uint8_t> body = o.compressed ? compress_bc(body_rgba[v], body_size, body_size, true) : body_rgba[v];
        body_layers.insert(body_layers.end(), body.begin(), body.end());
        skirt_layers.insert(skirt_layers.end(), skirt_rgba[v].begin(), skirt_rgba[v].end());
    }

    // Impostor atlases: layer k is baked frame frame_indices[k].
    const uint32_t tile = o.tile_size, columns = uint32_t(o.azimuths_deg.size()), rows = uint32_t(o.elevations_deg.size());
    const uint32_t aw = tile * columns, ah = tile * rows;
    std::vector<uint8_t> normal_layers, uv_layers, detail_layers;
    const std::vector<BakePart> parts = {{&body_hi, 0}, {&skirt_hi, 1}};
    const std::vector<uint8_t>* sources[2] = {&body_rgba[0], &skirt_rgba[0]};
    const uint32_t source_sizes[2] = {body_size, skirt_size};
    std::vector<BakeTexel> texels;
    for (uint32_t frame : o.frame_indices) {
        std::vector<uint8_t> normal(size_t(aw) * ah * 4, 0), detail(size_t(aw) * ah * 4, 0);
        std::vector<uint16_t> uv(size_t(aw) * ah * 4, 0);
        for (uint32_t e = 0; e < rows; ++e)
            for (uint32_t a = 0; a < columns; ++a) {
                bake_view(parts, frame, center, radius, o.azimuths_deg[a], o.elevations_deg[e], tile, &texels);
                for (uint32_t y = 0; y < tile; ++y)
                    for (uint32_t x = 0; x < tile; ++x) {
                        const BakeTexel& t = texels[y * tile + x];
                        const size_t at = ((size_t(e) * tile + y) * aw + a * tile + x) * 4;
                        if (!t.covered) {
                            normal[at + 0] = normal[at + 1] = normal[at + 2] = 128;
                            normal[at + 3] = 255;
                            continue;
                        }
                        for (int c = 0; c < 3; ++c) normal[at + c] = uint8_t(std::lround((t.normal[c] + 1.0f) * 0.5f * 255.0f));
                        normal[at + 3] = 255;
                        uv[at + 0] = uint16_t(std::lround(glm::clamp(t.uv.x, 0.0f, 1.0f) * 65535.0f));
                        uv[at + 1] = uint16_t(std::lround(glm::clamp(t.uv.y, 0.0f, 1.0f) * 65535.0f));
                        uv[at + 2] = uint16_t(t.material);
                        uv[at + 3] = 65535;
                        const uint32_t size = source_sizes[t.material];
                        const uint32_t sx = std::min(uint32_t(t.uv.x * size), size - 1);
                        const uint32_t sy = std::min(uint32_t(t.uv.y * size), size - 1);
                        std::memcpy(&detail[at], &(*sources[t.material])[(size_t(sy) * size + sx) * 4], 4);
                    }
            }
        const std::vector<uint8_t> n = o.compressed ? compress_bc(normal, aw, ah, false) : normal;
        const std::vector<uint8_t> d = o.compressed ? compress_bc(detail, aw, ah, true) : detail;
        normal_layers.insert(normal_layers.end(), n.begin(), n.end());
        detail_layers.insert(detail_layers.end(), d.begin(), d.end());
        const uint8_t* uv_bytes = reinterpret_cast<const uint8_t*>(uv.data());  // little-endian host
        uv_layers.insert(uv_layers.end(), uv_bytes, uv_bytes + uv.size() * 2);
    }

    // Files and manifest.
    struct File {
        std::string path, role, media_type;
        std::vector<uint8_t> bytes;
    };
    const char* pose = "application/vnd.crowdbake.pose-cache";
    const char* texture = "application/vnd.crowdbake.texture";
    const uint32_t bc1 = 3, bc2 = 4, rgba8 = 1, rgba16 = 2;
    auto cbpc = [&](const Mesh& m) { return encode_pose_cache(m.indices, m.uvs, m.positions, m.normals, frames, fps); };
    const std::string cycle_json = "{\"frames\": " + std::to_string(frames) + "}\n";
    std::vector<File> files = {
        {"poses/body_lod0.cbpc", "pose-cache", pose, cbpc(body_hi)},
        {"poses/body_lod1.cbpc", "pose-cache", pose, cbpc(body_lo)},
        {"poses/skirt_lod0.cbpc", "pose-cache", pose, cbpc(skirt_hi)},
        {"poses/skirt_lod1.cbpc", "pose-cache", pose, cbpc(skirt_lo)},
        {"textures/body.cbtx", "diffuse", texture,
         encode_texture_array(body_size, body_size, variations, o.compressed ? bc2 : rgba8, body_layers)},
        {"textures/skirt.cbtx", "diffuse", texture, encode_texture_array(skirt_size, skirt_size, variations, rgba8, skirt_layers)},
        {"textures/outfits.cbtx", "outfit-colours", texture, encode_texture_array(16, outfits, 1, rgba8, outfit_map(outfits))},
        {"impostor/normal.cbtx", "impostor-normal", texture,
         encode_texture_array(aw, ah, uint32_t(o.frame_indices.size()), o.compressed ? bc1 : rgba8, normal_layers)},
        {"impostor/uv.cbtx", "impostor-uv", texture, encode_texture_array(aw, ah, uint32_t(o.frame_indices.size()), rgba16, uv_layers)},
        {"impostor/detail.cbtx", "impostor-detail", texture,
         encode_texture_array(aw, ah, uint32_t(o.frame_indices.size()), o.compressed ? bc2 : rgba8, detail_layers)},
        {"cycle/cycle.json", "cycle", "application/json", std::vector<uint8_t>(cycle_json.begin(), cycle_json.end())},
    };
    using nlohmann::json;
    auto mesh_entry = [](const char* part, const char* kind, int lod, const char* file, int material, const Mesh& m) {
        return json{{"part", part},       {"kind", kind},
                    {"lod", lod},         {"file", file},
                    {"material", material}, {"vertex_count", m.vertex_count},
                    {"triangle_count", m.indices.size() / 3}};
    };
    json manifest = {
        {"format", "crowdbake-bundle"},
        {"format_version", 1},
        {"name", o.name},
        {"version", "1.0.0"},
        {"created", "2026-01-01T00:00:00Z"},
        {"producer", "crowdview tests (synthetic_bundle.cpp)"},
        {"frames_per_second", fps},
        {"cycle",
         {{"source_start_frame", 0}, {"source_end_frame", frames}, {"frames", frames}, {"closing", "none"},
          {"position_jump_ratio", 0.0}, {"velocity_jump_ratio", 0.0}}},
        {"materials",
         {{{"name", "body"}, {"diffuse", "textures/body.cbtx"}, {"variations", variations}},
          {{"name", "skirt"}, {"diffuse", "textures/skirt.cbtx"}, {"variations", variations}}}},
        {"outfits", {{"file", "textures/outfits.cbtx"}, {"count", outfits}, {"regions", 16}}},
        {"meshes",
         {mesh_entry("body", "body", 0, "poses/body_lod0.cbpc", 0, body_hi),
          mesh_entry("body", "body", 1, "poses/body_lod1.cbpc", 0, body_lo),
          mesh_entry("skirt", "garment", 0, "poses/skirt_lod0.cbpc", 1, skirt_hi),
          mesh_entry("skirt", "garment", 1, "poses/skirt_lod1.cbpc", 1, skirt_lo)}},
        {"impostor",
         {{"tile_size", tile},
          {"azimuths_deg", o.azimuths_deg},
          {"elevations_deg", o.elevations_deg},
          {"frame_indices", o.frame_indices},
          {"bounds", {{"center", {center.x, center.y, center.z}}, {"radius", radius}}},
          {"maps", {{"normal", "impostor/normal.cbtx"}, {"uv", "impostor/uv.cbtx"}, {"detail", "impostor/detail.cbtx"}}}}},
    };
    std::sort(files.begin(), files.end(), [](const File& a, const File& b) { return a.path < b.path; });
    json listed = json::array();
    for (const File& f : files) {
        listed.push_back({{"path", f.path},
                          {"size", f.bytes.size()},
                          {"sha256", sha256_hex(f.bytes.data(), f.bytes.size())},
                          {"media_type", f.media_type},
                          {"role", f.role}});
        if (!write_bytes(dir + "/" + f.path, f.bytes)) return "write_bundle: cannot write " + dir + "/" + f.path;
    }
    if (!o.clips.empty()) {  // format v2: clips, then transitions, tiling the pose frames
        manifest["format_version"] = 2;
        manifest.erase("cycle");
        manifest["pose_frames"] = frames;
        json clips = json::array(), transitions = json::array();
        uint32_t first = 0;
        for (const Options::Clip& c : o.clips) {
            clips.push_back({{"name", c.name}, {"first_frame", first}, {"frames", c.frames}, {"source_start_frame", first},
                             {"source_end_frame", first + c.frames}, {"closing", "none"}, {"position_jump_ratio", 0.0},
                             {"velocity_jump_ratio", 0.0}});
            first += c.frames;
        }
        for (const Options::Transition& t : o.transitions) {
            transitions.push_back({{"from_clip", t.from}, {"to_clip", t.to}, {"leave_frame", t.leave}, {"arrive_frame", t.arrive},
                                   {"first_frame", first}, {"frames", t.frames}, {"source_start_frame", first},
                                   {"source_end_frame", first + t.frames}, {"position_jump_ratio", 0.0}, {"velocity_jump_ratio", 0.0}});
            first += t.frames;
        }
        manifest["clips"] = clips;
        manifest["transitions"] = transitions;
    }
    manifest["files"] = listed;
    const std::string text = manifest.dump(2) + "\n";
    if (!write_bytes(dir + "/manifest.json", std::vector<uint8_t>(text.begin(), text.end())))
        return "write_bundle: cannot write the manifest";
    return "";
}

}  // namespace synthetic
