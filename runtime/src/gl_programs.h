// What every GL file of the renderer uses: labels for debuggers, programs built from shader files
// by name (<dir>/<name>.<stage>.glsl, niagara style, each `#include "x"` line replaced by <dir>/x),
// and the text of a GL error. Needs a current context (gl_context.h).
// Errors here are one line without a function prefix: the caller's public function adds its own.
#pragma once

#include <epoxy/gl.h>

#include <string>

namespace crowdview {

// Turns labels on where the context has KHR_debug (GL 4.3, or the extension); call once a
// context is current. Until then label() does nothing.
void enable_labels_if_supported();

// Names a GL object for debuggers (apitrace, RenderDoc); a no-op without KHR_debug.
void label(GLenum identifier, GLuint name, const std::string& text);

// The program of <vertex_name>.vert.glsl and <fragment_name>.frag.glsl in `dir`, labelled
// `fragment_name`. `defines` ("#define X 1\n" lines) go right after each file's #version line,
// which must come first. 0 and `error` (naming the file or program) when a file cannot be read
// or an include resolved, or a stage does not compile or the program does not link.
GLuint build_program(const std::string& dir, const std::string& vertex_name, const std::string& fragment_name,
                     std::string* error, const std::string& defines = "");

// The uniform's location, -1 where the program has none (which glUniform* ignores).
inline GLint uniform(GLuint program, const char* name) { return glGetUniformLocation(program, name); }

// "OpenGL error 0x0502" for a glGetError() code.
std::string gl_error_text(GLenum code);

}  // namespace crowdview
