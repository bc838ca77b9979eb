// The crowd description: parsed with nlohmann::json, checked by hand against
// shared_formats/crowd.schema.json (no schema engine), every error with its JSON pointer.
#include "crowd_file.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "bundle.h"

namespace crowdview {

namespace {

using nlohmann::json;

// The first problem found, as "<pointer>: <what>"; checks stop at the first one.
struct Checker {
    std::string error;

    bool fail(const std::string& pointer, const std::string& what) {
        if (error.empty()) error = (pointer.empty() ? "/" : pointer) + ": " + what;
        return false;
    }
    static std::string shown(const json& v) {
        std::string text = v.dump();
        if (text.size() > 60) text = text.substr(0, 57) + "...";
        return printable(text);
    }
    // Every key of `object` must be in `allowed`: a misspelt key is an error, not ignored.
    bool keys(const json& object, const std::string& pointer, std::initializer_list<const char*> allowed) {
        for (auto it = object.begin(); it != object.end(); ++it) {
            if (std::none_of(allowed.begin(), allowed.end(), [&](const char* k) { return it.key() == k; })) {
                std::string names;
                for (const char* k : allowed) names += std::string(names.empty() ? "" : ", ") + k;
                return fail(pointer + "/" + printable(it.key()), "unknown key (allowed: " + names + ")");
            }
        }
        return true;
    }
    bool object(const json& v, const std::string& pointer) {
        return v.is_object() || fail(pointer, "must be an object, got " + shown(v));
    }
    bool number(const json& v, const std::string& pointer, double lo, double hi, bool lo_open, double* out) {
        if (!v.is_number()) return fail(pointer, "must be a number, got " + shown(v));
        const double d = v.get<double>();
        if (!(lo_open ? d > lo : d >= lo) || !(d <= hi) || !std::isfinite(d)) {
            std::ostringstream range;
            range << "must be a number " << (lo_open ? "> " : ">= ") << lo << " and <= " << hi << ", got " << shown(v);
            return fail(pointer, range.str());
        }
        *out = d;
        return true;
    }
    bool integer(const json& v, const std::string& pointer, uint64_t lo, uint64_t hi, uint64_t* out) {
        if (!v.is_number_integer() || (v.is_number_integer() && !v.is_number_unsigned() && v.get<int64_t>() < 0) ||
            v.get<uint64_t>() < lo || v.get<uint64_t>() > hi)
            return fail(pointer, "must be a whole number in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got " + shown(v));
        *out = v.get<uint64_t>();
        return true;
    }
    bool string(const json& v, const std::string& pointer, std::string* out) {
        if (!v.is_string() || v.get<std::string>().empty()) return fail(pointer, "must be a non-empty string, got " + shown(v));
        *out = v.get<std::string>();
        return true;
    }
    // A fixed-length array of numbers.
    bool numbers(const json& v, const std::string& pointer, size_t n, float* out) {
        if (!v.is_array() || v.size() != n) return fail(pointer, "must be an array of " + std::to_string(n) + " numbers, got " + shown(v));
        for (size_t i = 0; i < n; ++i) {
            double d = 0;
            if (!number(v[i], pointer + "/" + std::to_string(i), -1e6, 1e6, false, &d)) return false;
            out[i] = float(d);
        }
        return true;
    }
};

// crowdbake's name and version rules (services/crowdbake/params.py NAME_PATTERN, VERSION_PATTERN).
bool is_bundle_name(const std::string& s) {
    if (s.empty() || s.size() > 64 || !(std::islower((unsigned char)s[0]) || std::isdigit((unsigned char)s[0]))) return false;
    return std::all_of(s.begin(), s.end(), [](char c) {
        return std::islower((unsigned char)c) || std::isdigit((unsigned char)c) || c == '.' || c == '_' || c == '-';
    });
}
bool is_bundle_version(const std::string& s) {
    if (s.empty() || s.size() > 64 || !std::isalnum((unsigned char)s[0])) return false;
    return std::all_of(s.begin(), s.end(), [](char c) { return std::isalnum((unsigned char)c) || c == '.' || c == '+' || c == '_' || c == '-'; });
}

std::string folder_of(const std::string& path) {
    const size_t slash = path.find_last_of('/');
    return slash == std::string::npos ? "" : path.substr(0, slash + 1);
}

bool parse_archetype(Checker& c, const json& v, const std::string& p, const std::string& base, ArchetypeDesc* a) {
    if (!c.object(v, p) || !c.keys(v, p, {"name", "bundle", "url", "published", "count", "share", "clips", "play_rate", "switch_after_s"})) return false;
    if (!v.contains("name")) return c.fail(p, "needs \"name\"");
    if (!c.string(v["name"], p + "/name", &a->name)) return false;
    if (a->name.size() > 64 || a->name.find_first_of(" \t\r\n\"\\") != std::string::npos)
        return c.fail(p + "/name", "must be at most 64 characters without spaces, quotes or backslashes");
    const int sources = int(v.contains("bundle")) + int(v.contains("url")) + int(v.contains("published"));
    if (sources != 1) return c.fail(p, "needs exactly one of \"bundle\" (a folder), \"url\" and \"published\", got " + std::to_string(sources));
    if (v.contains("bundle")) {
        if (!c.string(v["bundle"], p + "/bundle", &a->source.folder)) return false;
        if (a->source.folder[0] != '/') a->source.folder = base + a->source.folder;
    } else if (v.contains("url")) {
        if (!c.string(v["url"], p + "/url", &a->source.url)) return false;
        if (a->source.url.find("://") == std::string::npos) return c.fail(p + "/url", "must be an http://, https:// or file:// URL");
    } else {
        const json& pub = v["published"];
        const std::string pp = p + "/published";
        if (!c.object(pub, pp) || !c.keys(pub, pp, {"server", "name", "version"})) return false;
        std::string server, name, version = "latest";
        if (!pub.contains("server") || !pub.contains("name")) return c.fail(pp, "needs \"server\" and \"name\" (\"version\" defaults to latest)");
        if (!c.string(pub["server"], pp + "/server", &server) || !c.string(pub["name"], pp + "/name", &name)) return false;
        if (pub.contains("version") && !c.string(pub["version"], pp + "/version", &version)) return false;
        if (server.find("://") == std::string::npos) return c.fail(pp + "/server", "must be a URL such as http://host:8000");
        if (!is_bundle_name(name)) return c.fail(pp + "/name", "is not a bundle name ([a-z0-9][a-z0-9._-]{0,63})");
        if (!is_bundle_version(version)) return c.fail(pp + "/version", "is not a version or latest ([0-9A-Za-z][0-9A-Za-z.+_-]{0,63})");
        a->source.url = published_bundle_url(server, name, version);
    }
    // Neither is checked with the counts (parse_crowd_description): a positions layout takes neither.
    if (v.contains("count") && v.contains("share")) return c.fail(p, "gives both: needs exactly one of \"count\" and \"share\"");
    if (v.contains("count") && !c.integer(v["count"], p + "/count", 1, kMaxCrowdCount, &a->count)) return false;
    if (v.contains("share") && !c.number(v["share"], p + "/share", 0, 1e9, true, &a->share)) return false;
    if (v.contains("clips")) {
        const json& clips = v["clips"];
        if (!clips.is_array() || clips.empty()) return c.fail(p + "/clips", "must be a non-empty array of {\"clip\", \"weight\"}");
        for (size_t k = 0; k < clips.size(); ++k) {
            const std::string cp = p + "/clips/" + std::to_string(k);
            ClipWeight w;
            double weight = 1;
            if (!c.object(clips[k], cp) || !c.keys(clips[k], cp, {"clip", "weight"})) return false;
            if (!clips[k].contains("clip")) return c.fail(cp, "needs \"clip\"");
            if (!c.string(clips[k]["clip"], cp + "/clip", &w.clip)) return false;
            if (clips[k].contains("weight") && !c.number(clips[k]["weight"], cp + "/weight", 0, 1e6, true, &weight)) return false;
            w.weight = float(weight);
            a->clips.push_back(w);
        }
    }
    if (v.contains("play_rate")) {
        if (!c.numbers(v["play_rate"], p + "/play_rate", 2, a->play_rate)) return false;
        // A quarter to four times: beyond that a walk cycle reads as a different gait, not variety.
        for (int k = 0; k < 2; ++k)
            if (!(a->play_rate[k] >= 0.25f && a->play_rate[k] <= 4.0f))
                return c.fail(p + "/play_rate/" + std::to_string(k), "must lie in [0.25, 4]");
        if (a->play_rate[0] > a->play_rate[1]) return c.fail(p + "/play_rate", "must be [low, high] with low <= high");
    }
    if (v.contains("switch_after_s")) {
        if (!c.numbers(v["switch_after_s"], p + "/switch_after_s", 2, a->switch_after_s)) return false;
        for (int k = 0; k < 2; ++k)
            if (!(a->switch_after_s[k] >= 0.0f && a->switch_after_s[k] <= 86400.0f))
                return c.fail(p + "/switch_after_s/" + std::to_string(k), "must lie in [0, 86400] seconds");
        if (a->switch_after_s[0] > a->switch_after_s[1]) return c.fail(p + "/switch_after_s", "must be [low, high] with low <= high");
        a->has_switch_after = true;
    }
    return true;
}

bool parse_layout(Checker& c, const json& v, const std::vector<ArchetypeDesc>& archetypes, CrowdLayoutDesc* out) {
    const std::string p = "/layout";
    if (!c.object(v, p)) return false;
    std::string kind;
    if (!v.contains("kind")) return c.fail(p, "needs \"kind\": spot, paths, positions or scatter");
    if (!c.string(v["kind"], p + "/kind", &kind)) return false;
    if (kind == "spot") {
        out->kind = CrowdLayoutKind::spot;
        return c.keys(v, p, {"kind"});
    }
    if (kind == "paths") {
        out->kind = CrowdLayoutKind::paths;
        double speed = 1.3;
        if (!c.keys(v, p, {"kind", "walk_speed"})) return false;
        if (v.contains("walk_speed") && !c.number(v["walk_speed"], p + "/walk_speed", 0, 20, true, &speed)) return false;
        out->walk_speed = float(speed);
        return true;
    }
    if (kind == "scatter") {
        out->kind = CrowdLayoutKind::scatter;
        if (!c.keys(v, p, {"kind", "area"})) return false;
        if (!v.contains("area")) return c.fail(p, "a scatter needs \"area\": {\"min\": [x, z], \"max\": [x, z]} in metres");
        const json& area = v["area"];
        if (!c.object(area, p + "/area") || !c.keys(area, p + "/area", {"min", "max"})) return false;
        if (!area.contains("min") || !area.contains("max")) return c.fail(p + "/area", "needs \"min\" and \"max\"");
        if (!c.numbers(area["min"], p + "/area/min", 2, &out->area_min.x) || !c.numbers(area["max"], p + "/area/max", 2, &out->area_max.x))
            return false;
        if (!(out->area_max.x > out->area_min.x && out->area_max.y > out->area_min.y))
            return c.fail(p + "/area", "max must exceed min on both axes");
        return true;
    }
    if (kind == "positions") {
        out->kind = CrowdLayoutKind::positions;
        if (!c.keys(v, p, {"kind", "positions"})) return false;
        if (!v.contains("positions") || !v["positions"].is_array() || v["positions"].empty())
            return c.fail(p + "/positions", "must be a non-empty array of {\"archetype\", \"at\": [x, z], \"heading_deg\"}");
        const json& list = v["positions"];
        if (list.size() > kMaxCrowdCount) return c.fail(p + "/positions", "holds more than " + std::to_string(kMaxCrowdCount) + " entries");
        for (size_t k = 0; k < list.size(); ++k) {
            const std::string ep = p + "/positions/" + std::to_string(k);
            if (!c.object(list[k], ep) || !c.keys(list[k], ep, {"archetype", "at", "heading_deg"})) return false;
            std::string name;
            if (!list[k].contains("archetype") || !list[k].contains("at")) return c.fail(ep, "needs \"archetype\" and \"at\"");
            if (!c.string(list[k]["archetype"], ep + "/archetype", &name)) return false;
            const auto it = std::find_if(archetypes.begin(), archetypes.end(), [&](const ArchetypeDesc& a) { return a.name == name; });
            if (it == archetypes.end()) return c.fail(ep + "/archetype", "names no archetype: \"" + printable(name) + "\"");
            PlacedCharacter placed;
            placed.archetype = uint32_t(it - archetypes.begin());
            float at[2];
            if (!c.numbers(list[k]["at"], ep + "/at", 2, at)) return false;
            placed.x = at[0], placed.z = at[1];
            double heading = 0;
            if (list[k].contains("heading_deg") && !c.number(list[k]["heading_deg"], ep + "/heading_deg", -3600, 3600, false, &heading))
                return false;
            placed.heading_rad = float(heading * 3.14159265358979323846 / 180.0);
            out->positions.push_back(placed);
        }
        return true;
    }
    return c.fail(p + "/kind", "must be spot, paths, positions or scatter, got " + Checker::shown(v["kind"]));
}

bool parse_camera(Checker& c, const json& v, CrowdCameraDesc* out) {
    const std::string p = "/camera";
    if (!c.object(v, p) || !c.keys(v, p, {"kind", "eye", "target", "fov_deg"})) return false;
    std::string kind = "overview";
    if (v.contains("kind") && !c.string(v["kind"], p + "/kind", &kind)) return false;
    if (kind == "overview") out->kind = CrowdCameraKind::overview;
    else if (kind == "street") out->kind = CrowdCameraKind::street;
    else if (kind == "look_at") out->kind = CrowdCameraKind::look_at;
    else return c.fail(p + "/kind", "must be overview, street or look_at, got " + Checker::shown(v["kind"]));
    const bool look = out->kind == CrowdCameraKind::look_at;
    if (look != (v.contains("eye") && v.contains("target")) || (!look && (v.contains("eye") || v.contains("target"))))
        return c.fail(p, look ? "look_at needs \"eye\" and \"target\" ([x, y, z] metres)" : "\"eye\" and \"target\" go with kind look_at");
    if (look && (!c.numbers(v["eye"], p + "/eye", 3, &out->eye.x) || !c.numbers(v["target"], p + "/target", 3, &out->target.x)))
        return false;
    if (look && glm::length(out->target - out->eye) < 1e-3f) return c.fail(p + "/target", "must differ from eye");
    double fov = 45;
    if (v.contains("fov_deg") && !c.number(v["fov_deg"], p + "/fov_deg", 1, 170, false, &fov)) return false;
    out->fov_deg = float(fov);
    return true;
}

// With a positions layout each archetype's count is its number of entries: "count" may be left
// out, and where given must say the same; a "share" has nothing to split and is accepted as the
// format's first files wrote one.
bool check_positions_counts(Checker& c, const CrowdFile& crowd) {
    std::vector<uint64_t> placed(crowd.archetypes.size(), 0);
    for (const PlacedCharacter& p : crowd.layout.positions) ++placed[p.archetype];
    for (size_t k = 0; k < crowd.archetypes.size(); ++k) {
        const ArchetypeDesc& a = crowd.archetypes[k];
        if (a.count > 0 && a.count != placed[k])
            return c.fail("/archetypes/" + std::to_string(k) + "/count",
                          "is " + std::to_string(a.count) + " but /layout/positions places " + std::to_string(placed[k]) + " of \"" +
                              printable(a.name) + "\": with a positions layout an archetype's count is its number of entries; leave \"count\" out");
    }
    return true;
}

}  // namespace

std::string published_bundle_url(const std::string& server, const std::string& name, const std::string& version) {
    std::string base = server;
    while (!base.empty() && base.back() == '/') base.pop_back();
    return base + "/v1/bundles/" + name + "/" + version;
}

std::string parse_crowd_description(const std::string& text, const std::string& path, CrowdFile* out) {
    *out = CrowdFile();
    const std::string where = printable(path) + ": ";
    json doc;
    try {
        doc = json::parse(text);
    } catch (const json::parse_error& e) {
        return where + "not JSON: " + printable(e.what());
    }
    Checker c;
    const auto finish = [&](bool) { return c.error.empty() ? std::string() : where + c.error; };
    if (!c.object(doc, "") ||
        !c.keys(doc, "", {"$schema", "crowd_format_version", "seed", "count", "archetypes", "layout", "camera"}))
        return finish(false);
    uint64_t version = 0;
    if (!doc.contains("crowd_format_version")) return finish(c.fail("", "needs \"crowd_format_version\": 1"));
    if (!c.integer(doc["crowd_format_version"], "/crowd_format_version", 0, UINT32_MAX, &version)) return finish(false);
    if (version != kCrowdFormatVersion)
        return finish(c.fail("/crowd_format_version", "this crowdview reads version 1, the file is version " + std::to_string(version)));
    if (doc.contains("seed") && !c.integer(doc["seed"], "/seed", 0, uint64_t(1) << 53, &out->seed)) return finish(false);
    if (doc.contains("count") && !c.integer(doc["count"], "/count", 1, kMaxCrowdCount, &out->count)) return finish(false);
    if (!doc.contains("archetypes") || !doc["archetypes"].is_array() || doc["archetypes"].empty())
        return finish(c.fail("/archetypes", "must be a non-empty array"));
    const json& list = doc["archetypes"];
    if (list.size() > kMaxArchetypes) return finish(c.fail("/archetypes", "holds " + std::to_string(list.size()) + ", at most " +
                                                                          std::to_string(kMaxArchetypes)));
    const std::string base = folder_of(path);
    std::set<std::string> names;
    for (size_t k = 0; k < list.size(); ++k) {
        ArchetypeDesc a;
        const std::string p = "/archetypes/" + std::to_string(k);
        if (!parse_archetype(c, list[k], p, base, &a)) return finish(false);
        if (!names.insert(a.name).second) return finish(c.fail(p + "/name", "\"" + printable(a.name) + "\" is used twice"));
        out->archetypes.push_back(a);
    }
    if (doc.contains("layout") && !parse_layout(c, doc["layout"], out->archetypes, &out->layout)) return finish(false);
    if (doc.contains("camera") && !parse_camera(c, doc["camera"], &out->camera)) return finish(false);

    if (out->layout.kind == CrowdLayoutKind::positions) return finish(check_positions_counts(c, *out));
    // Otherwise counts and shares against "count".
    uint64_t fixed = 0;
    bool any_share = false;
    for (size_t k = 0; k < out->archetypes.size(); ++k) {
        const ArchetypeDesc& a = out->archetypes[k];
        if (a.count == 0 && a.share <= 0)
            return finish(c.fail("/archetypes/" + std::to_string(k), "needs one of \"count\" and \"share\" (a positions layout, which counts "
                                                                      "each archetype's entries, takes neither)"));
        fixed += a.count;
        any_share = any_share || a.share > 0;
    }
    if (any_share && out->count == 0) return finish(c.fail("", "an archetype gives a share: the crowd needs \"count\""));
    if (out->count > 0 && fixed > out->count)
        return finish(c.fail("/count", "is " + std::to_string(out->count) + " but the archetypes' counts add up to " + std::to_string(fixed)));
    if (fixed > kMaxCrowdCount) return finish(c.fail("/archetypes", "counts add up to more than " + std::to_string(kMaxCrowdCount)));
    return "";
}

std::string load_crowd_description(const std::string& path, CrowdFile* out) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return printable(path) + ": cannot read the crowd description";
    std::stringstream ss;
    ss << in.rdbuf();
    return parse_crowd_description(ss.str(), path, out);
}

std::vector<uint64_t> archetype_counts(const CrowdFile& crowd) {
    const size_t n = crowd.archetypes.size();
    std::vector<uint64_t> counts(n, 0);
    if (crowd.layout.kind == CrowdLayoutKind::positions) {
        for (const PlacedCharacter& p : crowd.layout.positions) ++counts[p.archetype];
        return counts;
    }
    uint64_t fixed = 0;
    double shares = 0;
    for (size_t k = 0; k < n; ++k) counts[k] = crowd.archetypes[k].count, fixed += counts[k], shares += crowd.archetypes[k].share;
    if (shares <= 0 || crowd.count <= fixed) return counts;
    // Largest remainder: floor each quota, then hand the leftover one by one to the largest fractions.
    const uint64_t rest = crowd.count - fixed;
    std::vector<std::pair<double, size_t>> remainders;
    uint64_t given = 0;
    for (size_t k = 0; k < n; ++k) {
        if (crowd.archetypes[k].share <= 0) continue;
        const double quota = double(rest) * crowd.archetypes[k].share / shares;
        counts[k] = uint64_t(std::floor(quota));
        given += counts[k];
        remainders.push_back({quota - std::floor(quota), k});
    }
    std::stable_sort(remainders.begin(), remainders.end(), [](const auto& a, const auto& b) { return a.first > b.first; });
    for (size_t i = 0; given < rest; ++i, ++given) ++counts[remainders[i % remainders.size()].second];
    return counts;
}

CrowdFile single_archetype_crowd(const ArchetypeSource& source, uint64_t count, uint64_t seed, bool paths) {
    CrowdFile crowd;
    crowd.seed = seed;
    crowd.count = count;
    ArchetypeDesc a;
    const std::string& where = source.is_url() ? source.url : source.folder;
    std::string name = where;
    while (!name.empty() && name.back() == '/') name.pop_back();
    a.name = name.empty() ? "bundle" : name;
    a.source = source;
    a.count = count;
    crowd.archetypes.push_back(a);
    crowd.layout.kind = paths ? CrowdLayoutKind::paths : CrowdLayoutKind::spot;
    return crowd;
}

}  // namespace crowdview
