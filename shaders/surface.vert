#version 330 core
// Isosurface vertices in world units; the fragment shader works in world space.
uniform mat4 u_view_proj;

in vec3 in_position;
in vec3 in_normal;

out vec3 v_world;
out vec3 v_normal;

void main() {
    v_world = in_position;
    v_normal = in_normal;
    gl_Position = u_view_proj * vec4(in_position, 1.0);
}
