// The crowd description (shared_formats/crowd.schema.json, SPEC.md "Crowd description"): a
// JSON file naming the archetypes of one crowd (bundle folders or published bundles), how
// many of each, how they are laid out, and the camera. No GL, no fetching: parse and check.
//
// Every error names the file, the JSON pointer of the offending value and what is wrong:
//   "crowd.json: /archetypes/1/share: must be a number > 0, got -2"
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <glm/glm.hpp>

namespace crowdview {

constexpr uint32_t kCrowdFormatVersion = 1;
// A crowd of more characters than this is refused: ten million 32-byte instances is already
// 320 MB of instance data a frame.
constexpr uint64_t kMaxCrowdCount = 10000000;
constexpr size_t kMaxArchetypes = 64;  // each archetype is its own uploads and draw calls

// Where an archetype's bundle comes from. A published bundle (server + name + version) is the
// URL <server>/v1/bundles/<name>/<version>, fetched and verified as --url does.
struct ArchetypeSource {
    std::string folder;  // a bundle folder, resolved against the description's folder
    std::string url;     // or a bundle URL (http, https, file)
    bool is_url() const { return !url.empty(); }
};

struct ClipWeight {
    std::string clip;  // a clip name of the bundle
    float weight = 1;  // > 0; relative to the others
};

struct ArchetypeDesc {
    std::string name;  // unique in the crowd; the report's key
    ArchetypeSource source;
    uint64_t count = 0;  // characters, when given as a count
    double share = 0;    // or a share of CrowdFile::count (> 0); exactly one of the two, but a positions layout counts entries
    // Which clips of the bundle the characters play, by weight (empty: all alike); a name the
    // bundle lacks is refused once the bundle is loaded.
    std::vector<ClipWeight> clips;
    float play_rate[2] = {1, 1};  // each character plays its clips at a rate drawn in [lo, hi]
    // Seconds a character dwells in a clip before it switches (clips.h); unset: crowdview's --switch-after.
    bool has_switch_after = false;
    float switch_after_s[2] = {0, 0};
};

enum class CrowdLayoutKind { spot, paths, positions, scatter };

struct PlacedCharacter {
    uint32_t archetype = 0;  // index into CrowdFile::archetypes
    float x = 0, z = 0;      // metres, the feet on the ground plane
    float heading_rad = 0;
};

struct CrowdLayoutDesc {
    CrowdLayoutKind kind = CrowdLayoutKind::spot;
    float walk_speed = 0;                   // paths: metres per second; 0 means 1.3
    glm::vec2 area_min{0}, area_max{0};     // scatter: the XZ rectangle, metres
    std::vector<PlacedCharacter> positions;  // positions: every character, explicitly
};

enum class CrowdCameraKind { overview, street, look_at };

struct CrowdCameraDesc {
    CrowdCameraKind kind = CrowdCameraKind::overview;
    glm::vec3 eye{0}, target{0};  // look_at
    float fov_deg = 45;
};

struct CrowdFile {
    uint64_t seed = 1;
    uint64_t count = 0;  // total characters; needed when an archetype gives a share
    std::vector<ArchetypeDesc> archetypes;
    CrowdLayoutDesc layout;
    CrowdCameraDesc camera;
};

// Parses and checks `text`; `path` names the file in messages and its folder resolves
// relative bundle folders. Returns "" or one line: "<path>: <JSON pointer>: <what is wrong>".
std::string parse_crowd_description(const std::string& text, const std::string& path, CrowdFile* out);

// Reads the file, then parse_crowd_description.
std::string load_crowd_description(const std::string& path, CrowdFile* out);

// Characters per archetype: counts as given; shares split what the counts leave of
// CrowdFile::count by largest remainder (so they add up exactly); positions layouts count
// their entries. Assumes a CrowdFile that parsed.
std::vector<uint64_t> archetype_counts(const CrowdFile& crowd);

// A one-archetype description for `--bundle DIR` / `--url URL` and the flags that go with them (--count, --seed, --layout).
CrowdFile single_archetype_crowd(const ArchetypeSource& source, uint64_t count, uint64_t seed, bool paths);

// The published bundle URL for a crowdbake server: "<server>/v1/bundles/<name>/<version>".
std::string published_bundle_url(const std::string& server, const std::string& name, const std::string& version);

}  // namespace crowdview
