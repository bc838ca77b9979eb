// The crowd and its per-frame decisions, without GL: where each character stands, which
// frame it shows, which LOD it gets (the 1:1 pixel-to-texel rule with hysteresis), which
// impostor view faces the camera, and whether it is in the frustum at all.
//
// Conventions (shared_formats/SPEC.md): right-handed, +Y up, metres; a character at heading 0
// faces +Z, and heading h turns it by h radians about +Y, so it faces (sin h, 0, cos h).
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <vector>

#include <glm/glm.hpp>

#include "clips.h"
#include "view_blend.h"

namespace crowdview {

// ---------------------------------------------------------------------------------------
// Per-instance data as the shaders read it (CV_ATTR_INSTANCE_POSE, CV_ATTR_INSTANCE_IDS in
// config.h). Mirrored in the vertex shaders on purpose: keep the asserts below in step. The ids
// are 16-bit (the shaders read them as a uvec4 all the same): every frame fills and uploads one per
// shown character, so its size is the frame's memory traffic. Renderer refuses bundles with more
// than kMaxPoseFrames pose frames; views, layers, variations and outfits stay far below 65,536
// (the bake's 64 x 9 views, GL's 2,048 array layers).
struct Instance {
    float position[3];   // metres, the character's feet
    float heading;       // radians about +Y
    uint16_t frame;      // meshes: pose frame; impostors: atlas layer
    uint16_t variation;  // diffuse layer before the per-material modulo
    uint16_t outfit;     // row of the outfit map
    uint16_t tile;       // impostors: azimuth + elevation * azimuth_count; meshes: unused
};
static_assert(sizeof(Instance) == 24, "Instance is a vec4 and a 16-bit uvec4 attribute in the shaders");
static_assert(offsetof(Instance, heading) == 12 && offsetof(Instance, frame) == 16, "shader attribute offsets");
constexpr uint32_t kMaxPoseFrames = 65536;  // Instance::frame's range

// Per impostor, beside its Instance: the (view, frame) samples it blends (view_blend.h), as
// impostor.vert.glsl reads them (CV_ATTR_IMPOSTOR_* in config.h; tiles and layers 16-bit as in
// Instance). Mirrored on purpose.
struct ImpostorSamples {
    uint16_t tiles[4];        // atlas tiles, azimuth + elevation * azimuth_count
    float view_weights[4];    // summing to 1, heaviest first; weight-0 entries last
    uint16_t layers[2];       // atlas layers (baked frames)
    float frame_weight;       // of layers[1]; layers[0] has 1 - frame_weight
};
static_assert(sizeof(ImpostorSamples) == 32, "four attributes, 4-byte aligned");
static_assert(offsetof(ImpostorSamples, view_weights) == 8 && offsetof(ImpostorSamples, layers) == 24 &&
                  offsetof(ImpostorSamples, frame_weight) == 28,
              "shader attribute offsets");

// ---------------------------------------------------------------------------------------
// Deterministic random numbers (splitmix64): the same seed gives the same crowd on every
// platform, which std::uniform_*_distribution does not promise.
struct Rng {
    uint64_t state;
    explicit Rng(uint64_t seed) : state(seed) {}
    uint64_t next();
    float uniform(float lo, float hi);          // [lo, hi)
    uint32_t below(uint32_t n);                 // [0, n), n > 0
};

enum class Layout { on_the_spot, paths };

struct CrowdDesc {
    uint32_t count = 100;
    uint64_t seed = 1;
    Layout layout = Layout::on_the_spot;
    float spacing = 0;     // metres between grid neighbours; 0 means 1.6 (shoulder room for a walk)
    float walk_speed = 0;  // metres per second along paths; 0 means 1.3 (a relaxed human walk)
};

struct Character {
    glm::vec3 start;       // feet at time 0
    float heading;         // radians
    float phase_s;         // offset into its first clip, seconds
    uint32_t variation;    // in [0, variation_count)
    uint32_t outfit;       // in [0, outfit_count)
    float rate = 1;        // play rate of its clips: they advance rate seconds per second
    uint32_t clip = 0;     // the clip it plays at time 0 (clips.h); later ones follow the schedule
};

struct Crowd {
    std::vector<Character> characters;
    Layout layout = Layout::on_the_spot;
    float half_extent = 0;  // characters stay inside [-half_extent, half_extent]^2 on the XZ plane
    float walk_speed = 0;
    ClipPlan clip_plan;      // the clip mix and how long characters dwell in a clip
    uint64_t clip_seed = 0;  // the switch schedule's draws
};

// Gives each character of `crowd` a first clip drawn by `weights` (per clip, >= 0, one > 0) and a
// phase drawn in that clip's `clip_seconds`, from `seed`. Where only clip 0 can be drawn it draws
// nothing, so a one-clip crowd is the crowd its seed gives without clips.
void assign_clips(Crowd* crowd, const std::vector<float>& weights, const std::vector<float>& clip_seconds, uint64_t seed);

// N characters on a jittered square grid centred on the origin, each with its own heading,
// phase, diffuse variation and outfit; identical for identical arguments.
Crowd make_crowd(const CrowdDesc& desc, uint32_t variation_count, uint32_t outfit_count, float cycle_seconds);

// Metres between grid neighbours for a character whose impostor bounding sphere has `radius`
// metres (the manifest's impostor bounds): 1.6 up to a human's radius, in proportion above it, so
// a crowd of 4 m robots does not stand at human spacing and overlap. radius <= 0 gives 1.6.
float crowd_spacing(float radius);

// Where a character's feet are at time t: its start on the spot, or walked along its heading
// and wrapped around the crowd's square (a torus, so density stays even).
glm::vec3 character_position(const Crowd& crowd, const Character& character, float time_s);

// The cycle frame shown at time t (nearest earlier keyframe; frame_count wraps to 0).
uint32_t cycle_frame(float time_s, float phase_s, float frames_per_second, uint32_t frame_count);

// The impostor atlas layer for a cycle frame: the baked frame (frame_indices, ascending)
// nearest to it around the cycle. frame_indices must not be empty.
uint32_t impostor_layer(uint32_t frame, const std::vector<uint32_t>& frame_indices, uint32_t frame_count);

// ---------------------------------------------------------------------------------------
// LOD: high mesh, low mesh, impostor

enum class Lod : uint8_t { high = 0, low = 1, impostor = 2 };

// Distance (metres, along the view axis) at which one impostor texel covers one pixel.
// A tile spans 2*radius metres with tile_size texels; a perspective pixel at distance d
// spans 2*d*tan(fov_y/2)/viewport_height metres. Equal at d = radius*H / (tile*tan(fov/2)).
float impostor_switch_distance(float fov_y_rad, float viewport_height_px, float radius_m, uint32_t tile_size);

struct LodRule {
    float impostor_distance = 0;  // impostor_switch_distance(...)
    // The low mesh takes over at this fraction of the impostor distance: from there on a
    // character is under 2*tile_size pixels tall, where a high mesh's extra triangles fall
    // below a pixel each (1 disables the low mesh).
    float low_fraction = 0.5f;
    bool has_low = true;
    // Switch to a coarser level only beyond boundary*(1+h), back to a finer one below the
    // boundary itself: a character hovering at a boundary keeps its level, and an impostor is
    // never shown closer than the 1:1 distance.
    float hysteresis = 0.05f;
};

// The level for `distance` given the level shown last frame (pass `lod_without_history` for
// a character seen for the first time).
Lod select_lod(float distance, Lod previous, const LodRule& rule);
Lod lod_without_history(float distance, const LodRule& rule);

// ---------------------------------------------------------------------------------------
// Impostor view selection

struct ImpostorView {
    uint32_t azimuth;    // column of the atlas
    uint32_t elevation;  // row of the atlas
};

// The atlas tile whose bake camera is nearest the real camera direction, seen in the
// character's own frame. `to_camera` points from the character's bounds centre to the camera
// (world space, any length > 0). Azimuths wrap at 360 degrees; elevations do not.
ImpostorView select_view(const glm::vec3& to_camera, float heading, const std::vector<float>& azimuths_deg,
                         const std::vector<float>& elevations_deg);

// ---------------------------------------------------------------------------------------
// Camera and culling

struct Camera {
    glm::vec3 position{0, 1.7f, 10};
    float yaw = 0;       // radians; 0 looks along -Z
    float pitch = 0;     // radians; positive looks up
    float fov_y = glm::radians(45.0f);
    float near_m = 0.1f, far_m = 2000.0f;

    glm::vec3 forward() const;
    glm::mat4 view() const;
    glm::mat4 projection(float aspect) const;
};

// A camera at `eye` looking at `target` (no roll).
Camera look_at(glm::vec3 eye, glm::vec3 target);

struct Frustum {
    glm::vec4 planes[6];  // inward normals: dot(plane.xyz, p) + plane.w >= 0 inside
};
Frustum frustum_from(const glm::mat4& view_projection);
bool sphere_in_frustum(const Frustum& frustum, const glm::vec3& center, float radius);

// The benchmark's crowd (the paper's figure 3 test: everyone on screen, walking on the spot):
// staggered rows `spacing` apart on the ground in front of `camera`, from `near_m` (metres
// along the ground) outwards, nearest first, each kept only when a sphere of `radius` around
// its centre (`center_height` above the feet) lies wholly inside the view. More characters
// reach further away, as in a real crowd, so near ones are meshes and far ones impostors
// under LodMode::automatic.
Crowd make_crowd_in_view(const CrowdDesc& desc, const Camera& camera, float aspect, float center_height, float radius,
                         float near_m, uint32_t variation_count, uint32_t outfit_count, float cycle_seconds);

// A camera that sees the whole crowd: looking down at `pitch` onto its centre, backed off
// until the crowd's bounding sphere fits the vertical and horizontal field of view.
Camera camera_for_crowd(const Crowd& crowd, float character_height, float aspect, float pitch_rad);
// A viewer standing just outside the crowd's front edge, a little above eye level and
// looking across it, so the nearest characters are meshes and the far ones impostors.
Camera street_camera(const Crowd& crowd, float character_height);

// ---------------------------------------------------------------------------------------
// One frame's instances

enum class LodMode { automatic, high, low, impostor };

// What the crowd needs from the bundle, copied out so this file needs no bundle types.
struct CharacterModel {
    glm::vec3 center{0, 1, 0};  // impostor bounds centre, in the character's frame
    float radius = 1;
    float frames_per_second = 24;
    uint32_t frame_count = 1;  // pose frames, every clip and transition
    std::vector<ClipRange> clips;  // none: one clip of frame_count frames
    std::vector<TransitionRange> transitions;
    uint32_t tile_size = 64;
    std::vector<float> azimuths_deg, elevations_deg;
    std::vector<uint32_t> frame_indices;
    bool has_low = false;
};

// The LOD rule for `model` seen through `camera` on a viewport `viewport_height_px` tall:
// impostors from the 1:1 switch distance, a low mesh only where the bundle has one.
LodRule lod_rule_for(const CharacterModel& model, const Camera& camera, float viewport_height_px);

// Headless and benchmark runs step time by this much per frame, so output is reproducible.
constexpr float kFixedTimeStep = 1.0f / 30.0f;

struct FrameInstances {
    // The lists, where build_frames was given no InstanceStorage; else empty (the lists are in its memory).
    std::vector<Instance> by_lod[3];  // indexed by Lod; impostors carry their nearest view and frame
    std::vector<ImpostorSamples> impostor_samples;  // one per by_lod[Lod::impostor] entry
    ImpostorBlend blend = ImpostorBlend::warp;      // how they were chosen: the shader variant to draw them
    uint32_t culled = 0;
    uint32_t shown[3] = {0, 0, 0};  // instances per list (by Lod), wherever they were written
    bool in_storage = false;        // written by an InstanceStorage (instance_upload.h: in the GL buffers)
};

// Where one archetype's lists go, as InstanceStorage::open hands them out.
struct InstancePlaces {
    Instance* by_lod[3];
    ImpostorSamples* impostor_samples;  // nullptr where the frame has no samples
};

// Where build_frames writes the lists when not into FrameInstances' vectors: once its first pass has
// counted every list, it asks for room, its fill threads write there, and it closes the storage.
// instance_upload.h's MappedInstanceStorage hands out mapped GL buffer memory, so a frame's
// instances reach the GPU with no copy.
class InstanceStorage {
public:
    virtual ~InstanceStorage() = default;
    // Room for sizes[l] Instances in list l of archetype `archetype` (its index in build_frames'
    // list) and, where `samples`, as many ImpostorSamples as impostors; valid until close(). Called
    // on build_frames' calling thread, between its passes.
    virtual InstancePlaces open(size_t archetype, const uint32_t sizes[3], bool samples) = 0;
    // Every place is written: done with them (GL: unmapped), before anything draws.
    virtual void close() = 0;
    // Whether impostors need samples even where the model has no views to blend (then each gets its
    // nearest view and frame, as upload_instances makes them): true for GL buffers, which the
    // impostor shader reads.
    virtual bool always_samples() const = 0;
};

// What build_frame keeps between frames for one archetype: the LOD history, and tables it would
// otherwise recompute for every character every frame (the frame is the hot loop of a crowd of
// 100,000: no trigonometry it can look up, no allocation once the vectors have grown).
struct FrameState {
    std::vector<Lod> lod;  // per character: the level shown last frame (Lod(255): none yet)

    // Per character: the bounds centre's XZ offset from the feet, turned by the heading. Built
    // for `crowd`, rebuilt when the crowd's address or size changes.
    const Crowd* crowd = nullptr;
    std::vector<glm::vec2> center_offset;
    // Per pose frame: the nearest baked layer and the blend of the two either side, within the
    // frame's clip or transition (clips.h impostor_frame_tables). Built for the model's views, frames
    // and ranges (copied here), rebuilt when they change.
    CharacterModel tables_for;
    std::vector<uint32_t> nearest_layer;
    std::vector<FrameWeights> frame_weights;
    // Clip playback: the schedule (built for the model and the crowd's plan) and one state per
    // character, played up to clip_time_s; started again when time goes back.
    ClipSchedule schedule;
    ClipPlan schedule_plan;
    uint64_t schedule_seed = 0;
    std::vector<ClipState> clip;
    float clip_time_s = -INFINITY;
    // Per character clip[i].next_event_s alone, so the frame's look for due switches reads 4 bytes
    // a character instead of a 16-byte state.
    std::vector<float> next_switch_s;
    // Azimuths evenly spaced round the circle (as the bake writes them): the view is an index
    // computation; otherwise view_blend.h's search.
    bool even_azimuths = false;
    float azimuth0_deg = 0, azimuth_step_deg = 0;
    uint32_t lowest_elevation = 0, highest_elevation = 0;  // indices into the model's elevations

    // The frame's passes (structure of arrays, so the view maths vectorises; chunks of characters, so
    // threads share one archetype): per character its heading (built with center_offset), and this
    // frame's bounds centre, feet (walking layouts only) and level shown (a Lod, or 3: culled); per
    // chunk the characters it has at each level (and culled) and where its instances go.
    std::vector<float> heading, center_x, center_y, center_z;
    std::vector<glm::vec3> feet;
    std::vector<uint8_t> shown;
    std::vector<uint32_t> chunk_counts, chunk_offsets;  // 4 and 3 per chunk
};

// Cull, pick a LOD (with hysteresis through `state`, one entry per character, resized as
// needed) and fill the instance lists for one frame; impostors blend views and frames as
// `blend` says (the pose frame the mesh would show is the point between baked frames).
// Each character plays its clips at its own rate (Character::rate), switching as clips.h says;
// every character's clip state is stepped to `time_s`, culled or not.
void build_frame(const Crowd& crowd, const CharacterModel& model, const Camera& camera, float aspect, LodMode mode,
                 const LodRule& rule, float time_s, FrameState* state,
                 FrameInstances* out, ImpostorBlend blend = ImpostorBlend::warp);

// One archetype's part in build_frames: what build_frame takes for it.
struct ArchetypeFrame {
    const Crowd* crowd;
    const CharacterModel* model;
    const LodRule* rule;
    FrameState* state;
    FrameInstances* out;
};

// build_frame for every archetype with one camera, spread over up to `threads` threads (the calling
// thread among them) in chunks of characters, so two cores share even a one-archetype crowd. The
// instances, their order and every state are those of build_frame called for each archetype in turn,
// whatever `threads`.
// With `storage`, the lists go there instead of into FrameInstances' vectors, byte for byte the same
// (where the model has no views and the storage always wants samples, the samples upload_instances
// would make are written besides).
void build_frames(const std::vector<ArchetypeFrame>& archetypes, const Camera& camera, float aspect, LodMode mode, float time_s,
                  ImpostorBlend blend, unsigned threads, InstanceStorage* storage = nullptr);

// The threads build_frames is worth: the hardware's.
unsigned frame_threads();

}  // namespace crowdview
