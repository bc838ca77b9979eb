// Fetch a bundle by URL through a local content-addressed cache.
//
// The service publishes a bundle as <base>/manifest.json and <base>/<files_prefix><path>
// (bundles/{name}/{version}/manifest.json and .../files/{path}). Every file is stored in the
// cache by its sha256 only, so no path from a manifest ever becomes a path on disk:
//   <cache>/blobs/<sha[0:2]>/<sha>     verified files, moved in by an atomic rename
//   <cache>/partial/<sha>.part         a download in progress; resumed, or redone if bad
#pragma once

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

struct FetchOptions {
    std::string cache_dir;               // "" means default_cache_dir()
    std::string files_prefix = "files/";
    long connect_timeout_s = 15;
    int attempts = 3;                    // transport failures resumed this many times per file
    std::function<void(const std::string&)> log;  // progress lines; may be empty
};

// $XDG_CACHE_HOME/crowdview, else $HOME/.cache/crowdview, else ./.crowdview-cache.
std::string default_cache_dir();

// Where a verified file with this sha256 lives in the cache.
std::string cache_blob_path(const std::string& cache_dir, const std::string& sha256);

// Fetch the manifest, then every listed file not already in the cache (verifying size and
// sha256 before a file enters the cache), then verify and decode the bundle exactly as
// load_bundle does. Errors name the bundle file; transport failures are fetch_failed, an
// absent manifest manifest_invalid, an absent file missing_file.
Status fetch_bundle(const std::string& url, const FetchOptions& options, Bundle* out);

}  // namespace crowdview
