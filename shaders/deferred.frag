#version 330 core
// The full-screen pass of deferred shading (see surface.frag): for each surface pixel of
// the G-buffer (gbuffer.glsl), with DEFERRED the lattice's radiance (SHADING 5-7 as in
// surface.frag; alpha 1 marks the surface) and with DIRECT the per-pixel lights' direct
// light (direct.glsl), added to the HDR target (blending ONE, ONE).
#ifndef DEFERRED
#define DEFERRED 0
#endif
#ifndef DIRECT
#define DIRECT 0
#endif
#include "lighting.glsl"
#include "gbuffer.glsl"
#if DEFERRED
#include "lattice.glsl"
#endif
#if DIRECT
#include "direct.glsl"
#endif

uniform sampler2D u_gbuffer;
uniform vec3 u_eye;
// the eye ray through pixel centre (x, y) of gl_FragCoord runs along ray0 + x rayx + y rayy
uniform vec3 u_ray0;
uniform vec3 u_rayx;
uniform vec3 u_rayy;
uniform vec3 u_albedo;

out vec4 frag_color;

void main() {
    vec4 g = texelFetch(u_gbuffer, ivec2(gl_FragCoord.xy), 0);
    if (g.x == 0.0) discard;  // no surface here
    vec3 point = u_eye + g.x * normalize(u_ray0 + gl_FragCoord.x * u_rayx
                                         + gl_FragCoord.y * u_rayy);
    vec3 n = from_octahedral(g.yz);
#if DEFERRED
    frag_color = vec4(lattice_radiance(point, n, u_albedo), 1.0);
#else
    frag_color = vec4(0.0);  // the surface pass drew the radiance and the alpha
#endif
#if DIRECT
    // the smooth normal on the side of the facet the eye sees (as the reference and the
    // baker's start points turn it: at silhouettes it may point away from the eye)
    vec3 facet = unpack_normal(g.w);
    vec3 n_seen = dot(n, facet) < 0.0 ? -n : n;
    // from where the baker's paths start: off the surface along the normal
    frag_color.rgb += u_albedo * direct_irradiance(point + u_direct_offset * n_seen, n_seen,
                                                   facet) / PI;
#endif
}
