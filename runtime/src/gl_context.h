// An OpenGL 3.3 core context: a GLFW window, or headless through EGL surfaceless (Mesa;
// needs no display), falling back to an invisible GLFW window (needs X, e.g. xvfb-run).
// Rendering always goes to the renderer's own framebuffer; a window only shows a blit of it.
#pragma once

#include <memory>
#include <string>

struct GLFWwindow;

namespace crowdview {

struct GlContextDesc {
    int width = 1280, height = 720;
    bool window = false;       // false: headless
    bool vsync = false;        // windows only; the benchmark needs it off
    const char* title = "crowdview";
};

class GlContext {
public:
    ~GlContext();
    GlContext(const GlContext&) = delete;
    GlContext& operator=(const GlContext&) = delete;

    // nullptr and `error` set when no context can be made here.
    static std::unique_ptr<GlContext> create(const GlContextDesc& desc, std::string* error);

    GLFWwindow* window() const { return window_; }  // nullptr when headless through EGL
    bool visible() const { return visible_; }
    bool should_close() const;
    void swap_and_poll();
    void set_title(const std::string& title);
    std::string describe() const;  // "EGL surfaceless: llvmpipe (LLVM 15...), 4.5 (Core Profile) Mesa ..."
    std::string renderer_name() const;  // GL_RENDERER, "?" where the driver gives none
    std::string version() const;        // GL_VERSION

private:
    GlContext() = default;
    GLFWwindow* window_ = nullptr;
    void* egl_display_ = nullptr;
    void* egl_context_ = nullptr;
    bool visible_ = false;
    std::string kind_;
};

// True where `gl_renderer` (GL_RENDERER) names one of Mesa's CPU rasterisers: llvmpipe,
// softpipe or swrast. Blended impostors cost about 6x there (3 frames: 2.4 s off, 14.5 s warp).
bool is_software_renderer(const std::string& gl_renderer);

}  // namespace crowdview
