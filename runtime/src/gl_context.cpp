// GL context creation: EGL devices, then EGL surfaceless, for headless runs; GLFW for windows.
#include "gl_context.h"

#include <epoxy/egl.h>
#include <epoxy/gl.h>
#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>
#include <nlohmann/json.hpp>

#include <cctype>
#include <cstdlib>
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

std::string gl_text(GLenum name) {
    const GLubyte* s = glGetString(name);
    return s ? std::string(reinterpret_cast<const char*>(s)) : std::string("?");
}

std::string join(const std::vector<std::string>& parts, const char* separator) {
    std::string out;
    for (const std::string& p : parts) out += (out.empty() ? "" : separator) + p;
    return out;
}

// One EGL device, as eglQueryDevicesEXT lists it (glvnd lists every vendor library's devices).
struct EglDevice {
    EGLDeviceEXT handle = EGL_NO_DEVICE_EXT;
    std::string name;        // "/dev/dri/card0, CUDA device 0", "Mesa software", or "unnamed"
    std::string extensions;  // the device's own (eglQueryDeviceStringEXT)
    bool software = false;   // EGL_MESA_device_software: llvmpipe dressed as a device
};

// The device's DRM node and CUDA index where its driver names them.
std::string device_name(EGLDeviceEXT device, const char* extensions) {
    if (has_extension(extensions, "EGL_MESA_device_software")) return "Mesa software";
    std::vector<std::string> parts;
    if (has_extension(extensions, "EGL_EXT_device_drm"))
        if (const char* file = eglQueryDeviceStringEXT(device, EGL_DRM_DEVICE_FILE_EXT)) parts.push_back(file);
    EGLAttrib cuda = 0;
    if (has_extension(extensions, "EGL_NV_device_cuda") && eglQueryDeviceAttribEXT(device, EGL_CUDA_DEVICE_NV, &cuda))
        parts.push_back("CUDA device " + std::to_string(cuda));
    return parts.empty() ? "unnamed" : join(parts, ", ");
}

// Every EGL device, in the order EGL lists them; false and `error` where EGL cannot list devices
// or make displays on them. The client extensions are checked first: epoxy resolves these entry
// points through eglGetProcAddress on first call, and aborts where none of their extensions exists.
bool list_egl_devices(std::vector<EglDevice>* devices, std::string* error) {
    const char* client = eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS);
    const bool base = has_extension(client, "EGL_EXT_device_base");
    if (!base && !(has_extension(client, "EGL_EXT_device_enumeration") && has_extension(client, "EGL_EXT_device_query"))) {
        *error = "EGL cannot list devices (no EGL_EXT_device_enumeration)";
        return false;
    }
    if (!has_extension(client, "EGL_EXT_platform_device")) {
        *error = "EGL cannot make a display on a device (no EGL_EXT_platform_device)";
        return false;
    }
    EGLint count = 0;
    if (!eglQueryDevicesEXT(0, nullptr, &count) || count < 0) {
        *error = "eglQueryDevicesEXT failed";
        return false;
    }
    std::vector<EGLDeviceEXT> handles(size_t(count), EGL_NO_DEVICE_EXT);
    if (count > 0 && !eglQueryDevicesEXT(count, handles.data(), &count)) {
        *error = "eglQueryDevicesEXT failed";
        return false;
    }
    devices->clear();
    for (EGLint i = 0; i < count; ++i) {
        EglDevice d;
        d.handle = handles[size_t(i)];
        const char* extensions = eglQueryDeviceStringEXT(d.handle, EGL_EXTENSIONS);
        d.extensions = extensions ? extensions : "";
        d.software = has_extension(extensions, "EGL_MESA_device_software");
        d.name = device_name(d.handle, extensions);
        devices->push_back(d);
    }
    return true;
}

// "2 EGL devices: 0 /dev/dri/card0, CUDA device 0; 1 Mesa software", for errors.
std::string list_text(const std::vector<EglDevice>& devices) {
    std::vector<std::string> entries;
    for (size_t i = 0; i < devices.size(); ++i) entries.push_back(std::to_string(i) + " " + devices[i].name);
    return std::to_string(devices.size()) + (devices.size() == 1 ? " EGL device" : " EGL devices") +
           (devices.empty() ? "" : ": " + join(entries, "; "));
}

struct EglCurrent {
    EGLDisplay display = EGL_NO_DISPLAY;
    EGLContext context = EGL_NO_CONTEXT;
};

void release(EglCurrent* egl) {
    if (egl->context != EGL_NO_CONTEXT) {
        eglMakeCurrent(egl->display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
        eglDestroyContext(egl->display, egl->context);
    }
    if (egl->display != EGL_NO_DISPLAY) eglTerminate(egl->display);
    *egl = EglCurrent();
}

// A GL 3.3 core context current on `display` with no surface (EGL_KHR_surfaceless_context): the
// renderer draws into its own framebuffer. On failure the display is terminated.
bool make_current_without_surface(EGLDisplay display, EglCurrent* out, std::string* error) {
    EGLint major = 0, minor = 0;
    if (display == EGL_NO_DISPLAY || !eglInitialize(display, &major, &minor)) {
        *error = "eglInitialize failed";
        return false;
    }
    EglCurrent egl;
    egl.display = display;
    if (!eglBindAPI(EGL_OPENGL_API)) {
        release(&egl);
        *error = "eglBindAPI(EGL_OPENGL_API) failed";
        return false;
    }
    EGLConfig config = EGL_NO_CONFIG_KHR;
    if (!has_extension(eglQueryString(display, EGL_EXTENSIONS), "EGL_KHR_no_config_context")) {
        const EGLint attributes[] = {EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_SURFACE_TYPE, EGL_PBUFFER_BIT, EGL_NONE};
        EGLint count = 0;
        if (!eglChooseConfig(display, attributes, &config, 1, &count) || count == 0) {
            release(&egl);
            *error = "no EGL config with desktop OpenGL";
            return false;
        }
    }
    const EGLint context_attributes[] = {EGL_CONTEXT_MAJOR_VERSION, 3, EGL_CONTEXT_MINOR_VERSION, 3,
                                         EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT, EGL_NONE};
    egl.context = eglCreateContext(display, config, EGL_NO_CONTEXT, context_attributes);
    if (egl.context == EGL_NO_CONTEXT || !eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, egl.context)) {
        release(&egl);
        *error = "cannot make an OpenGL 3.3 core context current without a surface";
        return false;
    }
    *out = egl;
    return true;
}

bool make_on_device(const EglDevice& device, EglCurrent* out, std::string* error) {
    return make_current_without_surface(eglGetPlatformDisplayEXT(EGL_PLATFORM_DEVICE_EXT, device.handle, nullptr), out, error);
}

// Mesa's surfaceless platform: no window system and no device named.
bool make_surfaceless(EglCurrent* out, std::string* error) {
    if (!has_extension(eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS), "EGL_MESA_platform_surfaceless")) {
        *error = "EGL_MESA_platform_surfaceless is not available";
        return false;
    }
    if (make_current_without_surface(eglGetPlatformDisplayEXT(EGL_PLATFORM_SURFACELESS_MESA, EGL_DEFAULT_DISPLAY, nullptr), out, error))
        return true;
    *error = "EGL surfaceless: " + *error;
    return false;
}

void set_device(const std::vector<EglDevice>& devices, size_t index, GlContextInfo* info) {
    info->context = "EGL device";
    info->device_index = int(index);
    info->device_count = int(devices.size());
    info->device_name = devices[index].name;
    info->device_extensions = devices[index].extensions;
}

// --gl-device N or software: that device or nothing.
bool make_on_named_device(const GlDeviceChoice& choice, EglCurrent* out, GlContextInfo* info, std::string* error) {
    std::vector<EglDevice> devices;
    std::string list_error;
    if (!list_egl_devices(&devices, &list_error)) {
        *error = (choice.kind == GlDeviceChoice::software ? "no software EGL device: " : "no EGL device " + std::to_string(choice.index) + ": ") +
                 list_error;
        return false;
    }
    size_t index = size_t(choice.index);
    if (choice.kind == GlDeviceChoice::software) {
        for (index = 0; index < devices.size() && !devices[index].software; ++index) {}
        if (index == devices.size()) {
            *error = "no software EGL device (EGL_MESA_device_software) among " + list_text(devices);
            return false;
        }
    } else if (index >= devices.size()) {
        *error = "there is no EGL device " + std::to_string(choice.index) + "; this machine has " + list_text(devices);
        return false;
    }
    std::string why;
    if (!make_on_device(devices[index], out, &why)) {
        *error = "EGL device " + std::to_string(index) + " (" + devices[index].name + "): " + why;
        return false;
    }
    set_device(devices, index, info);
    return true;
}

// --gl-device auto: the first hardware device whose context is not a software rasteriser, else
// Mesa surfaceless. What was passed over goes to info->passed_over.
bool make_headless_automatic(EglCurrent* out, GlContextInfo* info, std::string* error) {
    std::vector<EglDevice> devices;
    std::string list_error;
    const bool listed = list_egl_devices(&devices, &list_error);
    if (!listed) info->passed_over.push_back("EGL devices: " + list_error);
    size_t hardware = 0;
    for (size_t i = 0; i < devices.size(); ++i) {
        if (devices[i].software) continue;
        ++hardware;
        std::string why;
        if (make_on_device(devices[i], out, &why)) {
            const std::string renderer = gl_text(GL_RENDERER);
            if (!is_software_renderer(renderer)) {
                set_device(devices, i, info);
                return true;
            }
            why = "renders on " + renderer;
            release(out);
        }
        info->passed_over.push_back("EGL device " + std::to_string(i) + " of " + std::to_string(devices.size()) + " (" + devices[i].name +
                                    "): " + why);
    }
    if (listed && hardware == 0) info->passed_over.push_back("EGL devices: none is hardware (" + list_text(devices) + ")");
    if (!make_surfaceless(out, error)) return false;
    info->context = "EGL surfaceless";
    return true;
}

// "EGL device 0 of 1 (Mesa software)", "EGL surfaceless", ...: no ": ", which parts the describe() text.
std::string context_name(const GlContextInfo& info) {
    if (info.device_index < 0) return info.context;
    return info.context + " " + std::to_string(info.device_index) + " of " + std::to_string(info.device_count) + " (" + info.device_name + ")";
}

}  // namespace

bool parse_gl_device(const std::string& text, GlDeviceChoice* choice) {
    if (text == "auto" || text == "software") {
        choice->kind = text == "auto" ? GlDeviceChoice::automatic : GlDeviceChoice::software;
        return true;
    }
    if (text.empty() || text.size() > 4 || text.find_first_not_of("0123456789") != std::string::npos) return false;
    choice->kind = GlDeviceChoice::numbered;
    choice->index = std::atoi(text.c_str());
    return true;
}

bool GlContext::make_headless(const GlDeviceChoice& choice, std::string* error) {
    EglCurrent egl;
    const bool made = choice.kind == GlDeviceChoice::automatic ? make_headless_automatic(&egl, &info_, error)
                                                                : make_on_named_device(choice, &egl, &info_, error);
    if (!made) return false;
    egl_display_ = egl.display;
    egl_context_ = egl.context;
    return true;
}

bool GlContext::make_glfw(const GlContextDesc& desc, std::string* error) {
    if (!glfwInit()) {
        *error = "GLFW cannot start (no display? try xvfb-run)";
        return false;
    }
    glfwWindowHint(GLFW_CONTEXT_VERSION_MAJOR, 3);
    glfwWindowHint(GLFW_CONTEXT_VERSION_MINOR, 3);
    glfwWindowHint(GLFW_OPENGL_PROFILE, GLFW_OPENGL_CORE_PROFILE);
    glfwWindowHint(GLFW_OPENGL_FORWARD_COMPAT, GLFW_TRUE);
    glfwWindowHint(GLFW_VISIBLE, desc.window ? GLFW_TRUE : GLFW_FALSE);
    window_ = glfwCreateWindow(desc.width, desc.height, desc.title, nullptr, nullptr);
    if (!window_) {
        glfwTerminate();
        *error = "GLFW cannot create an OpenGL 3.3 core window";
        return false;
    }
    glfwMakeContextCurrent(window_);
    glfwSwapInterval(desc.vsync ? 1 : 0);
    visible_ = desc.window;
    info_.context = desc.window ? "GLFW window" : "GLFW hidden window";
    return true;
}

std::unique_ptr<GlContext> GlContext::create(const GlContextDesc& desc, std::string* error) {
    std::unique_ptr<GlContext> context(new GlContext());
    GlContextInfo& info = context->info_;
    std::string why;
    bool made = false;
    if (!desc.window) {
        made = context->make_headless(desc.device, &why);
        if (!made && desc.device.kind != GlDeviceChoice::automatic) {
            *error = "GlContext::create: " + why;
            return nullptr;
        }
        if (!made) info.passed_over.push_back(why);
    }
    if (!made && !context->make_glfw(desc, &why)) {
        info.passed_over.push_back(why);
        *error = "GlContext::create: no context: " + join(info.passed_over, "; ");
        return nullptr;
    }
    info.vendor = gl_text(GL_VENDOR);
    info.renderer = gl_text(GL_RENDERER);
    info.version = gl_text(GL_VERSION);
    if (desc.require_gpu && is_software_renderer(info.renderer)) {
        *error = "GlContext::create: a GPU is required, and the context found, " + context_name(info) + ", renders on " + info.renderer +
                 ", a software rasteriser" + (info.passed_over.empty() ? "" : "; passed over: " + join(info.passed_over, "; "));
        return nullptr;
    }
    return context;
}

GlContext::~GlContext() {
    EglCurrent egl;
    egl.display = egl_display_;
    egl.context = egl_context_;
    if (egl_display_) release(&egl);
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

std::string GlContext::describe() const { return context_name(info_) + ": " + info_.renderer + ", " + info_.version; }

std::string gl_context_line(const GlContextInfo& info) {
    std::string line = "GL_RENDERER " + info.renderer + "; GL_VERSION " + info.version + "; GL_VENDOR " + info.vendor + "; " + context_name(info);
    if (!info.passed_over.empty()) line += "; passed over: " + join(info.passed_over, "; ");
    return line;
}

nlohmann::json gl_report(const GlContextInfo& info) {
    nlohmann::json device = nullptr;
    if (info.device_index >= 0)
        device = {{"index", info.device_index}, {"count", info.device_count}, {"name", info.device_name}, {"extensions", info.device_extensions}};
    return {{"context", info.context},
            {"device", device},
            {"vendor", info.vendor},
            {"renderer", info.renderer},
            {"version", info.version},
            {"software_rasteriser", is_software_renderer(info.renderer)},
            {"passed_over", info.passed_over}};
}

bool is_software_renderer(const std::string& gl_renderer) {
    std::string lower = gl_renderer;
    for (char& c : lower) c = char(std::tolower(static_cast<unsigned char>(c)));
    for (const char* name : {"llvmpipe", "softpipe", "swrast"})
        if (lower.find(name) != std::string::npos) return true;
    return false;
}

}  // namespace crowdview
