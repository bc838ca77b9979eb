// Fetch over libcurl into a sha256-addressed cache: download to a .part file, verify, rename.
#include "fetch.h"

#include <curl/curl.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <climits>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <mutex>

namespace crowdview {

// Redirects one request may follow. The service answers with at most two in a row (`latest` to the
// concrete version, then a file to its presigned object-store URL); 5 leaves room for a proxy or
// CDN hop. Without a limit (libcurl before 8.3 follows any number) a redirect loop makes about 2,000
// requests in 0.4 s and stops only at libcurl's cap on header bytes, with a confusing message.
constexpr long kMaxRedirects = 5;

BundleUrls bundle_urls(const std::string& url, const std::string& files_prefix) {
    BundleUrls urls;
    std::string base = url;
    const std::string manifest = "manifest.json";
    if (base.size() >= manifest.size() && base.compare(base.size() - manifest.size(), manifest.size(), manifest) == 0 &&
        (base.size() == manifest.size() || base[base.size() - manifest.size() - 1] == '/'))
        base.erase(base.size() - manifest.size());
    if (base.empty() || base.back() != '/') base += '/';
    urls.base = base;
    urls.files_prefix = files_prefix;
    if (!urls.files_prefix.empty() && urls.files_prefix.back() != '/') urls.files_prefix += '/';
    return urls;
}

std::string default_cache_dir() {
    if (const char* xdg = std::getenv("XDG_CACHE_HOME"); xdg && *xdg) return std::string(xdg) + "/crowdview";
    if (const char* home = std::getenv("HOME"); home && *home) return std::string(home) + "/.cache/crowdview";
    return ".crowdview-cache";
}

std::string cache_blob_path(const std::string& cache_dir, const std::string& sha256) {
    return cache_dir + "/blobs/" + sha256.substr(0, 2) + "/" + sha256;
}

namespace {

bool make_dirs(const std::string& path) {
    for (size_t i = 1; i <= path.size(); ++i)
        if (i == path.size() || path[i] == '/') {
            const std::string prefix = path.substr(0, i);
            if (mkdir(prefix.c_str(), 0755) != 0 && errno != EEXIST) return false;
        }
    return true;
}

int64_t file_size_or_minus_one(const std::string& path) {
    struct stat info;
    return stat(path.c_str(), &info) == 0 && S_ISREG(info.st_mode) ? int64_t(info.st_size) : -1;
}

// Where one transfer writes: a memory buffer or an open file, never beyond `limit` bytes.
struct Sink {
    std::vector<uint8_t>* memory = nullptr;
    FILE* file = nullptr;
    uint64_t written = 0;
    uint64_t limit = 0;
    bool over_limit = false;
};

size_t write_sink(char* data, size_t size, size_t count, void* user) {
    Sink* sink = static_cast<Sink*>(user);
    const size_t n = size * count;
    if (sink->written + n > sink->limit) {  // more bytes than the manifest promised: stop now
        sink->over_limit = true;
        return 0;
    }
    if (sink->memory) sink->memory->insert(sink->memory->end(), data, data + n);
    if (sink->file && std::fwrite(data, 1, n, sink->file) != n) return 0;
    sink->written += n;
    return n;
}

enum class Transfer { ok, not_found, unauthorized, range_refused, too_large, deadline, too_many_redirects, failed };

using Clock = std::chrono::steady_clock;

Clock::time_point after_seconds(Clock::time_point start, double seconds) {
    // Clamp: a huge deadline must not overflow the clock's integer ticks.
    return start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(std::min(seconds, 1e9)));
}

struct Request {
    std::string url;
    uint64_t resume_from = 0;
    Clock::time_point deadline;  // the transfer is abandoned (Transfer::deadline) here
    const FetchOptions* options = nullptr;
};

// One GET of `request.url` into `sink`.
Transfer http_get(const Request& request, Sink* sink, std::string* error) {
    static std::once_flag init;
    std::call_once(init, [] { curl_global_init(CURL_GLOBAL_DEFAULT); });
    const long long left_ms =
        std::chrono::duration_cast<std::chrono::milliseconds>(request.deadline - Clock::now()).count();
    if (left_ms <= 0) {
        *error = "deadline passed";
        return Transfer::deadline;
    }
    CURL* curl = curl_easy_init();
    if (!curl) {
        *error = "curl_easy_init failed";
        return Transfer::failed;
    }
    const FetchOptions& options = *request.options;
    char curl_error[CURL_ERROR_SIZE] = "";
    curl_easy_setopt(curl, CURLOPT_URL, request.url.c_str());
    curl_easy_setopt(curl, CURLOPT_FOLLOWLOCATION, 1L);
    curl_easy_setopt(curl, CURLOPT_MAXREDIRS, kMaxRedirects);
    curl_easy_setopt(curl, CURLOPT_FAILONERROR, 1L);
    curl_easy_setopt(curl, CURLOPT_CONNECTTIMEOUT, options.connect_timeout_s);
    // A stalled server (under 1 byte/s for 30 s) counts as an interrupted transfer, resumed;
    // a slow one is bounded by the deadline, which is not.
    curl_easy_setopt(curl, CURLOPT_LOW_SPEED_LIMIT, 1L);
    curl_easy_setopt(curl, CURLOPT_LOW_SPEED_TIME, 30L);
    curl_easy_setopt(curl, CURLOPT_TIMEOUT_MS, long(std::min<long long>(left_ms, LONG_MAX)));
    if (!options.api_key.empty()) {
        // libcurl's own bearer support, unlike a custom header, is not sent on to another host
        // after a redirect.
        curl_easy_setopt(curl, CURLOPT_HTTPAUTH, CURLAUTH_BEARER);
        curl_easy_setopt(curl, CURLOPT_XOAUTH2_BEARER, options.api_key.c_str());
    }
    curl_easy_setopt(curl, CURLOPT_WRITEFUNCTION, write_sink);
    curl_easy_setopt(curl, CURLOPT_WRITEDATA, sink);
    curl_easy_setopt(curl, CURLOPT_ERRORBUFFER, curl_error);
    curl_easy_setopt(curl, CURLOPT_NOSIGNAL, 1L);
    if (request.resume_from > 0) curl_easy_setopt(curl, CURLOPT_RESUME_FROM_LARGE, curl_off_t(request.resume_from));
    const CURLcode code = curl_easy_perform(curl);
    long http_status = 0;
    curl_easy_getinfo(curl, CURLINFO_RESPONSE_CODE, &http_status);
    std::string last_url;
    if (const char* effective = nullptr; curl_easy_getinfo(curl, CURLINFO_EFFECTIVE_URL, &effective) == CURLE_OK && effective)
        last_url = effective;
    curl_easy_cleanup(curl);
    if (code == CURLE_OK) return Transfer::ok;
    if (code == CURLE_TOO_MANY_REDIRECTS) {  // a loop, or a chain no real server makes: not retried
        *error = "more than " + std::to_string(kMaxRedirects) + " redirects (a redirect loop?); the last one went to " + last_url;
        return Transfer::too_many_redirects;
    }
    *error = curl_error[0] ? curl_error : curl_easy_strerror(code);
    if (sink->over_limit) return Transfer::too_large;
    // CURLE_OPERATION_TIMEDOUT is also the stall rule; only the clock tells them apart.
    if (code == CURLE_OPERATION_TIMEDOUT && Clock::now() + std::chrono::milliseconds(50) >= request.deadline)
        return Transfer::deadline;
    const bool http_error = code == CURLE_HTTP_RETURNED_ERROR;
    if (code == CURLE_FILE_COULDNT_READ_FILE || (http_error && (http_status == 404 || http_status == 410)))
        return Transfer::not_found;
    if (http_error && (http_status == 401 || http_status == 403)) {
        *error = "HTTP " + std::to_string(http_status) +
                 (options.api_key.empty() ? ": the server wants an API key (--key or CROWDVIEW_API_KEY)"
                                          : ": the server refused the API key");
        return Transfer::unauthorized;
    }
    // 416: the server's file is no longer than our partial one; CURLE_RANGE_ERROR: no Range support.
    if (code == CURLE_RANGE_ERROR || (http_error && http_status == 416)) return Transfer::range_refused;
    return Transfer::failed;
}

std::string seconds_text(double s) {
    char text[32];
    std::snprintf(text, sizeof text, "%.0f", s);
    return text;
}

// "the total fetch deadline ... passed", saying where it comes from.
std::string total_deadline_passed(const FetchOptions& options) {
    const std::string rule = options.total_timeout_s > 0 ? "--timeout " + seconds_text(options.total_timeout_s) + " s"
                                                         : seconds_text(options.total_grace_s) + " s + the bytes at the minimum rate";
    return "the total fetch deadline passed (" + rule + "; a crowd's fetches share it)";
}

// When the fetches sharing `deadline` must be done, with the bytes known so far.
Clock::time_point total_deadline(const FetchDeadline& deadline, const FetchOptions& options) {
    return after_seconds(deadline.start, total_deadline_seconds(deadline.bytes, options));
}

// One listed file's download: where it comes from and goes, and by when.
struct FileFetch {
    const FileEntry* entry;
    const FetchOptions* options;
    std::string url, part, blob;  // part: the download so far; blob: the verified copy in the cache
    double file_seconds = 0;      // the file's own deadline, in seconds from its start
    Clock::time_point deadline, total_deadline;

    void log(const std::string& line) const {
        if (options->log) options->log(line);
    }
    Status error(ErrorCode code, const std::string& message) const { return make_error(code, "fetch_file", entry->path, message); }
};

// One GET of the file into `part`: appended to a part worth resuming, else from the start
// (`started_fresh` then set). An error only where the part cannot be written.
Status get_attempt(const FileFetch& f, bool* started_fresh, Transfer* result, std::string* error) {
    int64_t have = file_size_or_minus_one(f.part);
    if (have < 0 || uint64_t(have) >= f.entry->size) {  // nothing to resume, or a part that cannot be right
        std::remove(f.part.c_str());
        have = 0;
    }
    if (have == 0) *started_fresh = true;
    if (have > 0) f.log("fetch: resuming " + f.entry->path + " at byte " + std::to_string(have));
    FILE* file = std::fopen(f.part.c_str(), have > 0 ? "ab" : "wb");
    if (!file) return f.error(ErrorCode::fetch_failed, "cannot write " + f.part);
    Sink sink;
    sink.file = file;
    sink.limit = f.entry->size - uint64_t(have);  // never more than the manifest declares
    Request request;
    request.url = f.url;
    request.resume_from = uint64_t(have);
    request.deadline = f.deadline;
    request.options = f.options;
    *result = http_get(request, &sink, error);
    std::fclose(file);
    return {};
}

// What an attempt's transfer means for the download.
enum class Next { verify, retry, stop };

// `stop` with `status` set where the transfer ends the download; a part kept only where a later
// attempt (or run) may resume it.
Next after_transfer(const FileFetch& f, Transfer result, const std::string& error, bool last_attempt, Status* status) {
    if (result != Transfer::failed && result != Transfer::ok) std::remove(f.part.c_str());
    switch (result) {
    case Transfer::ok: return Next::verify;
    case Transfer::not_found: *status = f.error(ErrorCode::missing_file, "not found at " + f.url); return Next::stop;
    case Transfer::unauthorized: *status = f.error(ErrorCode::unauthorized, f.url + ": " + error); return Next::stop;
    case Transfer::range_refused:  // redo from the start
        f.log("fetch: " + f.url + " cannot resume (" + error + "); downloading again");
        return Next::retry;
    case Transfer::too_many_redirects: *status = f.error(ErrorCode::fetch_failed, f.url + ": " + error); return Next::stop;
    case Transfer::too_large:
        *status = f.error(ErrorCode::size_mismatch, "the server sent more than the manifest's " + std::to_string(f.entry->size) + " bytes");
        return Next::stop;
    case Transfer::deadline:  // a limit broken: nothing of it is kept for a later run
        *status = f.error(ErrorCode::fetch_failed, f.deadline < f.total_deadline
                                                       ? "did not arrive within its deadline of " + seconds_text(f.file_seconds) + " s (" +
                                                             std::to_string(f.entry->size) + " bytes at no less than " +
                                                             seconds_text(f.options->min_rate_bytes_per_s) + " bytes/s)"
                                                       : total_deadline_passed(*f.options));
        return Next::stop;
    case Transfer::failed:  // keep the part: the next attempt (or run) resumes it
        f.log("fetch: " + f.entry->path + " interrupted (" + error + ")");
        if (!last_attempt) return Next::retry;
        *status = f.error(ErrorCode::fetch_failed, "download failed: " + error);
        return Next::stop;
    }
    return Next::stop;
}

// A complete download that does not verify (`bytes` as read back): never kept. A resumed download
// may have joined two different versions of the file, so a bad resume is redone once from the start.
Next after_bad_download(const FileFetch& f, const std::vector<uint8_t>& bytes, bool* started_fresh, Status* status) {
    std::remove(f.part.c_str());
    if (!*started_fresh) {
        f.log("fetch: resumed download of " + f.entry->path + " does not verify; downloading again");
        *started_fresh = true;
        return Next::retry;
    }
    if (bytes.size() != f.entry->size)
        *status = f.error(ErrorCode::size_mismatch,
                          std::to_string(bytes.size()) + " bytes downloaded, manifest says " + std::to_string(f.entry->size));
    else
        *status = f.error(ErrorCode::sha256_mismatch, "downloaded bytes differ from the manifest's sha256");
    return Next::stop;
}

// Brings one listed file into the cache (or finds it there) and returns its verified bytes.
// Nothing is fetched after `total_deadline`.
Status fetch_file(const BundleUrls& urls, const FileEntry& entry, const FetchOptions& options, const std::string& cache,
                  Clock::time_point total_deadline, std::vector<uint8_t>* bytes) {
    FileFetch f;
    f.entry = &entry, f.options = &options;
    f.url = urls.file(entry.path);
    f.part = cache + "/partial/" + entry.sha256 + ".part";
    f.blob = cache_blob_path(cache, entry.sha256);
    f.file_seconds = file_deadline_seconds(entry.size, options);
    f.deadline = std::min(after_seconds(Clock::now(), f.file_seconds), total_deadline);
    f.total_deadline = total_deadline;
    auto verified = [&](const std::string& path) {
        return read_file_bytes(path, bytes) && bytes->size() == entry.size && sha256_hex(bytes->data(), bytes->size()) == entry.sha256;
    };
    if (file_size_or_minus_one(f.blob) >= 0) {
        if (verified(f.blob)) return {};
        f.log("fetch: cached copy of " + entry.path + " is corrupt; fetching it again");
        std::remove(f.blob.c_str());
    }
    if (!make_dirs(cache + "/partial") || !make_dirs(cache + "/blobs/" + entry.sha256.substr(0, 2)))
        return f.error(ErrorCode::fetch_failed, "cannot create the cache folders under " + cache);
    bool started_fresh = false;
    for (int attempt = 0; attempt < options.attempts + 1; ++attempt) {
        Transfer result = Transfer::failed;
        std::string error;
        if (Status written = get_attempt(f, &started_fresh, &result, &error); !written) return written;
        Status status;
        Next next = after_transfer(f, result, error, attempt == options.attempts, &status);
        if (next == Next::verify && verified(f.part)) {
            if (std::rename(f.part.c_str(), f.blob.c_str()) != 0)
                return f.error(ErrorCode::fetch_failed, "cannot move the download into " + f.blob);
            return {};
        }
        if (next == Next::verify) next = after_bad_download(f, *bytes, &started_fresh, &status);
        if (next == Next::stop) return status;
    }
    return f.error(ErrorCode::fetch_failed, "gave up after " + std::to_string(options.attempts) + " attempts");
}

// The manifest's bytes into `manifest`, by the earlier of its own deadline and `total_deadline`.
// Manifests are small; 16 MiB bounds what a broken server can make us hold.
Status fetch_manifest(const BundleUrls& urls, const FetchOptions& options, Clock::time_point total_deadline,
                      std::vector<uint8_t>* manifest) {
    static const char* fn = "fetch_bundle";
    constexpr uint64_t kManifestLimit = 16u << 20;
    Sink sink;
    sink.memory = manifest;
    sink.limit = kManifestLimit;
    Request request;
    request.url = urls.manifest();
    request.options = &options;
    const Clock::time_point own_deadline = after_seconds(Clock::now(), options.manifest_timeout_s);
    request.deadline = std::min(own_deadline, total_deadline);
    std::string error;
    switch (http_get(request, &sink, &error)) {
    case Transfer::ok: return {};
    case Transfer::not_found:
        return make_error(ErrorCode::not_found, fn, "manifest.json", "no bundle at " + urls.manifest());
    case Transfer::unauthorized:
        return make_error(ErrorCode::unauthorized, fn, "manifest.json", urls.manifest() + ": " + error);
    case Transfer::too_large:
        return make_error(ErrorCode::manifest_invalid, fn, "manifest.json", "larger than 16 MiB at " + urls.manifest());
    case Transfer::deadline:
        return make_error(ErrorCode::fetch_failed, fn, "manifest.json",
                          urls.manifest() + ": " +
                              (own_deadline < total_deadline ? "did not arrive within the manifest's deadline of " +
                                                                   seconds_text(options.manifest_timeout_s) + " s"
                                                             : total_deadline_passed(options)));
    default:
        return make_error(ErrorCode::fetch_failed, fn, "manifest.json", urls.manifest() + ": " + error);
    }
}

}  // namespace

double file_deadline_seconds(uint64_t size, const FetchOptions& options) {
    return options.file_grace_s + double(size) / std::max(options.min_rate_bytes_per_s, 1.0);
}

double total_deadline_seconds(uint64_t total_bytes, const FetchOptions& options) {
    if (options.total_timeout_s > 0) return options.total_timeout_s;
    return options.total_grace_s + double(total_bytes) / std::max(options.min_rate_bytes_per_s, 1.0);
}

bool resolve_latest(const BundleUrls& urls, const std::string& name, const std::string& version, BundleUrls* resolved) {
    const std::string tail = "/" + name + "/latest/";
    const std::string& base = urls.base;
    if (name.empty() || version.empty() || base.size() < tail.size() ||
        base.compare(base.size() - tail.size(), tail.size(), tail) != 0)
        return false;
    *resolved = urls;
    resolved->base = base.substr(0, base.size() - tail.size()) + "/" + name + "/" + version + "/";
    return true;
}

Status fetch_bundle(const std::string& url, const FetchOptions& options, Bundle* out, FetchDeadline* shared) {
    static const char* fn = "fetch_bundle";
    BundleUrls urls = bundle_urls(url, options.files_prefix);
    const std::string cache = options.cache_dir.empty() ? default_cache_dir() : options.cache_dir;
    FetchDeadline own;
    FetchDeadline& deadline = shared ? *shared : own;
    if (!deadline.started) deadline.started = true, deadline.start = Clock::now();
    std::vector<uint8_t> manifest;
    if (Status status = fetch_manifest(urls, options, total_deadline(deadline, options), &manifest); !status) return status;
    if (options.log) options.log("fetch: " + urls.manifest() + " (cache " + cache + ")");
    const std::string text(manifest.begin(), manifest.end());

    // Limits and the concrete version, from the manifest, before any file is fetched. A
    // manifest that does not parse is left for load_bundle to name.
    Manifest parsed;
    if (parse_manifest(text, &parsed).ok()) {
        uint64_t total = 0;
        for (const FileEntry& f : parsed.files) total += std::min<uint64_t>(f.size, UINT64_MAX - total);
        if (total > options.cache_budget_bytes)
            return make_error(ErrorCode::over_budget, fn, "manifest.json",
                              "the bundle lists " + std::to_string(total) + " bytes, the cache budget is " +
                                  std::to_string(options.cache_budget_bytes));
        deadline.bytes += total;  // at most the budget per bundle: no overflow
        BundleUrls concrete;
        if (resolve_latest(urls, parsed.name, parsed.version, &concrete)) {
            if (options.log) options.log("fetch: latest is " + parsed.version + "; files from " + concrete.base);
            urls = concrete;
        } else if (urls.base.size() >= 8 && urls.base.compare(urls.base.size() - 8, 8, "/latest/") == 0) {
            return make_error(ErrorCode::manifest_invalid, fn, "manifest.json",
                              "the URL asks for the latest version of another bundle than '" + parsed.name + "'");
        }
    }
    const Clock::time_point files_deadline = total_deadline(deadline, options);
    const FileSource source = [&](const FileEntry& entry, std::vector<uint8_t>* bytes) {
        return fetch_file(urls, entry, options, cache, files_deadline, bytes);
    };
    return load_bundle(text, source, out);
}

}  // namespace crowdview
