// Lattice lookup: world position -> texture coordinate -> hardware trilinear filtering.
// The lattice spans the volume's world box [u_box_lo, u_box_lo + u_box_size]; GL places
// texel centres at (i + 0.5) / n, exactly where the lattice's texel centres are, so the
// mapping needs no half-texel correction. Textures hold values * valid; dividing by the
// interpolated `valid` interpolates over computed texels only.
uniform sampler3D u_valid;       // 1 where the texel has been computed
uniform vec3 u_box_lo;
uniform vec3 u_box_size;

const vec3 UNBAKED_TINT = vec3(0.8, 0.85, 1.0);

vec3 lattice_coord(vec3 world) {
    return (world - u_box_lo) / u_box_size;
}

// Baked radiance where the lattice is computed; elsewhere hemisphere-ambient Lambert with
// a cool tint shows through, so unbaked regions are visible but still readable.
vec3 lattice_blend(float w, vec3 irradiance_times_w, vec3 n, vec3 albedo) {
    vec3 baked = albedo * max(irradiance_times_w / max(w, 1e-4), 0.0) / PI;
    vec3 fallback = UNBAKED_TINT * albedo * (hemisphere_irradiance(n) + 0.5 * u_key_irradiance
                    * max(dot(n, u_key_dir), 0.0)) / PI;
    return mix(fallback, baked, smoothstep(0.0, 0.25, w));
}

#if SHADING == 5
uniform sampler3D u_irradiance;  // E * valid, GL_RGB9_E5

vec3 lattice_radiance(vec3 world, vec3 n, vec3 albedo) {
    vec3 tc = lattice_coord(world);
    return lattice_blend(texture(u_valid, tc).r, texture(u_irradiance, tc).rgb, n, albedo);
}
#endif

#if SHADING == 6
// SH transfer: E = sum_i tau_i l_i, with tau from SH_TEXTURES RGBA16F textures per colour
// group and the rotated environment coefficients l in u_light (four per vec4, red first).
SH_DECLARE
uniform vec4 u_light[3 * SH_TEXTURES];

vec3 lattice_radiance(vec3 world, vec3 n, vec3 albedo) {
    vec3 tc = lattice_coord(world);
    return lattice_blend(texture(u_valid, tc).r, SH_IRRADIANCE(tc), n, albedo);
}
#endif
