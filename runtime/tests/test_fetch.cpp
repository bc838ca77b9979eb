// Fetching through the cache with the real libcurl, over file:// URLs laid out as the service
// publishes bundles (<base>/manifest.json, <base>/files/<path>): the URL layout, the cache,
// resumed and redone downloads, tampered and missing files. (HTTP with Range requests and
// dropped connections: http_fetch_test.py.)
#include <filesystem>

#include <nlohmann/json.hpp>

#include "check.h"
#include "fetch.h"
#include "synthetic_bundle.h"

using namespace crowdview;
namespace fs = std::filesystem;

namespace {

void test_urls() {
    const BundleUrls a = bundle_urls("http://host:8000/bundles/walker/1.0.0");
    CHECK(a.base == "http://host:8000/bundles/walker/1.0.0/");
    CHECK(a.manifest() == "http://host:8000/bundles/walker/1.0.0/manifest.json");
    CHECK(a.file("poses/body_lod0.cbpc") == "http://host:8000/bundles/walker/1.0.0/files/poses/body_lod0.cbpc");
    CHECK(bundle_urls("http://host/bundles/walker/1.0.0/").manifest() == a.manifest().substr(0, 7) + "host/bundles/walker/1.0.0/manifest.json");
    CHECK(bundle_urls("https://h/b/manifest.json").base == "https://h/b/");
    CHECK(bundle_urls("https://h/b/my-manifest.json").base == "https://h/b/my-manifest.json/");  // only a whole name
    CHECK(bundle_urls("file:///srv/b", "").file("x/y.cbtx") == "file:///srv/b/x/y.cbtx");
    CHECK(bundle_urls("file:///srv/b", "blobs").file("y") == "file:///srv/b/blobs/y");
    CHECK(cache_blob_path("/c", "ab12") == "/c/blobs/ab/ab12");

    // `latest` is replaced by the manifest's version, only where the URL names that bundle.
    BundleUrls resolved;
    CHECK(resolve_latest(bundle_urls("http://h/v1/bundles/walker/latest"), "walker", "1.2.0+b", &resolved));
    CHECK(resolved.manifest() == "http://h/v1/bundles/walker/1.2.0+b/manifest.json");
    CHECK(resolved.file("a/b.cbtx") == "http://h/v1/bundles/walker/1.2.0+b/files/a/b.cbtx");
    CHECK(!resolve_latest(bundle_urls("http://h/v1/bundles/walker/1.0.0"), "walker", "1.2.0", &resolved));
    CHECK(!resolve_latest(bundle_urls("http://h/v1/bundles/runner/latest"), "walker", "1.2.0", &resolved));
    CHECK(!resolve_latest(bundle_urls("http://h/v1/bundles/xwalker/latest"), "walker", "1.2.0", &resolved));
}

void test_deadlines() {
    FetchOptions o;
    o.min_rate_bytes_per_s = 1000, o.file_grace_s = 5, o.total_grace_s = 20;
    CHECK_NEAR(file_deadline_seconds(0, o), 5.0, 1e-9);
    CHECK_NEAR(file_deadline_seconds(10000, o), 15.0, 1e-9);  // grace + size / rate
    CHECK_NEAR(total_deadline_seconds(50000, o), 70.0, 1e-9);
    o.total_timeout_s = 3;  // an explicit total wins
    CHECK_NEAR(total_deadline_seconds(50000, o), 3.0, 1e-9);
    // The defaults: a 2 byte/s drip of a 100 kB file is given up long before it ends (14 h).
    const FetchOptions d;
    CHECK(file_deadline_seconds(100000, d) < 20.0);
}

// A served copy of `bundle`: manifest.json at the root, every file under files/.
std::string serve(const std::string& bundle, const std::string& root) {
    fs::create_directories(root + "/files");
    fs::copy_file(bundle + "/manifest.json", root + "/manifest.json");
    for (const auto& entry : fs::recursive_directory_iterator(bundle)) {
        if (!entry.is_regular_file() || entry.path().filename() == "manifest.json") continue;
        const fs::path target = fs::path(root) / "files" / fs::relative(entry.path(), bundle);
        fs::create_directories(target.parent_path());
        fs::copy_file(entry.path(), target);
    }
    return "file://" + root;
}

std::vector<FileEntry> listed_files(const std::string& root) {
    Manifest m;
    CHECK(parse_manifest(synthetic::read_text(root + "/manifest.json"), &m).ok());
    return m.files;
}

size_t count_files(const std::string& dir) {
    size_t n = 0;
    if (fs::exists(dir))
        for (const auto& e : fs::recursive_directory_iterator(dir)) n += e.is_regular_file();
    return n;
}

void test_fetch(const std::string& bundle, const std::string& work) {
    const std::string root = work + "/served";
    const std::string url = serve(bundle, root);
    const std::vector<FileEntry> files = listed_files(root);
    FetchOptions options;
    options.cache_dir = work + "/cache";
    std::vector<std::string> log;
    options.log = [&](const std::string& line) { log.push_back(line); };

    // First fetch: everything downloaded, verified and stored by sha256; nothing left partial.
    Bundle fetched;
    Status s = fetch_bundle(url, options, &fetched);
    CHECK_MSG(s.ok(), s.message);
    CHECK(fetched.manifest.name == "synthetic-walker" && fetched.meshes.size() == 4);
    for (const FileEntry& f : files) CHECK_MSG(fs::file_size(cache_blob_path(options.cache_dir, f.sha256)) == f.size, f.path);
    CHECK(count_files(options.cache_dir + "/blobs") == files.size());
    CHECK(count_files(options.cache_dir + "/partial") == 0);
    CHECK(count_files(options.cache_dir) == files.size());  // only blobs: no manifest path became a file path

    // Second fetch: the files are gone from the server, the cache serves them.
    fs::remove_all(root + "/files");
    s = fetch_bundle(url, options, &fetched);
    CHECK_MSG(s.ok(), s.message);

    // A corrupt cached blob is noticed, dropped and fetched again.
    serve(bundle, work + "/served2");
    const std::string url2 = "file://" + work + "/served2";
    const std::string blob = cache_blob_path(options.cache_dir, files[0].sha256);
    synthetic::write_bytes(blob, {1, 2, 3});
    log.clear();
    s = fetch_bundle(url2, options, &fetched);
    CHECK_MSG(s.ok(), s.message);
    CHECK(fs::file_size(blob) == files[0].size);
    CHECK(!log.empty() && log.back().find("corrupt") != std::string::npos);

    // An interrupted download resumes from its .part file.
    FetchOptions fresh = options;
    fresh.cache_dir = work + "/cache-resume";
    const FileEntry& big = *std::max_element(files.begin(), files.end(), [](auto& a, auto& b) { return a.size < b.size; });
    std::vector<uint8_t> bytes;
    CHECK(read_file_bytes(bundle + "/" + big.path, &bytes));
    bytes.resize(bytes.size() / 2);
    synthetic::write_bytes(fresh.cache_dir + "/partial/" + big.sha256 + ".part", bytes);
    log.clear();
    fresh.log = options.log;
    s = fetch_bundle(url2, fresh, &fetched);
    CHECK_MSG(s.ok(), s.message);
    bool resumed = false;
    for (const std::string& line : log) resumed |= line.find("resuming " + big.path) != std::string::npos;
    CHECK(resumed);
    CHECK(count_files(fresh.cache_dir + "/partial") == 0);

    // A .part holding wrong bytes: the resumed file fails its sha256, is dropped and redone.
    fresh.cache_dir = work + "/cache-redo";
    std::fill(bytes.begin(), bytes.end(), uint8_t(0x5A));
    synthetic::write_bytes(fresh.cache_dir + "/partial/" + big.sha256 + ".part", bytes);
    log.clear();
    s = fetch_bundle(url2, fresh, &fetched);
    CHECK_MSG(s.ok(), s.message);
    bool redone = false;
    for (const std::string& line : log) redone |= line.find("downloading again") != std::string::npos;
    CHECK(redone);
    CHECK(fs::file_size(cache_blob_path(fresh.cache_dir, big.sha256)) == big.size);

    // A tampered file on the server is refused by name, and never enters the cache.
    const std::string tampered_root = work + "/tampered";
    const std::string tampered_url = serve(bundle, tampered_root);
    const std::string victim = "poses/skirt_lod1.cbpc";
    std::vector<uint8_t> victim_bytes;
    CHECK(read_file_bytes(tampered_root + "/files/" + victim, &victim_bytes));
    victim_bytes[victim_bytes.size() / 2] ^= 0x40;
    synthetic::write_bytes(tampered_root + "/files/" + victim, victim_bytes);
    fresh.cache_dir = work + "/cache-tampered";
    s = fetch_bundle(tampered_url, fresh, &fetched);
    CHECK_MSG(s.code == ErrorCode::sha256_mismatch && s.file == victim, s.message);
    CHECK(s.message.find(victim) != std::string::npos);
    std::string victim_sha;
    for (const FileEntry& f : files)
        if (f.path == victim) victim_sha = f.sha256;
    CHECK(!fs::exists(cache_blob_path(fresh.cache_dir, victim_sha)));
    CHECK(count_files(fresh.cache_dir + "/partial") == 0);

    // Truncated on the server: a size mismatch, named.
    victim_bytes.resize(victim_bytes.size() - 8);
    synthetic::write_bytes(tampered_root + "/files/" + victim, victim_bytes);
    fresh.cache_dir = work + "/cache-short";
    s = fetch_bundle(tampered_url, fresh, &fetched);
    CHECK_MSG(s.code == ErrorCode::size_mismatch && s.file == victim, s.message);

    // Missing file and missing manifest.
    fs::remove(tampered_root + "/files/" + victim);
    s = fetch_bundle(tampered_url, fresh, &fetched);
    CHECK_MSG(s.code == ErrorCode::missing_file && s.file == victim, s.message);
    s = fetch_bundle("file://" + work + "/nowhere", fresh, &fetched);
    CHECK_MSG(s.code == ErrorCode::not_found && s.file == "manifest.json", s.message);

    // A manifest whose files exceed the cache budget is refused before anything is fetched;
    // one claiming far more than the server has never leaves a partial file behind.
    FetchOptions tight = fresh;
    tight.cache_dir = work + "/cache-budget";
    uint64_t total = 0;
    for (const FileEntry& f : files) total += f.size;
    tight.cache_budget_bytes = total - 1;
    s = fetch_bundle(url2, tight, &fetched);
    CHECK_MSG(s.code == ErrorCode::over_budget && s.file == "manifest.json", s.message);
    CHECK(count_files(tight.cache_dir) == 0);
    tight.cache_budget_bytes = total;
    s = fetch_bundle(url2, tight, &fetched);
    CHECK_MSG(s.ok(), s.message);
    nlohmann::json claims = nlohmann::json::parse(synthetic::read_text(root + "/manifest.json"));
    claims["files"][0]["size"] = uint64_t(1000000000000);
    const std::string huge_root = work + "/huge";
    serve(bundle, huge_root);
    const std::string huge_text = claims.dump();
    synthetic::write_bytes(huge_root + "/manifest.json", std::vector<uint8_t>(huge_text.begin(), huge_text.end()));
    FetchOptions roomy = fresh;
    roomy.cache_dir = work + "/cache-huge";
    s = fetch_bundle("file://" + huge_root, roomy, &fetched);
    CHECK_MSG(s.code == ErrorCode::over_budget, s.message);
    CHECK(count_files(roomy.cache_dir) == 0);
    roomy.cache_budget_bytes = uint64_t(1) << 41;
    s = fetch_bundle("file://" + huge_root, roomy, &fetched);
    CHECK_MSG(s.code == ErrorCode::size_mismatch && s.file == claims["files"][0]["path"].get<std::string>(), s.message);
    CHECK(count_files(roomy.cache_dir + "/partial") == 0);

    // A manifest path that would leave the folder is refused before anything is fetched.
    nlohmann::json manifest = nlohmann::json::parse(synthetic::read_text(root + "/manifest.json"));
    manifest["files"][0]["path"] = "../../../outside.bin";
    const std::string evil_root = work + "/evil";
    serve(bundle, evil_root);
    const std::string text = manifest.dump();
    synthetic::write_bytes(evil_root + "/manifest.json", std::vector<uint8_t>(text.begin(), text.end()));
    fresh.cache_dir = work + "/cache-evil";
    s = fetch_bundle("file://" + evil_root, fresh, &fetched);
    CHECK_MSG(s.code == ErrorCode::unsafe_path && s.file == "../../../outside.bin", s.message);
    CHECK(count_files(fresh.cache_dir) == 0);

    // Nothing listening: a transport failure, not a bundle fault.
    s = fetch_bundle("http://127.0.0.1:9/bundles/x/1", fresh, &fetched);
    CHECK_MSG(s.code == ErrorCode::fetch_failed, s.message);
}

}  // namespace

int main() {
    test_urls();
    test_deadlines();
    const std::string work = synthetic::temp_dir("fetch");
    synthetic::Options small;
    small.tile_size = 16;  // the fetch path does not care about impostor resolution
    const std::string error = synthetic::write_bundle(work + "/bundle", small);
    CHECK_MSG(error.empty(), error);
    if (error.empty()) test_fetch(work + "/bundle", work);
    fs::remove_all(work);
    return check::exit_code();
}
