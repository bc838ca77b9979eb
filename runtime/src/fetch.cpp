// Fetch over libcurl into a sha256-addressed cache: download to a .part file, verify, rename.
#include "fetch.h"

#include <curl/curl.h>
#include <sys/stat.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <mutex>

namespace crowdview {

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

enum class Transfer { ok, not_found, range_refused, too_large, failed };

// One GET of `url` into `sink`, resuming at byte `resume_from`.
Transfer http_get(const std::string& url, Sink* sink, uint64_t resume_from, long connect_timeout_s, std::string* error) {
    static std::once_flag init;
    std::call_once(init, [] { curl_global_init(CURL_GLOBAL_DEFAULT); });
    CURL* curl = curl_easy_init();
    if (!curl) {
        *error = "curl_easy_init failed";
        return Transfer::failed;
    }
    char curl_error[CURL_ERROR_SIZE] = "";
    curl_easy_setopt(curl, CURLOPT_URL, url.c_str());
    curl_easy_setopt(curl, CURLOPT_FOLLOWLOCATION, 1L);
    curl_easy_setopt(curl, CURLOPT_FAILONERROR, 1L);
    curl_easy_setopt(curl, CURLOPT_CONNECTTIMEOUT, connect_timeout_s);
    // A stalled server (under 1 byte/s for 30 s) counts as an interrupted transfer.
    curl_easy_setopt(curl, CURLOPT_LOW_SPEED_LIMIT, 1L);
    curl_easy_setopt(curl, CURLOPT_LOW_SPEED_TIME, 30L);
    curl_easy_setopt(curl, CURLOPT_WRITEFUNCTION, write_sink);
    curl_easy_setopt(curl, CURLOPT_WRITEDATA, sink);
    curl_easy_setopt(curl, CURLOPT_ERRORBUFFER, curl_error);
    curl_easy_setopt(curl, CURLOPT_NOSIGNAL, 1L);
    if (resume_from > 0) curl_easy_setopt(curl, CURLOPT_RESUME_FROM_LARGE, curl_off_t(resume_from));
    const CURLcode code = curl_easy_perform(curl);
    long http_status = 0;
    curl_easy_getinfo(curl, CURLINFO_RESPONSE_CODE, &http_status);
    curl_easy_cleanup(curl);
    if (code == CURLE_OK) return Transfer::ok;
    *error = curl_error[0] ? curl_error : curl_easy_strerror(code);
    if (sink->over_limit) return Transfer::too_large;
    if (code == CURLE_FILE_COULDNT_READ_FILE || (code == CURLE_HTTP_RETURNED_ERROR && (http_status == 404 || http_status == 410)))
        return Transfer::not_found;
    // 416: the server's file is no longer than our partial one; CURLE_RANGE_ERROR: no Range support.
    if (code == CURLE_RANGE_ERROR || (code == CURLE_HTTP_RETURNED_ERROR && http_status == 416)) return Transfer::range_refused;
    return Transfer::failed;
}

// Brings one listed file into the cache (or finds it there) and returns its verified bytes.
Status fetch_file(const BundleUrls& urls, const FileEntry& entry, const FetchOptions& options, const std::string& cache,
                  std::vector<uint8_t>* bytes) {
    static const char* fn = "fetch_file";
    auto log = [&](const std::string& line) {
        if (options.log) options.log(line);
    };
    const std::string blob = cache_blob_path(cache, entry.sha256);
    auto verified = [&](const std::string& path) {
        return read_file_bytes(path, bytes) && bytes->size() == entry.size &&
               sha256_hex(bytes->data(), bytes->size()) == entry.sha256;
    };
    if (file_size_or_minus_one(blob) >= 0) {
        if (verified(blob)) return {};
        log("fetch: cached copy of " + entry.path + " is corrupt; fetching it again");
        std::remove(blob.c_str());
    }
    if (!make_dirs(cache + "/partial") || !make_dirs(cache + "/blobs/" + entry.sha256.substr(0, 2)))
        return make_error(ErrorCode::fetch_failed, fn, entry.path, "cannot create the cache folders under " + cache);

    const std::string part = cache + "/partial/" + entry.sha256 + ".part";
    const std::string url = urls.file(entry.path);
    bool started_fresh = false;
    for (int attempt = 0; attempt < options.attempts + 1; ++attempt) {
        int64_t have = file_size_or_minus_one(part);
        if (have < 0 || uint64_t(have) >= entry.size) {  // nothing to resume, or a part that cannot be right
            std::remove(part.c_str());
            have = 0;
        }
        if (have == 0) started_fresh = true;
        if (have > 0) log("fetch: resuming " + entry.path + " at byte " + std::to_string(have));
        FILE* file = std::fopen(part.c_str(), have > 0 ? "ab" : "wb");
        if (!file) return make_error(ErrorCode::fetch_failed, fn, entry.path, "cannot write " + part);
        Sink sink;
        sink.file = file;
        sink.limit = entry.size - uint64_t(have);
        std::string error;
        const Transfer result = http_get(url, &sink, uint64_t(have), options.connect_timeout_s, &error);
        std::fclose(file);
        switch (result) {
        case Transfer::ok:
            break;
        case Transfer::not_found:
            std::remove(part.c_str());
            return make_error(ErrorCode::missing_file, fn, entry.path, "not found at " + url);
        case Transfer::range_refused:  // redo from the start
            log("fetch: " + url + " cannot resume (" + error + "); downloading again");
            std::remove(part.c_str());
            continue;
        case Transfer::too_large:
            std::remove(part.c_str());
            return make_error(ErrorCode::size_mismatch, fn, entry.path,
                              "the server sent more than the manifest's " + std::to_string(entry.size) + " bytes");
        case Transfer::failed:  // keep the part: the next attempt (or run) resumes it
            log("fetch: " + entry.path + " interrupted (" + error + ")");
            if (attempt == options.attempts)
                return make_error(ErrorCode::fetch_failed, fn, entry.path, "download failed: " + error);
            continue;
        }
        if (verified(part)) {
            if (std::rename(part.c_str(), blob.c_str()) != 0)
                return make_error(ErrorCode::fetch_failed, fn, entry.path, "cannot move the download into " + blob);
            return {};
        }
        // Complete but wrong: never keep it. A resumed download may have joined two different
        // versions of the file, so a bad resume is redone once from the start.
        std::remove(part.c_str());
        const bool short_file = bytes->size() != entry.size;
        if (!started_fresh) {
            log("fetch: resumed download of " + entry.path + " does not verify; downloading again");
            started_fresh = true;
            continue;
        }
        if (short_file)
            return make_error(ErrorCode::size_mismatch, fn, entry.path,
                              std::to_string(bytes->size()) + " bytes downloaded, manifest says " + std::to_string(entry.size));
        return make_error(ErrorCode::sha256_mismatch, fn, entry.path, "downloaded bytes differ from the manifest's sha256");
    }
    return make_error(ErrorCode::fetch_failed, fn, entry.path, "gave up after " + std::to_string(options.attempts) + " attempts");
}

}  // namespace

Status fetch_bundle(const std::string& url, const FetchOptions& options, Bundle* out) {
    static const char* fn = "fetch_bundle";
    const BundleUrls urls = bundle_urls(url, options.files_prefix);
    const std::string cache = options.cache_dir.empty() ? default_cache_dir() : options.cache_dir;

    // Manifests are small; 16 MiB bounds what a broken server can make us hold.
    std::vector<uint8_t> manifest;
    Sink sink;
    sink.memory = &manifest;
    sink.limit = 16u << 20;
    std::string error;
    switch (http_get(urls.manifest(), &sink, 0, options.connect_timeout_s, &error)) {
    case Transfer::ok: break;
    case Transfer::not_found:
        return make_error(ErrorCode::manifest_invalid, fn, "manifest.json", "not found at " + urls.manifest());
    case Transfer::too_large:
        return make_error(ErrorCode::manifest_invalid, fn, "manifest.json", "larger than 16 MiB at " + urls.manifest());
    default:
        return make_error(ErrorCode::fetch_failed, fn, "manifest.json", urls.manifest() + ": " + error);
    }
    if (options.log) options.log("fetch: " + urls.manifest() + " (cache " + cache + ")");
    const FileSource source = [&](const FileEntry& entry, std::vector<uint8_t>* bytes) {
        return fetch_file(urls, entry, options, cache, bytes);
    };
    return load_bundle(std::string(manifest.begin(), manifest.end()), source, out);
}

}  // namespace crowdview
