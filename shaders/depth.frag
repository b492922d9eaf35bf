#version 330 core
// Depth pass of the direct lights' shadow atlas: linear depth (see depth.vert).
in float v_depth;

void main() {
    gl_FragDepth = clamp(v_depth, 0.0, 1.0);
}
