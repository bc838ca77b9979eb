// The figure 3 benchmark's search (benchmark_search.h).
#include "benchmark_search.h"

#include <algorithm>
#include <cmath>
#include <iterator>
#include <utility>

namespace crowdview {

namespace {

constexpr uint32_t kFirstCount = 8;
constexpr uint32_t kMaxCount = 1u << 20;  // a million characters bounds the doubling

std::vector<double> of_runs(const std::vector<Sample>& runs, double Sample::*field) {
    std::vector<double> values;
    for (const Sample& s : runs) values.push_back(s.*field);
    return values;
}

double median(std::vector<double> values) {
    if (values.empty()) return 0;
    std::sort(values.begin(), values.end());
    const size_t mid = values.size() / 2;
    return values.size() % 2 ? values[mid] : 0.5 * (values[mid - 1] + values[mid]);
}

// To `decimals` places, as the nearest double to the decimal (dividing, not multiplying by 0.1).
double rounded(double value, int decimals) {
    const double scale = std::pow(10.0, decimals);
    return std::round(value * scale) / scale;
}

// Bisection stops within 5 % (or 1 character) of the answer.
bool bracket_closed(uint32_t lo, uint32_t hi) { return hi - lo <= std::max(1u, lo / 20); }

}  // namespace

std::vector<Sample> Probe::counted() const {
    std::vector<Sample> complete;
    std::copy_if(runs.begin(), runs.end(), std::back_inserter(complete), [](const Sample& s) { return !s.cut_short; });
    return complete.empty() ? runs : complete;
}

double Probe::fps() const { return median(of_runs(counted(), &Sample::fps)); }

double Probe::fps_min() const {
    const std::vector<double> v = of_runs(counted(), &Sample::fps);
    return v.empty() ? 0 : *std::min_element(v.begin(), v.end());
}

double Probe::fps_max() const {
    const std::vector<double> v = of_runs(counted(), &Sample::fps);
    return v.empty() ? 0 : *std::max_element(v.begin(), v.end());
}

bool Probe::cut_short() const {
    return std::any_of(runs.begin(), runs.end(), [](const Sample& s) { return s.cut_short; });
}

nlohmann::json Probe::to_json(uint32_t n) const {
    return {{"n", n},
            {"fps", rounded(fps(), 1)},
            {"fps_min", rounded(fps_min(), 1)},
            {"fps_max", rounded(fps_max(), 1)},
            {"runs", runs.size()},
            {"runs_cut_short", std::count_if(runs.begin(), runs.end(), [](const Sample& s) { return s.cut_short; })},
            {"fps_median", rounded(median(of_runs(counted(), &Sample::fps_median)), 1)},
            {"cpu_ms_per_frame", rounded(median(of_runs(counted(), &Sample::cpu_ms)), 2)}};
}

ProbeSearch::ProbeSearch(Measure measure, Clock::time_point deadline, Clock::time_point run_end)
    : measure_(std::move(measure)), deadline_(std::min(deadline, run_end)), run_end_(run_end) {}

Sample ProbeSearch::measured(uint32_t n) {
    Sample s = measure_(n);
    last_cost_ = {s.seconds, n};
    return s;
}

bool ProbeSearch::fits(uint32_t n, Clock::time_point limit) const {
    const auto predicted = std::chrono::duration<double>(last_cost_.predict(n));
    return Clock::now() + std::chrono::duration_cast<Clock::duration>(predicted) < limit;
}

bool ProbeSearch::holds(uint32_t n, double target) {
    auto it = probes_.find(n);
    if (it == probes_.end()) it = probes_.emplace(n, Probe{{measured(n)}}).first;
    Probe& probe = it->second;
    while (probe.runs.size() < kProbeRuns && probe.fps() < target * kConfirmMargin && fits(n, deadline_))
        probe.runs.push_back(measured(n));
    return probe.fps() >= target;
}

void ProbeSearch::bracket_from_probes(double target, uint32_t* lo, uint32_t* hi) {
    *lo = 0, *hi = 0;
    for (const auto& entry : probes_) {  // holds() adds runs to known sizes, never a size: the iteration stays valid
        const uint32_t n = entry.first;
        if (holds(n, target)) *lo = std::max(*lo, n);
        else if (*hi == 0 || n < *hi) *hi = n;
    }
    if (*hi != 0 && *lo > *hi) *lo = 0;  // sizes that disagree even after their repeats: trust the failing one
}

uint32_t ProbeSearch::largest_holding(double target, bool* converged) {
    uint32_t lo = 0, hi = 0;
    bracket_from_probes(target, &lo, &hi);
    if (hi == 0) {
        const uint32_t first = std::max(lo * 2, kFirstCount);
        for (uint32_t n = first; n <= kMaxCount && fits(n, n == first ? run_end_ : deadline_); n *= 2) {
            if (!holds(n, target)) {
                hi = n;
                break;
            }
            lo = n;
        }
    }
    if (hi == 0) {
        *converged = false;
        return lo;
    }
    while (!bracket_closed(lo, hi) && fits(lo + (hi - lo) / 2, deadline_)) {
        const uint32_t mid = lo + (hi - lo) / 2;
        (holds(mid, target) ? lo : hi) = mid;
    }
    *converged = bracket_closed(lo, hi);
    return lo;
}

bool ProbeSearch::cut_short() const {
    return std::any_of(probes_.begin(), probes_.end(), [](const auto& entry) { return entry.second.cut_short(); });
}

nlohmann::json ProbeSearch::probes_json() const {
    nlohmann::json list = nlohmann::json::array();
    for (const auto& [n, probe] : probes_) list.push_back(probe.to_json(n));
    return list;
}

}  // namespace crowdview
