#version 330 core
// Depth pass of the direct lights' shadow atlas: linear depth (see depth.vert), also as a
// colour (an R32F copy that the blocker search reads: on llvmpipe a float texture is read
// several times faster than a depth texture without comparison).
in float v_depth;
out float depth_copy;

void main() {
    gl_FragDepth = clamp(v_depth, 0.0, 1.0);
    depth_copy = gl_FragDepth;
}
