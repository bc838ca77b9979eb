// Fetch a bundle by URL through a local content-addressed cache.
//
// The service publishes a bundle as <base>/manifest.json and <base>/<files_prefix><path>
// (bundles/{name}/{version}/manifest.json and .../files/{path}). Every file is stored in the
// cache by its sha256 only, so no path from a manifest ever becomes a path on disk:
//   <cache>/blobs/<sha[0:2]>/<sha>     verified files, moved in by an atomic rename
//   <cache>/partial/<sha>.part         a download in progress; resumed, or redone if bad
//
// A server cannot make a fetch hold without end or fill the disk: the manifest's sizes must
// fit the cache budget before anything is downloaded, no file is written past its declared
// size, the manifest must arrive within its own deadline (its size is not known before it
// does), each file within a deadline derived from its size and a minimum rate, and the whole
// fetch within a total deadline, which the fetches of a crowd's bundles share (FetchDeadline). A partial file that failed verification or
// broke a limit is deleted; only an interrupted one is kept, to be resumed.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <string>

#include "bundle.h"

namespace crowdview {

struct BundleUrls {
    std::string base;          // ends with '/'
    std::string files_prefix;  // "files/" by default; "" when files sit beside the manifest
    std::string manifest() const { return base + "manifest.json"; }
    std::string file(const std::string& path) const { return base + files_prefix + path; }
};

// `url` names the bundle folder (with or without a trailing '/') or its manifest.json.
// http://, https:// and file:// URLs all work (libcurl).
BundleUrls bundle_urls(const std::string& url, const std::string& files_prefix = "files/");

// `url` with a last path segment "latest" (the service's alias for the newest version) and
// `version` in its place: ".../bundles/walker/latest/" -> ".../bundles/walker/1.2.0/". False
// (and `resolved` untouched) when the URL's bundle folder is not ".../<name>/latest".
bool resolve_latest(const BundleUrls& urls, const std::string& name, const std::string& version, BundleUrls* resolved);

struct FetchOptions {
    std::string cache_dir;               // "" means default_cache_dir()
    std::string files_prefix = "files/";
    // Sent as "Authorization: Bearer <key>" (the service also takes X-API-Key); "" sends none.
    // Never logged, never part of an error message.
    std::string api_key;
    long connect_timeout_s = 15;
    int attempts = 3;                    // transport failures resumed this many times per file
    // Refuse a manifest whose files add up to more than this, before downloading anything.
    // 4 GiB: a crowd bundle of the paper's kind is tens of megabytes.
    uint64_t cache_budget_bytes = uint64_t(4) << 30;
    // Each file must arrive within file_grace_s + size / min_rate_bytes_per_s seconds, all its
    // attempts together (64 KiB/s: a slow mobile link; the grace covers connection set-up).
    double min_rate_bytes_per_s = 64 * 1024;
    double file_grace_s = 10;
    // The manifest must arrive within this many seconds of its request (and the total deadline):
    // a manifest is kilobytes, so a minute is a link that barely moves.
    double manifest_timeout_s = 60;
    // The whole fetch, manifest included; 0 means total_grace_s + total bytes / min rate.
    double total_timeout_s = 0;
    double total_grace_s = 60;
    std::function<void(const std::string&)> log;  // progress lines; may be empty
};

// The total deadline of one fetch, or of several that share it one after another (a crowd's
// bundles): it counts from the first fetch's start, and without total_timeout_s it is total_grace_s
// plus every manifest's bytes so far at the minimum rate, so a crowd's fetches together take no
// longer than one fetch of all their bytes, however many of its servers trickle.
struct FetchDeadline {
    bool started = false;
    std::chrono::steady_clock::time_point start;
    uint64_t bytes = 0;  // the listed files of every manifest fetched so far
};

// Seconds a file of `size` bytes may take, all attempts together (see FetchOptions).
double file_deadline_seconds(uint64_t size, const FetchOptions& options);
// Seconds the whole fetch may take for files adding up to `total_bytes`.
double total_deadline_seconds(uint64_t total_bytes, const FetchOptions& options);

// $XDG_CACHE_HOME/crowdview, else $HOME/.cache/crowdview, else ./.crowdview-cache.
std::string default_cache_dir();

// Where a verified file with this sha256 lives in the cache.
std::string cache_blob_path(const std::string& cache_dir, const std::string& sha256);

// Fetch the manifest, then every listed file not already in the cache (verifying size and
// sha256 before a file enters the cache), then verify and decode the bundle exactly as
// load_bundle does. A URL ending in ".../<name>/latest" is resolved once: the manifest
// fetched there names the version, and every file comes from ".../<name>/<version>/", so a
// version published meanwhile cannot mix in. Errors name the bundle file; transport failures
// and missed deadlines are fetch_failed, no manifest at the URL not_found, a refused key
// unauthorized, a bundle bigger than the budget over_budget, an absent file missing_file.
// `shared`: a deadline this fetch shares with others (see FetchDeadline); nullptr: its own.
Status fetch_bundle(const std::string& url, const FetchOptions& options, Bundle* out, FetchDeadline* shared = nullptr);

}  // namespace crowdview
