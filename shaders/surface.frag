#version 330 core
// Shades the isosurface into a linear HDR target. SHADING selects the model:
//   1 lambert, 2 phong, 3 lambert + hemisphere ambient, 4 phong + hemisphere ambient,
//   5 lattice irradiance (albedo E / pi), 6 lattice SH transfer under a rotating
//   environment, 9 world position (for tests and picking).
#include "lighting.glsl"
#if SHADING == 5 || SHADING == 6
#include "lattice.glsl"
#endif

uniform vec3 u_eye;
uniform vec3 u_albedo;

in vec3 v_world;
in vec3 v_normal;

out vec4 frag_color;

void main() {
#if SHADING == 9
    frag_color = vec4(v_world, 1.0);
    return;
#endif
    vec3 v = normalize(u_eye - v_world);
    vec3 n = normalize(v_normal);
    // Local models light both sides of the surface: turn the normal towards the eye.
    if (dot(n, v) < 0.0) n = -n;
#if SHADING == 5 || SHADING == 6
    frag_color = vec4(lattice_radiance(v_world, n, u_albedo), 1.0);
    return;
#endif
    vec3 e = lambert_irradiance(n, v);
#if SHADING == 3 || SHADING == 4
    e += hemisphere_irradiance(n);
#endif
    vec3 radiance = u_albedo * e / PI;
#if SHADING == 2 || SHADING == 4
    radiance += phong_radiance(n, v);
#endif
    frag_color = vec4(radiance, 1.0);
}
