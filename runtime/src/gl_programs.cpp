// Labels, shader programs from files, GL error text (see gl_programs.h).
#include "gl_programs.h"

#include <cstdio>
#include <fstream>
#include <sstream>

namespace crowdview {

namespace {

bool g_has_labels = false;

bool read_text(const std::string& path, std::string* text) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return false;
    std::stringstream ss;
    ss << in.rdbuf();
    *text = ss.str();
    return true;
}

// `<dir>/<file>` with each `#include "x"` line replaced by `<dir>/x` (one level: config.h).
bool load_shader_source(const std::string& dir, const std::string& file, std::string* source, std::string* error) {
    std::string text;
    if (!read_text(dir + "/" + file, &text)) {
        *error = "cannot read " + dir + "/" + file;
        return false;
    }
    std::istringstream lines(text);
    std::string line;
    source->clear();
    while (std::getline(lines, line)) {
        const size_t open = line.find("#include \"");
        if (open != std::string::npos && line.find_first_not_of(" \t") == open) {
            const size_t close = line.find('"', open + 10);
            std::string included;
            if (close == std::string::npos || !read_text(dir + "/" + line.substr(open + 10, close - open - 10), &included)) {
                *error = file + ": cannot resolve " + line;
                return false;
            }
            *source += included + "\n";
        } else {
            *source += line + "\n";
        }
    }
    return true;
}

// `defines` ("#define X 1\n" lines) go right after the #version line, which must come first.
GLuint compile_shader(GLenum stage, const std::string& dir, const std::string& file, const std::string& defines,
                      std::string* error) {
    std::string source;
    if (!load_shader_source(dir, file, &source, error)) return 0;
    if (!defines.empty()) {
        const size_t end_of_version = source.find('\n');
        source.insert(end_of_version == std::string::npos ? source.size() : end_of_version + 1, defines);
    }
    GLuint shader = glCreateShader(stage);
    const char* text = source.c_str();
    glShaderSource(shader, 1, &text, nullptr);
    glCompileShader(shader);
    GLint ok = 0;
    glGetShaderiv(shader, GL_COMPILE_STATUS, &ok);
    if (!ok) {
        char log[2048] = "";
        glGetShaderInfoLog(shader, sizeof log, nullptr, log);
        *error = file + ": " + log;
        glDeleteShader(shader);
        return 0;
    }
    label(GL_SHADER, shader, file);
    return shader;
}

}  // namespace

void enable_labels_if_supported() { g_has_labels = epoxy_gl_version() >= 43 || epoxy_has_gl_extension("GL_KHR_debug"); }

void label(GLenum identifier, GLuint name, const std::string& text) {
    if (g_has_labels) glObjectLabel(identifier, name, GLsizei(text.size()), text.c_str());
}

GLuint build_program(const std::string& dir, const std::string& vertex_name, const std::string& fragment_name,
                     std::string* error, const std::string& defines) {
    GLuint vs = compile_shader(GL_VERTEX_SHADER, dir, vertex_name + ".vert.glsl", defines, error);
    if (!vs) return 0;
    GLuint fs = compile_shader(GL_FRAGMENT_SHADER, dir, fragment_name + ".frag.glsl", defines, error);
    if (!fs) {
        glDeleteShader(vs);
        return 0;
    }
    GLuint program = glCreateProgram();
    glAttachShader(program, vs);
    glAttachShader(program, fs);
    glLinkProgram(program);
    glDeleteShader(vs);
    glDeleteShader(fs);
    GLint ok = 0;
    glGetProgramiv(program, GL_LINK_STATUS, &ok);
    if (!ok) {
        char log[2048] = "";
        glGetProgramInfoLog(program, sizeof log, nullptr, log);
        *error = fragment_name + " program: " + log;
        glDeleteProgram(program);
        return 0;
    }
    label(GL_PROGRAM, program, fragment_name);
    return program;
}

std::string gl_error_text(GLenum code) {
    char hex[16];
    std::snprintf(hex, sizeof hex, "%04x", code);
    return std::string("OpenGL error 0x") + hex;
}

}  // namespace crowdview
