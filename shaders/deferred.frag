#version 330 core
// The full-screen pass of deferred shading (see surface.frag): for each surface pixel of
// the G-buffer (gbuffer.glsl), the irradiance lattice's radiance (SHADING 5 or 7, as
// surface.frag defines them) and with DIRECT the per-pixel lights' direct light
// (direct.glsl), added to the HDR target (blending ONE, ONE; alpha unchanged).
#ifndef DIRECT
#define DIRECT 0
#endif
#include "lighting.glsl"
#include "gbuffer.glsl"
#if SHADING == 5 || SHADING == 7
#include "lattice.glsl"
#endif
#if DIRECT
#include "direct.glsl"
#endif

uniform sampler2D u_g_point;    // surface point (world), w = 1 on the surface
uniform sampler2D u_g_normals;  // octahedral shading normal and facet normal (eye side)
uniform vec3 u_albedo;

out vec4 frag_color;

void main() {
    ivec2 pixel = ivec2(gl_FragCoord.xy);
    vec4 point = texelFetch(u_g_point, pixel, 0);
    if (point.w == 0.0) discard;  // no surface here
    vec4 normals = texelFetch(u_g_normals, pixel, 0);
    vec3 n = from_octahedral(normals.xy);
    vec3 radiance = vec3(0.0);
#if SHADING == 5 || SHADING == 7
    radiance += lattice_radiance(point.xyz, n, u_albedo);
#endif
#if DIRECT
    // the smooth normal on the side of the facet the eye sees (as the reference and the
    // baker's start points turn it: at silhouettes it may point away from the eye)
    vec3 facet = from_octahedral(normals.zw);
    vec3 n_seen = dot(n, facet) < 0.0 ? -n : n;
    // from where the baker's paths start: off the surface along the normal
    radiance += u_albedo * direct_irradiance(point.xyz + u_direct_offset * n_seen, n_seen,
                                             facet) / PI;
#endif
    frag_color = vec4(radiance, 0.0);
}
