// Command-line values for crowdview's main.cpp: numbers in a range and named choices, or a usage
// error (cli_options.cpp's usage_error: one line, exit 2).
#pragma once

#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <initializer_list>
#include <string>
#include <type_traits>
#include <utility>

namespace {

[[noreturn]] void usage_error(const std::string& message);

template <typename T>
T parse_number(const std::string& flag, const char* text, T lo, T hi) {
    char* end = nullptr;
    errno = 0;
    const double v = std::strtod(text, &end);
    if (errno || end == text || *end || !(v >= double(lo) && v <= double(hi)))
        usage_error(flag + " needs a number in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got '" + text + "'");
    if (std::is_integral<T>::value && std::floor(v) != v) usage_error(flag + " needs a whole number, got '" + text + "'");
    return T(v);
}

// `text` as one of `choices` (name, value), or a usage error listing them.
template <typename E>
E parse_choice(const std::string& flag, const std::string& text, std::initializer_list<std::pair<const char*, E>> choices) {
    std::string names;
    for (const auto& [name, value] : choices) {
        if (text == name) return value;
        names += std::string(names.empty() ? "" : ", ") + name;
    }
    usage_error(flag + " is one of " + names + "; got '" + text + "'");
}

}  // namespace
