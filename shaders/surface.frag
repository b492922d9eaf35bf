#version 330 core
// Shades the isosurface into a linear HDR target. SHADING selects the model:
//   1 lambert, 2 phong, 3 lambert + hemisphere ambient, 4 phong + hemisphere ambient,
//   5 lattice irradiance (albedo E / pi; also vicinity shading), 6 lattice SH transfer
//   under a rotating environment, 7 ambient occlusion (lattice E / (pi L_sky) times
//   hemisphere-ambient Lambert), 9 world position (for tests and picking).
// Feature switches of the local models (1-4): SHADOW 1 shadow-maps the key light,
// FOG 1 fades to the fog colour with eye distance. LOOKUP picks how irradiance lattices
// (5, 7) are read: 0 trilinear, 1 nearest texel, 2 closest-isovalue texel, 3 B-spline.
// DIRECT 1 (with 5 or 7): the lattice holds all but the direct light of the
// point/directional lights and the sun, added per pixel with shadows; with 6: a split SH
// transfer, shown under the sun-free sky, plus the turned sun per pixel.
//
// Deferred shading: with DEFERRED 1 (the lattice modes 5-7) the lattice and the per-pixel
// lights are not shaded here but in one full-screen pass (deferred.frag) over what this
// pass leaves in the G-buffer (gbuffer.glsl): the point's eye distance and its normals.
// On llvmpipe a draw shades every 4x4 block a triangle touches, and a dense isosurface's
// triangles cover a pixel or two each, so lookups made here ran for many times more SIMD
// lanes than there are pixels. This pass then writes the G-buffer alone, and the
// full-screen pass the HDR target. SH transfer (6) is drawn here (DEFERRED 0) when its
// textures, the G-buffer and the shadow atlas would not fit one pass's 16 texture units;
// with DIRECT it writes the G-buffer too, for the lights.
#ifndef DEFERRED
#define DEFERRED 0
#endif
#ifndef SHADOW
#define SHADOW 0
#endif
#ifndef FOG
#define FOG 0
#endif
#ifndef LOOKUP
#define LOOKUP 0
#endif
#ifndef DIRECT
#define DIRECT 0
#endif
#include "lighting.glsl"
#if SHADOW
#include "shadow.glsl"
#endif
#if DEFERRED || DIRECT || SHADING == 6
#include "gbuffer.glsl"
#endif
#if SHADING == 6 && !DEFERRED
#include "lattice.glsl"
#endif

uniform vec3 u_eye;
uniform vec3 u_albedo;
uniform vec3 u_fog_color;  // radiance the fog fades to (the background before exposure)

in vec3 v_world;
in vec3 v_normal;

#if DEFERRED
layout(location = 0) out vec4 g_surface;  // gbuffer.glsl; the HDR target is not drawn
#else
layout(location = 0) out vec4 frag_color;
#if DIRECT
layout(location = 1) out vec4 g_surface;
#endif
#endif

void main() {
#if SHADING == 9
    frag_color = vec4(v_world, 1.0);
#else
    vec3 v = normalize(u_eye - v_world);
    vec3 n = normalize(v_normal);
    // Local models light both sides of the surface: turn the normal towards the eye.
    if (dot(n, v) < 0.0) n = -n;
#if DIRECT
    // the facet's normal on the side the eye sees (the per-pixel lights' receiver plane)
    vec3 facet_n = normalize(cross(dFdx(v_world), dFdy(v_world)));
    if (dot(facet_n, v) < 0.0) facet_n = -facet_n;
    g_surface = gbuffer_value(length(u_eye - v_world), n, facet_n);
#elif DEFERRED
    g_surface = gbuffer_value(length(u_eye - v_world), n, n);
#endif
#if DEFERRED
#elif SHADING == 6
    frag_color = vec4(lattice_radiance(v_world, n, u_albedo), 1.0);
#else
#if SHADOW
    vec3 facet = normalize(cross(dFdx(v_world), dFdy(v_world)));
    float visibility = key_visibility(v_world, facet);
#else
    float visibility = 1.0;
#endif
    vec3 e = lambert_irradiance(n, v, visibility);
#if SHADING == 3 || SHADING == 4
    e += hemisphere_irradiance(n);
#endif
    vec3 radiance = u_albedo * e / PI;
#if SHADING == 2 || SHADING == 4
    radiance += phong_radiance(n, v, visibility);
#endif
#if FOG
    radiance = mix(u_fog_color, radiance, fog_transmittance(length(u_eye - v_world)));
#endif
    frag_color = vec4(radiance, 1.0);
#endif
#endif
}
