// Layouts of a crowd of several archetypes (crowd_layout.h): dart throwing with a spatial hash.
#include "crowd_layout.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <unordered_map>

#include <glm/gtc/constants.hpp>

namespace crowdview {

namespace {

// Tries per character before a spot/paths square grows (or a scatter gives the character up).
// Random sequential addition at the coverage used here (discs of 0.6 spacing on spacing^2 of
// ground each: about 28%) rarely needs more than a few.
constexpr int kDartTries = 40;
// A spot/paths square grows by this factor when a character finds no room.
constexpr float kGrowth = 1.05f;

struct Placed {
    float x, z, spacing;
};

// Characters already placed, bucketed by a grid whose cell is at least the largest separation,
// so a neighbour that is too close lies in the 3x3 cells around.
class SpatialHash {
public:
    explicit SpatialHash(float cell) : cell_(cell) {}
    bool fits(float x, float z, float spacing) const {
        const int64_t cx = cell_of(x), cz = cell_of(z);
        for (int64_t dz = -1; dz <= 1; ++dz)
            for (int64_t dx = -1; dx <= 1; ++dx) {
                const auto it = cells_.find(key(cx + dx, cz + dz));
                if (it == cells_.end()) continue;
                for (const Placed& p : it->second) {
                    const float d = min_separation(p.spacing, spacing), ex = p.x - x, ez = p.z - z;
                    if (ex * ex + ez * ez < d * d) return false;
                }
            }
        return true;
    }
    void add(float x, float z, float spacing) { cells_[key(cell_of(x), cell_of(z))].push_back({x, z, spacing}); }

private:
    int64_t cell_of(float v) const { return int64_t(std::floor(v / cell_)); }
    static int64_t key(int64_t x, int64_t z) { return (x << 32) ^ (z & 0xffffffff); }
    float cell_;
    std::unordered_map<int64_t, std::vector<Placed>> cells_;
};

Character random_character(Rng& rng, glm::vec3 feet, float heading, const ArchetypeTraits& t) {
    Character c;
    c.start = feet;
    c.heading = heading;
    c.phase_s = rng.uniform(0.0f, std::max(t.cycle_seconds, 0.0f));
    c.variation = rng.below(std::max(t.variations, 1u));
    c.outfit = rng.below(std::max(t.outfits, 1u));
    c.rate = t.play_rate[0] < t.play_rate[1] ? rng.uniform(t.play_rate[0], t.play_rate[1]) : t.play_rate[0];
    return c;
}

}  // namespace

float crowds_half_extent(const std::vector<Crowd>& crowds) {
    float half = 0;
    for (const Crowd& c : crowds) {
        half = std::max(half, c.half_extent);
        for (const Character& ch : c.characters) half = std::max(half, std::max(std::fabs(ch.start.x), std::fabs(ch.start.z)));
    }
    return half;
}

namespace {

// The description's own positions; every crowd's square holds them all.
void place_at_positions(const CrowdLayoutDesc& layout, const std::vector<ArchetypeTraits>& traits, Rng& rng, std::vector<Crowd>* crowds) {
    for (const PlacedCharacter& p : layout.positions) {
        if (p.archetype >= traits.size() || traits[p.archetype].count == 0) continue;
        (*crowds)[p.archetype].characters.push_back(random_character(rng, glm::vec3(p.x, 0, p.z), p.heading_rad, traits[p.archetype]));
    }
    const float half = crowds_half_extent(*crowds);
    for (Crowd& c : *crowds) c.half_extent = half;
}

// One archetype: the grid --bundle has always drawn.
Crowd place_on_grid(const CrowdFile& file, const ArchetypeTraits& t, Layout motion, float walk_speed, Rng& rng) {
    CrowdDesc desc;
    desc.count = uint32_t(t.count);
    desc.seed = file.seed;
    desc.layout = motion;
    desc.spacing = t.spacing;
    desc.walk_speed = walk_speed;
    Crowd crowd = make_crowd(desc, t.variations, t.outfits, t.cycle_seconds);
    if (t.play_rate[0] != 1 || t.play_rate[1] != 1)
        for (Character& c : crowd.characters) c.rate = rng.uniform(t.play_rate[0], std::max(t.play_rate[0], t.play_rate[1]));
    return crowd;
}

// Several archetypes (`present`, largest first), each character thrown at random until it fits:
// within the description's area (scatter: what does not fit is left out, and said in `note`), or
// a square as dense as make_crowd's grid that grows until it does.
void place_by_darts(const CrowdLayoutDesc& layout, const std::vector<ArchetypeTraits>& traits, const std::vector<size_t>& present, Rng& rng,
                    std::vector<Crowd>* crowds, std::string* note) {
    float largest = 0;
    double ground = 0;  // m^2: spacing^2 for each character, the density of make_crowd's grid
    for (size_t k : present) largest = std::max(largest, traits[k].spacing), ground += double(traits[k].count) * traits[k].spacing * traits[k].spacing;
    SpatialHash hash(min_separation(largest, largest));
    const bool scatter = layout.kind == CrowdLayoutKind::scatter;
    glm::vec2 lo = layout.area_min, hi = layout.area_max;
    if (!scatter) {
        const float half = 0.5f * float(std::sqrt(ground));
        lo = glm::vec2(-half), hi = glm::vec2(half);
    }
    uint64_t left_out = 0;
    for (size_t k : present) {
        const ArchetypeTraits& t = traits[k];
        (*crowds)[k].characters.reserve(t.count);
        for (uint64_t i = 0; i < t.count; ++i) {
            bool placed = false;
            while (!placed) {
                for (int attempt = 0; attempt < kDartTries && !placed; ++attempt) {
                    const float x = rng.uniform(lo.x, hi.x), z = rng.uniform(lo.y, hi.y);
                    if (!hash.fits(x, z, t.spacing)) continue;
                    hash.add(x, z, t.spacing);
                    (*crowds)[k].characters.push_back(random_character(rng, glm::vec3(x, 0, z), rng.uniform(0.0f, 2.0f * glm::pi<float>()), t));
                    placed = true;
                }
                if (placed) break;
                if (scatter) {
                    ++left_out;
                    break;
                }
                lo *= kGrowth, hi *= kGrowth;
            }
        }
    }
    if (left_out && note)
        *note = "the scatter area holds " + std::to_string(std::accumulate(present.begin(), present.end(), uint64_t(0),
                                                                          [&](uint64_t s, size_t k) { return s + (*crowds)[k].characters.size(); })) +
                " characters; " + std::to_string(left_out) + " did not fit and are left out";
    const float half = scatter ? crowds_half_extent(*crowds) : hi.x;
    for (Crowd& c : *crowds) c.half_extent = half;
}

std::vector<Crowd> place_characters(const CrowdFile& file, const std::vector<ArchetypeTraits>& traits, std::string* note) {
    std::vector<Crowd> crowds(traits.size());
    const CrowdLayoutDesc& layout = file.layout;
    const Layout motion = layout.kind == CrowdLayoutKind::paths ? Layout::paths : Layout::on_the_spot;
    const float walk_speed = layout.walk_speed > 0 ? layout.walk_speed : 1.3f;
    for (Crowd& c : crowds) c.layout = motion, c.walk_speed = walk_speed;
    Rng rng(file.seed);
    if (layout.kind == CrowdLayoutKind::positions) {
        place_at_positions(layout, traits, rng, &crowds);
        return crowds;
    }
    std::vector<size_t> present;
    for (size_t k = 0; k < traits.size(); ++k)
        if (traits[k].count > 0) present.push_back(k);
    if (present.size() == 1 && layout.kind != CrowdLayoutKind::scatter) {
        crowds[present[0]] = place_on_grid(file, traits[present[0]], motion, walk_speed, rng);
        return crowds;
    }
    std::stable_sort(present.begin(), present.end(), [&](size_t a, size_t b) { return traits[a].spacing > traits[b].spacing; });
    place_by_darts(layout, traits, present, rng, &crowds, note);
    return crowds;
}

}  // namespace

std::vector<Crowd> lay_out_crowd(const CrowdFile& file, const std::vector<ArchetypeTraits>& traits, std::string* note) {
    if (note) note->clear();
    std::vector<Crowd> crowds = place_characters(file, traits, note);
    for (size_t k = 0; k < crowds.size(); ++k) {
        const ArchetypeTraits& t = traits[k];
        crowds[k].clip_plan = t.clip_plan;
        // One schedule stream per archetype of this seed (splitmix64's increment keeps them apart).
        crowds[k].clip_seed = Rng(file.seed + 0x9E3779B97F4A7C15ull * (k + 1)).next();
        std::vector<float> weights = t.clip_plan.weights;
        if (weights.empty()) weights.assign(std::max<size_t>(t.clip_seconds.size(), 1), 1.0f);
        assign_clips(&crowds[k], weights, t.clip_seconds, crowds[k].clip_seed);
    }
    return crowds;
}

}  // namespace crowdview
