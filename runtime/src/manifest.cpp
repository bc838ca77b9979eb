// Manifest reader: manifest.schema.json written out as checks (format versions 1 to 4), and the
// rules across fields a schema cannot say (ranges tiling the pose frames, clip names unique).
#include "bundle.h"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <regex>
#include <set>

namespace crowdview {

using json = nlohmann::json;
// ---------------------------------------------------------------------------------------
// Manifest: manifest.schema.json written out as checks

namespace {

// Walks a JSON document and records the first schema violation with its location.
class SchemaCheck {
public:
    bool failed() const { return !error_.empty(); }
    const std::string& error() const { return error_; }

    void fail(const std::string& where, const std::string& what) {
        if (error_.empty()) error_ = "at " + where + ": " + what;
    }

    // JSON Schema "integer": any number with no fractional part (draft 2020-12).
    static bool is_integer(const json& v) {
        if (v.is_number_integer()) return true;
        return v.is_number_float() && std::isfinite(v.get<double>()) && std::floor(v.get<double>()) == v.get<double>();
    }

    const json* member(const json& object, const std::string& where, const char* key) {
        auto it = object.find(key);
        if (it == object.end()) {
            fail(where, std::string("'") + key + "' is a required property");
            return nullptr;
        }
        return &*it;
    }

    const json* object(const json& parent, const std::string& where, const char* key) {
        const json* v = member(parent, where, key);
        if (v && !v->is_object()) {
            fail(where + "/" + key, "is not of type 'object'");
            return nullptr;
        }
        return v;
    }

    const json* array(const json& parent, const std::string& where, const char* key, size_t min_items) {
        const json* v = member(parent, where, key);
        if (!v) return nullptr;
        if (!v->is_array()) {
            fail(where + "/" + key, "is not of type 'array'");
            return nullptr;
        }
        if (v->size() < min_items) {
            fail(where + "/" + key, "should be non-empty");
            return nullptr;
        }
        return v;
    }

    // Integer in [minimum, maximum]; stored as uint32 (larger values cannot describe a
    // real bundle and are refused here rather than wrapped).
    uint32_t integer(const json& parent, const std::string& where, const char* key, int64_t minimum,
                     int64_t maximum = UINT32_MAX) {
        const json* v = member(parent, where, key);
        return v ? integer_value(*v, where + "/" + key, minimum, maximum) : 0;
    }

    uint32_t integer_value(const json& v, const std::string& where, int64_t minimum, int64_t maximum = UINT32_MAX) {
        if (!is_integer(v)) {
            fail(where, "is not of type 'integer'");
            return 0;
        }
        const double d = v.get<double>();
        if (d < double(minimum) || d > double(maximum)) {
            fail(where, "is out of range [" + std::to_string(minimum) + ", " + std::to_string(maximum) + "]");
            return 0;
        }
        return uint32_t(d);
    }

    // A file size: an exact integer in [0, kMaxFileSize]. Read exactly, never through a cast that
    // could overflow: 2^64 - 1 as a double is 2^64, and converting that to uint64_t is undefined
    // (it read as 0, and the file then had to be empty).
    uint64_t size_value(const json& v, const std::string& where) {
        const std::string range = "is out of range [0, " + std::to_string(kMaxFileSize) + "]";
        if (v.is_number_unsigned()) {
            const uint64_t n = v.get<uint64_t>();
            if (n > kMaxFileSize) fail(where, range);
            return n <= kMaxFileSize ? n : 0;
        }
        if (v.is_number_integer()) {  // signed, so negative here
            fail(where, range);
            return 0;
        }
        if (!is_integer(v)) {
            fail(where, "is not of type 'integer'");
            return 0;
        }
        const double d = v.get<double>();  // integral and finite; compared before any conversion
        if (d < 0 || d > double(kMaxFileSize)) {
            fail(where, range);
            return 0;
        }
        return uint64_t(d);
    }

    // Number with optional bounds; `exclusive_min` makes the minimum exclusive.
    double number(const json& parent, const std::string& where, const char* key, double minimum = -INFINITY,
                  bool exclusive_min = false) {
        const json* v = member(parent, where, key);
        return v ? number_value(*v, where + "/" + key, minimum, exclusive_min) : 0;
    }

    double number_value(const json& v, const std::string& where, double minimum = -INFINITY, bool exclusive_min = false,
                        double maximum = INFINITY, bool exclusive_max = false) {
        if (!v.is_number()) {
            fail(where, "is not of type 'number'");
            return 0;
        }
        const double d = v.get<double>();
        if ((exclusive_min ? d <= minimum : d < minimum) || (exclusive_max ? d >= maximum : d > maximum))
            fail(where, "is out of range");
        return d;
    }

    std::string string(const json& parent, const std::string& where, const char* key, const char* pattern = nullptr,
                       size_t min_length = 0, size_t max_length = SIZE_MAX) {
        const json* v = member(parent, where, key);
        return v ? string_value(*v, where + "/" + key, pattern, min_length, max_length) : std::string();
    }

    std::string string_value(const json& v, const std::string& where, const char* pattern = nullptr,
                             size_t min_length = 0, size_t max_length = SIZE_MAX) {
        if (!v.is_string()) {
            fail(where, "is not of type 'string'");
            return {};
        }
        const std::string s = v.get<std::string>();
        // JSON Schema lengths count code points, not bytes.
        const size_t length = size_t(std::count_if(s.begin(), s.end(), [](char c) { return (c & 0xC0) != 0x80; }));
        if (length < min_length || length > max_length) fail(where, "has the wrong length");
        if (pattern && !std::regex_search(s, std::regex(pattern))) fail(where, "does not match '" + std::string(pattern) + "'");
        return s;
    }

    std::string enumerated(const json& parent, const std::string& where, const char* key,
                           std::initializer_list<const char*> values) {
        const json* v = member(parent, where, key);
        if (!v) return {};
        for (const char* value : values)
            if (v->is_string() && v->get<std::string>() == value) return value;
        fail(where + "/" + key, "is not one of the allowed values");
        return {};
    }

    // manifest.schema.json's $defs/path.
    std::string path(const json& parent, const std::string& where, const char* key) {
        std::string p = string(parent, where, key, "^[A-Za-z0-9._-]+(/[A-Za-z0-9._-]+)*$", 0, 200);
        if (p == "manifest.json") fail(where + "/" + key, "must not be 'manifest.json'");
        return p;
    }

private:
    std::string error_;
};

// Calls read(item, where) for each item of `array`, `where` being "<name>/<index>", while no
// check has failed and up to `limit` items; an item that is not an object fails the check and
// ends the walk.
template <typename Read>
void each_object(SchemaCheck& check, const json& array, const std::string& name, size_t limit, Read read) {
    for (size_t i = 0; i < array.size() && i < limit && !check.failed(); ++i) {
        const std::string where = name + "/" + std::to_string(i);
        if (!array[i].is_object()) return check.fail(where, "is not of type 'object'");
        read(array[i], where);
    }
}

const std::initializer_list<const char*> kClosings = {"none", "linear", "hermite", "crossfade"};

ClipInfo parse_clip(const json& item, const std::string& where, SchemaCheck& check) {
    ClipInfo clip;
    clip.name = check.string(item, where, "name", nullptr, 1, 64);
    clip.first_frame = check.integer(item, where, "first_frame", 0);
    clip.frames = check.integer(item, where, "frames", 1);
    clip.source_start_frame = check.integer(item, where, "source_start_frame", 0);
    clip.source_end_frame = check.integer(item, where, "source_end_frame", 1);
    clip.closing = check.enumerated(item, where, "closing", kClosings);
    clip.position_jump_ratio = check.number(item, where, "position_jump_ratio", 0);
    clip.velocity_jump_ratio = check.number(item, where, "velocity_jump_ratio", 0);
    return clip;
}

TransitionInfo parse_transition(const json& item, const std::string& where, SchemaCheck& check) {
    TransitionInfo t;
    t.from_clip = check.integer(item, where, "from_clip", 0);
    t.to_clip = check.integer(item, where, "to_clip", 0);
    t.leave_frame = check.integer(item, where, "leave_frame", 0);
    t.arrive_frame = check.integer(item, where, "arrive_frame", 0);
    t.first_frame = check.integer(item, where, "first_frame", 0);
    t.frames = check.integer(item, where, "frames", 1);
    t.source_start_frame = check.integer(item, where, "source_start_frame", 0);
    t.source_end_frame = check.integer(item, where, "source_end_frame", 1);
    t.position_jump_ratio = check.number(item, where, "position_jump_ratio", 0);
    t.velocity_jump_ratio = check.number(item, where, "velocity_jump_ratio", 0);
    return t;
}

// Clip names unique; each transition between two different clips, leaving and arriving at loop
// frames of them.
void check_clip_references(const Manifest& m, SchemaCheck& check) {
    std::set<std::string> names;
    for (size_t i = 0; i < m.clips.size(); ++i)
        if (!names.insert(m.clips[i].name).second)
            return check.fail("clips/" + std::to_string(i) + "/name", "'" + m.clips[i].name + "' names two clips");
    const uint64_t clip_count = m.clips.size();
    for (size_t i = 0; i < m.transitions.size(); ++i) {
        const TransitionInfo& t = m.transitions[i];
        const std::string where = "transitions/" + std::to_string(i);
        if (t.from_clip >= clip_count || t.to_clip >= clip_count)
            return check.fail(where, "from_clip " + std::to_string(t.from_clip) + " or to_clip " + std::to_string(t.to_clip) +
                                         " is not a clip index (" + std::to_string(clip_count) + " clips)");
        if (t.from_clip == t.to_clip) return check.fail(where, "from_clip and to_clip are the same clip");
        if (t.leave_frame >= m.clips[t.from_clip].frames)
            return check.fail(where + "/leave_frame", std::to_string(t.leave_frame) + " is not a loop frame of clip " +
                                                          std::to_string(t.from_clip) + " (" + std::to_string(m.clips[t.from_clip].frames) + " frames)");
        if (t.arrive_frame >= m.clips[t.to_clip].frames)
            return check.fail(where + "/arrive_frame", std::to_string(t.arrive_frame) + " is not a loop frame of clip " +
                                                           std::to_string(t.to_clip) + " (" + std::to_string(m.clips[t.to_clip].frames) + " frames)");
    }
}

// The ranges tile [0, pose_frames) exactly: clips in order, then transitions in order.
void check_tiling(const Manifest& m, SchemaCheck& check) {
    uint64_t next = 0;  // where the next range must start
    auto tile = [&](const std::string& where, uint32_t first, uint32_t frames) {
        if (first != next)
            check.fail(where + "/first_frame", std::to_string(first) + ", the ranges before it end at " + std::to_string(next) +
                                                   " (clips then transitions must tile the pose frames in order)");
        next = uint64_t(first) + frames;
    };
    for (size_t i = 0; i < m.clips.size(); ++i) tile("clips/" + std::to_string(i), m.clips[i].first_frame, m.clips[i].frames);
    for (size_t i = 0; i < m.transitions.size(); ++i)
        tile("transitions/" + std::to_string(i), m.transitions[i].first_frame, m.transitions[i].frames);
    if (!check.failed() && next != m.pose_frames)
        check.fail("pose_frames", std::to_string(m.pose_frames) + ", the clips and transitions cover " + std::to_string(next));
}

// v2's pose_frames, clips and transitions (schema), then the rules across them: indices and loop
// frames in range, clip names unique, and the ranges tiling [0, pose_frames) exactly: clips in
// order, then transitions in order (SPEC.md "Clips and transitions").
void parse_clips_v2(const json& doc, SchemaCheck& check, Manifest* m) {
    if (doc.contains("cycle")) check.fail("cycle", "is a format_version 1 key; a manifest of format_version 2 or later has clips and transitions");
    m->pose_frames = check.integer(doc, "", "pose_frames", 1);
    if (const json* clips = check.array(doc, "", "clips", 1)) {
        if (clips->size() > kMaxClips) check.fail("clips", "has more than " + std::to_string(kMaxClips) + " items");
        each_object(check, *clips, "clips", kMaxClips,
                    [&](const json& item, const std::string& where) { m->clips.push_back(parse_clip(item, where, check)); });
    }
    if (const json* transitions = check.array(doc, "", "transitions", 0)) {
        if (transitions->size() > kMaxTransitions) check.fail("transitions", "has more than " + std::to_string(kMaxTransitions) + " items");
        each_object(check, *transitions, "transitions", kMaxTransitions,
                    [&](const json& item, const std::string& where) { m->transitions.push_back(parse_transition(item, where, check)); });
    }
    if (check.failed()) return;
    check_clip_references(*m, check);
    if (!check.failed()) check_tiling(*m, check);
}

// v1: one cycle, read as the one clip "cycle" (SPEC.md "v1 read as v2").
void parse_cycle_v1(const json& doc, SchemaCheck& check, Manifest* m) {
    ClipInfo clip;
    clip.name = "cycle";
    if (const json* cycle = check.object(doc, "", "cycle")) {
        clip.source_start_frame = check.integer(*cycle, "cycle", "source_start_frame", 0);
        clip.source_end_frame = check.integer(*cycle, "cycle", "source_end_frame", 1);
        clip.frames = check.integer(*cycle, "cycle", "frames", 1);
        clip.closing = check.enumerated(*cycle, "cycle", "closing", kClosings);
        clip.position_jump_ratio = check.number(*cycle, "cycle", "position_jump_ratio", 0);
        clip.velocity_jump_ratio = check.number(*cycle, "cycle", "velocity_jump_ratio", 0);
    }
    m->pose_frames = clip.frames;
    m->clips.push_back(clip);
}

// The frame rates a bundle may play at (SPEC.md "manifest.json"): every duration the runtime derives
// (clip lengths, switch times) divides by it, so 1e300 would make every clip last no time at all.
constexpr double kMinFramesPerSecond = 1, kMaxFramesPerSecond = 1000;

// The required top-level keys, then format, format_version, name, version, created, producer and
// frames_per_second.
void parse_identity(const json& doc, SchemaCheck& check, Manifest* m) {
    const std::string top = "(top level)";
    for (const char* key : {"format", "format_version", "name", "version", "created", "producer", "frames_per_second",
                            "materials", "outfits", "meshes", "impostor", "files"})
        check.member(doc, top, key);
    if (const json* format = check.member(doc, top, "format"); format && *format != "crowdbake-bundle")
        check.fail("format", "must be 'crowdbake-bundle'");
    m->format_version = check.integer(doc, "", "format_version", 1);
    m->name = check.string(doc, "", "name", "^[a-z0-9][a-z0-9._-]{0,63}$");
    m->version = check.string(doc, "", "version", "^[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}$");
    m->created = check.string(doc, "", "created", "^[0-9]{4}-[0-9]{2}-[0-9]{2}T[0-9]{2}:[0-9]{2}:[0-9]{2}(\\.[0-9]+)?Z$");
    m->producer = check.string(doc, "", "producer", nullptr, 1, 200);
    if (const json* fps = check.member(doc, top, "frames_per_second"))
        m->frames_per_second = check.number_value(*fps, "/frames_per_second", kMinFramesPerSecond, false, kMaxFramesPerSecond);
}

MaterialInfo parse_material(const json& item, const std::string& where, SchemaCheck& check) {
    MaterialInfo material;
    material.name = check.string(item, where, "name", nullptr, 1, 64);
    material.diffuse = check.path(item, where, "diffuse");
    material.variations = check.integer(item, where, "variations", 1);
    return material;
}

MeshInfo parse_mesh(const json& item, const std::string& where, SchemaCheck& check) {
    MeshInfo mesh;
    mesh.part = check.string(item, where, "part", "^[a-z0-9_-]{1,32}$");
    mesh.kind = check.enumerated(item, where, "kind", {"body", "garment"});
    mesh.lod = check.integer(item, where, "lod", 0, 7);
    mesh.file = check.path(item, where, "file");
    mesh.material = check.integer(item, where, "material", 0);
    mesh.vertex_count = check.integer(item, where, "vertex_count", 1);
    mesh.triangle_count = check.integer(item, where, "triangle_count", 1);
    return mesh;
}

FileEntry parse_file_entry(const json& item, const std::string& where, SchemaCheck& check) {
    FileEntry entry;
    entry.path = check.string(item, where, "path", nullptr, 1);
    if (const json* size = check.member(item, where, "size")) entry.size = check.size_value(*size, where + "/size");
    entry.sha256 = check.string(item, where, "sha256", "^[0-9a-f]{64}$");
    entry.media_type = check.string(item, where, "media_type", nullptr, 1);
    entry.role = check.enumerated(item, where, "role",
                                  {"pose-cache", "diffuse", "outfit-colours", "impostor-normal", "impostor-uv", "impostor-detail",
                                   "impostor-surface", "cycle", "fidelity", "texture-memory", "report", "preview"});
    return entry;
}

// impostor.tile_size, and the crop (the whole tile where absent) on 4-texel blocks.
void parse_impostor_tile(const json& impostor, SchemaCheck& check, ImpostorInfo* info) {
    info->tile_size = check.integer(impostor, "impostor", "tile_size", 4, 4096);
    if (info->tile_size % 4) check.fail("impostor/tile_size", "is not a multiple of 4");
    info->crop = {0, 0, info->tile_size, info->tile_size};
    if (!impostor.contains("crop")) return;
    if (const json* crop = check.object(impostor, "impostor", "crop")) {
        info->crop.x = check.integer(*crop, "impostor/crop", "x", 0, 4092);
        info->crop.y = check.integer(*crop, "impostor/crop", "y", 0, 4092);
        info->crop.width = check.integer(*crop, "impostor/crop", "width", 4, 4096);
        info->crop.height = check.integer(*crop, "impostor/crop", "height", 4, 4096);
        if ((info->crop.x | info->crop.y | info->crop.width | info->crop.height) % 4)
            check.fail("impostor/crop", "must lie on 4-texel blocks (x, y, width and height multiples of 4)");
    }
}

// The baked views' azimuths and elevations and the baked frames.
void parse_impostor_views(const json& impostor, SchemaCheck& check, ImpostorInfo* info) {
    if (const json* az = check.array(impostor, "impostor", "azimuths_deg", 1))
        for (size_t i = 0; i < az->size(); ++i)
            info->azimuths_deg.push_back(
                float(check.number_value((*az)[i], "impostor/azimuths_deg/" + std::to_string(i), 0, false, 360, true)));
    if (const json* el = check.array(impostor, "impostor", "elevations_deg", 1))
        for (size_t i = 0; i < el->size(); ++i)
            info->elevations_deg.push_back(
                float(check.number_value((*el)[i], "impostor/elevations_deg/" + std::to_string(i), -90, false, 90, false)));
    if (const json* frames = check.array(impostor, "impostor", "frame_indices", 1))
        for (size_t i = 0; i < frames->size(); ++i)
            info->frame_indices.push_back(check.integer_value((*frames)[i], "impostor/frame_indices/" + std::to_string(i), 0));
}

// The bounding sphere and the map paths.
void parse_impostor_bounds_and_maps(const json& impostor, SchemaCheck& check, ImpostorInfo* info) {
    if (const json* bounds = check.object(impostor, "impostor", "bounds")) {
        if (const json* center = check.member(*bounds, "impostor/bounds", "center")) {
            if (!center->is_array() || center->size() != 3)
                check.fail("impostor/bounds/center", "must be an array of 3 numbers");
            else
                for (int i = 0; i < 3; ++i) info->center[i] = float(check.number_value((*center)[i], "impostor/bounds/center/" + std::to_string(i)));
        }
        info->radius = float(check.number(*bounds, "impostor/bounds", "radius", 0, true));
    }
    if (const json* maps = check.object(impostor, "impostor", "maps")) {
        info->normal_map = check.path(*maps, "impostor/maps", "normal");
        info->uv_map = check.path(*maps, "impostor/maps", "uv");
        if (maps->contains("detail")) info->detail_map = check.path(*maps, "impostor/maps", "detail");
        if (maps->contains("surface")) info->surface_map = check.path(*maps, "impostor/maps", "surface");
    }
}

// materials, outfits, meshes, impostor and files, in that order.
void parse_contents(const json& doc, SchemaCheck& check, Manifest* m) {
    const size_t all = SIZE_MAX;
    if (const json* materials = check.array(doc, "", "materials", 1))
        each_object(check, *materials, "materials", all,
                    [&](const json& item, const std::string& where) { m->materials.push_back(parse_material(item, where, check)); });
    if (const json* outfits = check.object(doc, "", "outfits")) {
        m->outfits_file = check.path(*outfits, "outfits", "file");
        m->outfit_count = check.integer(*outfits, "outfits", "count", 1);
        check.integer(*outfits, "outfits", "regions", 16, 16);
    }
    if (const json* meshes = check.array(doc, "", "meshes", 1))
        each_object(check, *meshes, "meshes", all,
                    [&](const json& item, const std::string& where) { m->meshes.push_back(parse_mesh(item, where, check)); });
    if (const json* impostor = check.object(doc, "", "impostor")) {
        parse_impostor_tile(*impostor, check, &m->impostor);
        parse_impostor_views(*impostor, check, &m->impostor);
        parse_impostor_bounds_and_maps(*impostor, check, &m->impostor);
    }
    if (const json* files = check.array(doc, "", "files", 1))
        each_object(check, *files, "files", all,
                    [&](const json& item, const std::string& where) { m->files.push_back(parse_file_entry(item, where, check)); });
}

}  // namespace

Status parse_manifest(const std::string& text, Manifest* out) {
    static const char* fn = "parse_manifest";
    const std::string file = "manifest.json";
    json doc = json::parse(text, nullptr, /*allow_exceptions=*/false);
    if (doc.is_discarded()) return make_error(ErrorCode::manifest_invalid, fn, file, "not JSON (or not UTF-8)");
    if (!doc.is_object()) return make_error(ErrorCode::manifest_invalid, fn, file, "the manifest is not a JSON object");
    // A newer format is named as such even when the rest would not validate against v1.
    if (auto it = doc.find("format_version");
        it != doc.end() && SchemaCheck::is_integer(*it) && it->get<double>() > kFormatVersion)
        return make_error(ErrorCode::unsupported_format_version, fn, file,
                          "format_version " + it->dump() + ", this reader supports " + std::to_string(kFormatVersion));
    SchemaCheck check;
    Manifest m;
    parse_identity(doc, check, &m);
    if (m.format_version == 1) parse_cycle_v1(doc, check, &m);
    else parse_clips_v2(doc, check, &m);
    parse_contents(doc, check, &m);
    if (check.failed()) return make_error(ErrorCode::manifest_invalid, fn, file, check.error());
    *out = std::move(m);
    return {};
}

bool is_safe_path(const std::string& path) {
    if (path.empty() || path.size() > 200 || path == "manifest.json") return false;
    size_t start = 0;
    while (true) {
        const size_t end = std::min(path.find('/', start), path.size());
        const std::string part = path.substr(start, end - start);
        if (part.empty() || part == "." || part == "..") return false;
        for (char c : part)
            if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '.' || c == '_' || c == '-'))
                return false;
        if (end == path.size()) return true;
        start = end + 1;
    }
}

}  // namespace crowdview
