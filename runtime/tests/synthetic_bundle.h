// Test helpers that write the bundle format (shared_formats/SPEC.md) from C++: encoders for
// CBPC and CBTX, and a complete synthetic bundle whose impostor maps are baked here by a
// small CPU rasterizer, independently of the renderer under test.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace synthetic {

// CBPC bytes. positions and normals: frame_count * vertex_count * 3; bounds from positions.
std::vector<uint8_t> encode_pose_cache(const std::vector<uint32_t>& indices, const std::vector<float>& uvs,
                                       const std::vector<float>& positions, const std::vector<float>& normals,
                                       uint32_t frame_count, float frames_per_second);

// CBTX bytes: `layers` holds layer_count layers of raw texels or BC blocks, back to back.
std::vector<uint8_t> encode_texture_array(uint32_t width, uint32_t height, uint32_t layer_count, uint32_t pixel_format,
                                          const std::vector<uint8_t>& layers);

// RGBA8 (rows top first) to BC1 or BC2 blocks (stb_dxt for colour; BC2 alpha is alpha >> 4,
// exact for region codes 17 * r).
std::vector<uint8_t> compress_bc(const std::vector<uint8_t>& rgba, uint32_t width, uint32_t height, bool bc2);

struct Options {
    uint32_t frames = 8;           // cycle frames at 8 fps: a one second walk
    uint32_t tile_size = 64;
    std::vector<float> azimuths_deg = {0, 30, 60, 90, 120, 150, 180, 210, 240, 270, 300, 330};
    std::vector<float> elevations_deg = {0, 30};
    std::vector<uint32_t> frame_indices = {0, 2, 4, 6};
    bool compressed = true;        // bc2 body diffuse, bc1 normal map, bc2 detail map; else rgba8
    float scale = 1;               // the figure's size (1: about 1.8 m tall); the bounds follow
    std::string name = "synthetic-walker";  // the manifest's name
    // Grid resolution (segments around x rings) of each body primitive and of the skirt, per
    // LOD. The defaults give 4,992 and 616 triangles; paper_counts() gives the paper's figure 3
    // characters: 13,056 (high) and 1,900 (low; the paper's has 1,899).
    uint32_t body_segments[2] = {24, 8}, body_rings[2] = {16, 6};
    uint32_t skirt_segments[2] = {32, 10}, skirt_rings[2] = {6, 2};
    // Bundle format v2: several clips (each `frames` loop frames of the walk at `stride` times its
    // swing: 1 walks, less idles) and transitions between them, which ease phase and stride from
    // loop frame `leave` of clip `from` to loop frame `arrive` of clip `to` over `frames` frames.
    // Empty: a v1 bundle of one cycle of `frames`. frame_indices then name pose frames.
    struct Clip {
        std::string name;
        uint32_t frames = 8;
        float stride = 1;
    };
    struct Transition {
        uint32_t from = 0, to = 1, leave = 0, arrive = 0, frames = 4;
    };
    std::vector<Clip> clips;
    std::vector<Transition> transitions;
    // Transitions that end 3/8 of a stride away from their arrive frame: a switch that pops, for
    // showing that the switch measure sees one.
    bool popping_transitions = false;
    // An idle (stride 0.5) and a walk of 8 frames each, a 6-frame transition each way, every clip
    // frame of an even index baked and each transition's ends: 28 pose frames, 12 layers.
    static Options two_clips() {
        Options o;
        o.clips = {{"idle", 8, 0.5f}, {"walk", 8, 1.0f}};
        o.transitions = {{0, 1, 1, 0, 6}, {1, 0, 2, 1, 6}};
        o.frame_indices = {0, 2, 4, 6, 8, 10, 12, 14, 16, 21, 22, 27};
        o.name = "synthetic-clips";
        return o;
    }
    static Options paper_counts() {
        Options o;
        o.body_segments[0] = 40, o.body_rings[0] = 26, o.skirt_segments[0] = 48;
        o.body_segments[1] = 14, o.body_rings[1] = 11, o.skirt_segments[1] = 13;
        return o;
    }
};

// A walking figure (body with head, arms and legs; a skirt garment), two LODs, two materials
// with two variations each, four outfits, and baked normal, UV and detail maps. Writes
// `dir` (created, must not exist) and returns "" or an error.
std::string write_bundle(const std::string& dir, const Options& options = Options());

// Reads a file into a string ("" when absent) and writes one, creating parent folders.
std::string read_text(const std::string& path);
bool write_bytes(const std::string& path, const std::vector<uint8_t>& bytes);

// What a crowdview run left: its exit status (-1 where it did not exit), standard output and error.
struct Run {
    int status = -1;
    std::string out, err;
};
// Runs the `crowdview` binary with `args` (already shell-quoted where needed), capturing both streams.
Run run_crowdview(const std::string& crowdview, const std::string& args);

// A copy of the folder tree `from` at `to` (cp -r), for tampering tests.
bool copy_tree(const std::string& from, const std::string& to);
// A fresh empty temporary folder.
std::string temp_dir(const std::string& tag);

}  // namespace synthetic
