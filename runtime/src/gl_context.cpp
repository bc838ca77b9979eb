// GL context creation: EGL surfaceless first for headless runs, GLFW for windows.
#include "gl_context.h"

#include <epoxy/egl.h>
#include <epoxy/gl.h>
#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>

#include <cctype>
#include <cstring>

namespace crowdview {

namespace {

bool has_extension(const char* list, const char* name) {
    if (!list) return false;
    const size_t n = std::strlen(name);
    for (const char* p = list; (p = std::strstr(p, name)); p += n)
        if ((p == list || p[-1] == ' ') && (p[n] == ' ' || p[n] == '\0')) return true;
    return false;
}

// A GL 3.3 core context on Mesa's surfaceless platform: no window system at all.
bool create_egl_surfaceless(void** display_out, void** context_out, std::string* error) {
    const char* client_extensions = eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS);
    if (!has_extension(client_extensions, "EGL_MESA_platform_surfaceless")) {
        *error = "EGL_MESA_platform_surfaceless is not available";
        return false;
    }
    EGLDisplay display = eglGetPlatformDisplayEXT(EGL_PLATFORM_SURFACELESS_MESA, EGL_DEFAULT_DISPLAY, nullptr);
    EGLint major = 0, minor = 0;
    if (display == EGL_NO_DISPLAY || !eglInitialize(display, &major, &minor)) {
        *error = "eglInitialize failed on the surfaceless platform";
        return false;
    }
    if (!eglBindAPI(EGL_OPENGL_API)) {
        eglTerminate(display);
        *error = "eglBindAPI(EGL_OPENGL_API) failed";
        return false;
    }
    EGLConfig config = EGL_NO_CONFIG_KHR;
    if (!has_extension(eglQueryString(display, EGL_EXTENSIONS), "EGL_KHR_no_config_context")) {
        const EGLint attributes[] = {EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_SURFACE_TYPE, EGL_PBUFFER_BIT, EGL_NONE};
        EGLint count = 0;
        if (!eglChooseConfig(display, attributes, &config, 1, &count) || count == 0) {
            eglTerminate(display);
            *error = "no EGL config with desktop OpenGL";
            return false;
        }
    }
    const EGLint context_attributes[] = {EGL_CONTEXT_MAJOR_VERSION, 3, EGL_CONTEXT_MINOR_VERSION, 3,
                                         EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT, EGL_NONE};
    EGLContext context = eglCreateContext(display, config, EGL_NO_CONTEXT, context_attributes);
    if (context == EGL_NO_CONTEXT || !eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, context)) {
        if (context != EGL_NO_CONTEXT) eglDestroyContext(display, context);
        eglTerminate(display);
        *error = "cannot make an OpenGL 3.3 core context current without a surface";
        return false;
    }
    *display_out = display;
    *context_out = context;
    return true;
}

}  // namespace

std::unique_ptr<GlContext> GlContext::create(const GlContextDesc& desc, std::string* error) {
    std::unique_ptr<GlContext> context(new GlContext());
    std::string egl_error;
    if (!desc.window) {
        if (create_egl_surfaceless(&context->egl_display_, &context->egl_context_, &egl_error)) {
            context->kind_ = "EGL surfaceless";
            return context;
        }
    }
    if (!glfwInit()) {
        *error = "GlContext::create: no EGL surfaceless context (" + (egl_error.empty() ? "not tried" : egl_error) +
                 ") and GLFW cannot start (no display? try xvfb-run)";
        return nullptr;
    }
    glfwWindowHint(GLFW_CONTEXT_VERSION_MAJOR, 3);
    glfwWindowHint(GLFW_CONTEXT_VERSION_MINOR, 3);
    glfwWindowHint(GLFW_OPENGL_PROFILE, GLFW_OPENGL_CORE_PROFILE);
    glfwWindowHint(GLFW_OPENGL_FORWARD_COMPAT, GLFW_TRUE);
    glfwWindowHint(GLFW_VISIBLE, desc.window ? GLFW_TRUE : GLFW_FALSE);
    context->window_ = glfwCreateWindow(desc.width, desc.height, desc.title, nullptr, nullptr);
    if (!context->window_) {
        glfwTerminate();
        *error = "GlContext::create: GLFW cannot create an OpenGL 3.3 core window";
        return nullptr;
    }
    glfwMakeContextCurrent(context->window_);
    glfwSwapInterval(desc.vsync ? 1 : 0);
    context->visible_ = desc.window;
    context->kind_ = desc.window ? "GLFW window" : "GLFW hidden window";
    return context;
}

GlContext::~GlContext() {
    if (egl_context_) {
        eglMakeCurrent(egl_display_, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
        eglDestroyContext(egl_display_, egl_context_);
        eglTerminate(egl_display_);
    }
    if (window_) {
        glfwDestroyWindow(window_);
        glfwTerminate();
    }
}

bool GlContext::should_close() const { return window_ && glfwWindowShouldClose(window_); }

void GlContext::swap_and_poll() {
    if (!window_) return;
    glfwSwapBuffers(window_);
    glfwPollEvents();
}

void GlContext::set_title(const std::string& title) {
    if (window_) glfwSetWindowTitle(window_, title.c_str());
}

namespace {

std::string gl_text(GLenum name) {
    const GLubyte* s = glGetString(name);
    return s ? std::string(reinterpret_cast<const char*>(s)) : std::string("?");
}

}  // namespace

std::string GlContext::describe() const { return kind_ + ": " + gl_text(GL_RENDERER) + ", " + gl_text(GL_VERSION); }
std::string GlContext::renderer_name() const { return gl_text(GL_RENDERER); }
std::string GlContext::version() const { return gl_text(GL_VERSION); }

bool is_software_renderer(const std::string& gl_renderer) {
    std::string lower = gl_renderer;
    for (char& c : lower) c = char(std::tolower(static_cast<unsigned char>(c)));
    for (const char* name : {"llvmpipe", "softpipe", "swrast"})
        if (lower.find(name) != std::string::npos) return true;
    return false;
}

}  // namespace crowdview
