// The G-buffer the surface pass leaves for the full-screen pass (deferred.frag): one
// RGBA32F target per pixel,
//   x   the eye's distance to the surface point (world units; 0 where there is no surface),
//   yz  the shading normal, turned to the eye, in octahedral coordinates (Meyer et al.
//       2010; exact to ~1e-7),
//   w   the facet normal, turned to the eye, in octahedral coordinates quantised to 12
//       bits each and packed into one integer below 2^24 (exact in a float; 5e-4 radians).
// The point is rebuilt on the pixel's eye ray (u_eye + t * direction; `GBufferRay`), so a
// single 16-byte write per fragment serves the lattice and the lights.

// Octahedral coordinates in [-1, 1]^2 of unit vector n.
vec2 octahedral(vec3 n) {
    vec2 p = n.xy / (abs(n.x) + abs(n.y) + abs(n.z));
    if (n.z < 0.0) p = (1.0 - abs(p.yx)) * vec2(p.x >= 0.0 ? 1.0 : -1.0,
                                                   p.y >= 0.0 ? 1.0 : -1.0);
    return p;
}

// The unit vector of octahedral coordinates p.
vec3 from_octahedral(vec2 p) {
    vec3 n = vec3(p, 1.0 - abs(p.x) - abs(p.y));
    if (n.z < 0.0) n.xy = (1.0 - abs(n.yx)) * vec2(n.x >= 0.0 ? 1.0 : -1.0,
                                                   n.y >= 0.0 ? 1.0 : -1.0);
    return normalize(n);
}

const float OCT_STEPS = 4095.0;  // 12 bits per octahedral coordinate

float pack_normal(vec3 n) {
    vec2 q = floor((octahedral(n) * 0.5 + 0.5) * OCT_STEPS + 0.5);
    return q.x + 4096.0 * q.y;
}

vec3 unpack_normal(float code) {
    float y = floor(code / 4096.0);
    vec2 q = vec2(code - 4096.0 * y, y);
    return from_octahedral(q / OCT_STEPS * 2.0 - 1.0);
}

// One pixel's G-buffer value: eye distance t > 0, shading normal n, facet normal.
vec4 gbuffer_value(float t, vec3 n, vec3 facet) {
    return vec4(t, octahedral(n), pack_normal(facet));
}
