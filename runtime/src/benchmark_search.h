// The figure 3 benchmark's search (benchmark.h): the largest crowd that holds a frame rate, from
// probes that are measured again near the threshold, so that one slow frame (other work on the
// machine) cannot end a search. No GL: the caller measures.
#pragma once

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <vector>

#include <nlohmann/json.hpp>

namespace crowdview {

// One measurement of a crowd of n characters.
struct Sample {
    uint32_t n = 0;
    double fps = 0;         // from the fastest timed frame: what the machine does undisturbed
    double fps_median = 0;  // from the median frame: includes whatever else the machine ran
    double cpu_ms = 0;      // median CPU time of this process per frame, all threads (llvmpipe
                            // renders on the CPU): the cost, whatever else the machine ran
    uint32_t by_lod[3] = {0, 0, 0};
    bool cut_short = false;  // the deadline ended it before its usual frame count (fewer timed frames)
    double seconds = 0;      // the measurement's wall time, warm-up included
};

// A probe is measured again, up to kProbeRuns runs, while its figure fails the target or holds it
// by less than kConfirmMargin: a run slowed by other work must not end the search, nor one lucky
// run pass a size. Once, on an idle machine, one run at N = 32 took 33.7 ms a frame where N = 30
// took 14.9 ms and ended a 30 fps search; figures of the same machine varied 30 against 76.
constexpr size_t kProbeRuns = 3;
constexpr double kConfirmMargin = 1.25;

// Every run at one crowd size. The figure is the median of the runs that count: the complete ones
// (a run cut short by the deadline times one or two frames), or every run where none is complete.
struct Probe {
    std::vector<Sample> runs;

    std::vector<Sample> counted() const;
    double fps() const;  // median of the counted runs' fps; 0 without runs
    double fps_min() const;  // the spread of the counted runs
    double fps_max() const;
    bool cut_short() const;  // a run was cut short
    nlohmann::json to_json(uint32_t n) const;  // n, fps (the median), fps_min, fps_max, runs, runs_cut_short, ...
};

// How long a measurement of n characters is predicted to take, from one of m that took `seconds`:
// in proportion above m, as long below it (a measurement takes half a second at least).
struct MeasureCost {
    double seconds = 0;  // 0: nothing measured yet, predicts 0
    uint32_t n = 1;

    double predict(uint32_t count) const { return seconds * std::max(1.0, double(count) / double(std::max(n, 1u))); }
};

// The search of one representation: probes by crowd size, shared by its 30 and 60 fps searches.
class ProbeSearch {
public:
    using Clock = std::chrono::steady_clock;
    using Measure = std::function<Sample(uint32_t n)>;

    // New probes and repeats start where they are predicted to end before `deadline` (this
    // phase's share of the run), except the first probe of a search, which needs only to end
    // before `run_end` (so a phase that inherits little time still reports a figure). The
    // prediction: MeasureCost of the last measurement.
    ProbeSearch(Measure measure, Clock::time_point deadline, Clock::time_point run_end);

    // The largest n whose probe holds `target` fps: N doubles from 8 (or from the largest size
    // known to hold) until a probe fails, then bisects to 5 %. converged: the bracket closed in
    // time. 0 when no size holds or none could be measured.
    uint32_t largest_holding(double target, bool* converged);

    const std::map<uint32_t, Probe>& probes() const { return probes_; }
    const MeasureCost& last_cost() const { return last_cost_; }
    bool cut_short() const;  // a run was cut short by the deadline
    nlohmann::json probes_json() const;

private:
    // Measures n if it has no run yet (the caller checked the time), and again while its figure is
    // below `target` or within kConfirmMargin of it, before the deadline: whether it holds `target`.
    bool holds(uint32_t n, double target);
    bool fits(uint32_t n, Clock::time_point limit) const;  // a measurement of n predicted to end before `limit`
    Sample measured(uint32_t n);
    // From the probes so far: lo the largest size that holds (0: none), hi the smallest that fails (0: none).
    void bracket_from_probes(double target, uint32_t* lo, uint32_t* hi);

    Measure measure_;
    Clock::time_point deadline_, run_end_;
    std::map<uint32_t, Probe> probes_;
    MeasureCost last_cost_;
};

}  // namespace crowdview
