// What the surface pass leaves for the full-screen pass (deferred.frag) in two RGBA32F
// targets: the surface point (world, w = 1 on the surface, 0 elsewhere) and two unit
// normals turned to the side the eye sees, the shading normal and the facet normal (only
// read with per-pixel lights), each in octahedral coordinates (two floats; exact to ~1e-7
// in 32-bit floats).

// Octahedral coordinates in [-1, 1]^2 of unit vector n (Meyer et al. 2010).
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

vec4 encode_normals(vec3 shading, vec3 facet) {
    return vec4(octahedral(shading), octahedral(facet));
}
