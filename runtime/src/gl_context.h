// An OpenGL 3.3 core context: a GLFW window, or headless. Headless, by default, the first of:
//   1. an EGL device that is a GPU (EGL_EXT_platform_device): NVIDIA's driver offers its GPUs
//      there and nowhere else on a server with no display;
//   2. Mesa's surfaceless platform (EGL_MESA_platform_surfaceless): llvmpipe where Mesa has no
//      driver for the GPU, which is why it comes after the devices;
//   3. an invisible GLFW window (needs X, e.g. xvfb-run).
// Rendering always goes to the renderer's own framebuffer; a window only shows a blit of it.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

struct GLFWwindow;

namespace crowdview {

// Which EGL device a headless context is made on (--gl-device).
struct GlDeviceChoice {
    enum Kind { automatic, software, numbered };
    Kind kind = automatic;  // automatic: the order above; software: Mesa's software device (EGL_MESA_device_software)
    int index = 0;          // kind numbered: the position in eglQueryDevicesEXT's list
};

// "auto", "software" or a device number (0, 1, ...); false for anything else.
bool parse_gl_device(const std::string& text, GlDeviceChoice* choice);

struct GlContextDesc {
    int width = 1280, height = 720;
    bool window = false;       // false: headless
    bool vsync = false;        // windows only; the benchmark needs it off
    const char* title = "crowdview";
    GlDeviceChoice device;     // headless only; a named device (software or index) has no fallback
    bool require_gpu = false;  // refuse a context that renders on a software rasteriser
};

// What a context is and what it runs on: the log line and the reports' "gl".
struct GlContextInfo {
    std::string context;  // "EGL device", "EGL surfaceless", "GLFW window" or "GLFW hidden window"
    // EGL device: its place in eglQueryDevicesEXT's list, its name ("/dev/dri/card0, CUDA device 0",
    // "Mesa software") and its own extensions; device_index -1 for any other context.
    int device_index = -1, device_count = 0;
    std::string device_name, device_extensions;
    std::string vendor, renderer, version;  // GL_VENDOR, GL_RENDERER, GL_VERSION ("?" where the driver gives none)
    // --gl-device auto: what came before the context made and why it was not used, e.g.
    // "EGL device 0 of 2 (/dev/dri/card0): renders on llvmpipe (LLVM 15.0.7, 256 bits)".
    std::vector<std::string> passed_over;
};

class GlContext {
public:
    ~GlContext();
    GlContext(const GlContext&) = delete;
    GlContext& operator=(const GlContext&) = delete;

    // nullptr and a one-line `error` when no context can be made here, or when desc.require_gpu
    // and the only context renders on a software rasteriser.
    static std::unique_ptr<GlContext> create(const GlContextDesc& desc, std::string* error);

    GLFWwindow* window() const { return window_; }  // nullptr when headless through EGL
    bool visible() const { return visible_; }
    bool should_close() const;
    void swap_and_poll();
    void set_title(const std::string& title);
    const GlContextInfo& info() const { return info_; }
    std::string describe() const;  // "EGL surfaceless: llvmpipe (LLVM 15...), 4.5 (Core Profile) Mesa ..."
    std::string renderer_name() const { return info_.renderer; }
    std::string version() const { return info_.version; }

private:
    GlContext() = default;
    bool make_headless(const GlDeviceChoice& choice, std::string* error);
    bool make_glfw(const GlContextDesc& desc, std::string* error);

    GLFWwindow* window_ = nullptr;
    void* egl_display_ = nullptr;
    void* egl_context_ = nullptr;
    bool visible_ = false;
    GlContextInfo info_;
};

// One line naming the context, device, vendor and renderer:
// "GL_RENDERER NVIDIA H100 80GB HBM3/PCIe/SSE2; GL_VERSION 4.6.0 NVIDIA 550.54; GL_VENDOR NVIDIA Corporation;
// EGL device 0 of 1 (/dev/dri/card0, CUDA device 0)", then "; passed over: ..." where auto passed some over.
std::string gl_context_line(const GlContextInfo& info);

// {"context", "device", "vendor", "renderer", "version", "software_rasteriser", "passed_over"}.
nlohmann::json gl_report(const GlContextInfo& info);

// True where `gl_renderer` (GL_RENDERER) names one of Mesa's CPU rasterisers: llvmpipe,
// softpipe or swrast. Blended impostors cost about 6x there (3 frames: 2.4 s off, 14.5 s warp).
bool is_software_renderer(const std::string& gl_renderer);

}  // namespace crowdview
