// Writes the synthetic test bundle (tests/synthetic_bundle.h):
//   make_synthetic_bundle OUT_DIR [--uncompressed] [--paper-counts] [--clips]
// --paper-counts sizes the meshes like the paper's figure 3 characters (13,056 and 1,900
// triangles) for benchmarks; --clips writes format v2 with an idle and a walk clip and a
// transition each way (Options::two_clips). ctest uses it as a fixture; handy for trying crowdview too.
#include <cstdio>
#include <cstring>

#include "synthetic_bundle.h"

int main(int argc, char** argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: make_synthetic_bundle OUT_DIR [--uncompressed] [--paper-counts] [--clips]\n");
        return 2;
    }
    synthetic::Options options;
    bool compressed = true;
    for (int i = 2; i < argc; ++i) {
        if (std::strcmp(argv[i], "--uncompressed") == 0) compressed = false;
        else if (std::strcmp(argv[i], "--paper-counts") == 0) options = synthetic::Options::paper_counts();
        else if (std::strcmp(argv[i], "--clips") == 0) options = synthetic::Options::two_clips();
        else {
            std::fprintf(stderr, "make_synthetic_bundle: unknown argument '%s'\n", argv[i]);
            return 2;
        }
    }
    options.compressed = compressed;
    const std::string error = synthetic::write_bundle(argv[1], options);
    if (!error.empty()) {
        std::fprintf(stderr, "%s\n", error.c_str());
        return 1;
    }
    std::printf("wrote %s\n", argv[1]);
    return 0;
}
