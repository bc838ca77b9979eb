// A few assertion macros for the runtime's tests: each failure prints where and what, and
// the test's main returns the failure count (ctest reads a non-zero exit as failure).
#pragma once

#include <cmath>
#include <cstdio>
#include <string>

namespace check {
inline int& failures() {
    static int count = 0;
    return count;
}
inline int& total() {
    static int count = 0;
    return count;
}
inline int exit_code() {
    if (failures()) std::fprintf(stderr, "%d of %d checks failed\n", failures(), total());
    else std::fprintf(stderr, "all %d checks passed\n", total());
    return failures() ? 1 : 0;
}
}  // namespace check

#define CHECK(condition)                                                                   \
    do {                                                                                   \
        ++check::total();                                                                  \
        if (!(condition)) {                                                                \
            std::fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #condition); \
            ++check::failures();                                                           \
        }                                                                                  \
    } while (0)

#define CHECK_MSG(condition, message)                                                       \
    do {                                                                                    \
        ++check::total();                                                                   \
        if (!(condition)) {                                                                 \
            std::fprintf(stderr, "%s:%d: CHECK failed: %s: %s\n", __FILE__, __LINE__, #condition, \
                         std::string(message).c_str());                                     \
            ++check::failures();                                                            \
        }                                                                                   \
    } while (0)

#define CHECK_NEAR(a, b, tolerance)                                                                        \
    do {                                                                                                   \
        const double check_a = double(a), check_b = double(b);                                             \
        ++check::total();                                                                                  \
        if (!(std::fabs(check_a - check_b) <= double(tolerance))) {                                        \
            std::fprintf(stderr, "%s:%d: CHECK_NEAR failed: %s = %.9g, %s = %.9g, tolerance %.3g\n", __FILE__, \
                         __LINE__, #a, check_a, #b, check_b, double(tolerance));                           \
            ++check::failures();                                                                           \
        }                                                                                                  \
    } while (0)
