// Lattice lookup: world position -> texture coordinate -> hardware trilinear filtering.
// The lattice spans the volume's world box [u_box_lo, u_box_lo + u_box_size]; GL places
// texel centres at (i + 0.5) / n, exactly where the lattice's texel centres are, so the
// mapping needs no half-texel correction.
uniform sampler3D u_irradiance;  // E * valid, GL_RGB9_E5
uniform sampler3D u_valid;       // 1 where the texel has been computed
uniform vec3 u_box_lo;
uniform vec3 u_box_size;

const vec3 UNBAKED_TINT = vec3(0.8, 0.85, 1.0);

vec3 lattice_coord(vec3 world) {
    return (world - u_box_lo) / u_box_size;
}

// Radiance albedo * E / pi from the lattice, interpolating over computed texels only;
// where none is computed yet, hemisphere-ambient Lambert with a cool tint shows through.
vec3 lattice_radiance(vec3 world, vec3 n, vec3 albedo) {
    vec3 tc = lattice_coord(world);
    float w = texture(u_valid, tc).r;
    vec3 e = texture(u_irradiance, tc).rgb;
    vec3 baked = albedo * e / max(w, 1e-4) / PI;
    vec3 fallback = UNBAKED_TINT * albedo * (hemisphere_irradiance(n) + 0.5 * u_key_irradiance
                    * max(dot(n, u_key_dir), 0.0)) / PI;
    return mix(fallback, baked, smoothstep(0.0, 0.25, w));
}
