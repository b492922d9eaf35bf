#version 330 core
// Depth pass of one tile of the direct lights' shadow atlas: isosurface vertices (world)
// -> the tile's clip space, with the linear depth dot(u_depth.xyz, p) + u_depth.w in [0, 1]
// passed on (for a point light's perspective faces, depth along the face's axis).
uniform mat4 u_view_proj;
uniform vec4 u_depth;

in vec3 in_position;
out float v_depth;

void main() {
    v_depth = dot(u_depth.xyz, in_position) + u_depth.w;
    gl_Position = u_view_proj * vec4(in_position, 1.0);
}
