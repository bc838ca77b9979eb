// Window controls: a fly camera (left-drag to look, W/A/S/D/Q/E to move, Shift for speed).
#pragma once

#define GLFW_INCLUDE_NONE
#include <GLFW/glfw3.h>

#include "crowd.h"

namespace crowdview {

struct FlyControls {
    double last_x = 0, last_y = 0;
    bool dragging = false;
    float speed = 8.0f;  // metres per second

    void update(GLFWwindow* w, Camera* camera, float dt) {
        double x, y;
        glfwGetCursorPos(w, &x, &y);
        const bool down = glfwGetMouseButton(w, GLFW_MOUSE_BUTTON_LEFT) == GLFW_PRESS;
        if (down && dragging) {
            camera->yaw -= float(x - last_x) * 0.004f;
            camera->pitch = glm::clamp(camera->pitch - float(y - last_y) * 0.004f, -1.5f, 1.5f);
        }
        dragging = down;
        last_x = x, last_y = y;
        const glm::vec3 forward = camera->forward();
        const glm::vec3 right = glm::normalize(glm::cross(forward, glm::vec3(0, 1, 0)));
        const float step = speed * dt * (glfwGetKey(w, GLFW_KEY_LEFT_SHIFT) == GLFW_PRESS ? 4.0f : 1.0f);
        auto key = [&](int k) { return glfwGetKey(w, k) == GLFW_PRESS ? 1.0f : 0.0f; };
        camera->position += forward * step * (key(GLFW_KEY_W) - key(GLFW_KEY_S));
        camera->position += right * step * (key(GLFW_KEY_D) - key(GLFW_KEY_A));
        camera->position.y += step * (key(GLFW_KEY_E) - key(GLFW_KEY_Q));
    }
};

}  // namespace crowdview
