// Lattice lookup: world position -> lattice coordinate -> the stored illumination.
// The lattice spans the volume's world box [u_box_lo, u_box_lo + u_box_size] with texel
// centres at (i + 0.5) / n of it, as GL places them. The texels live in bricks of BRICK^3
// in the slots of atlas textures (app/render/bricks.py): u_bricks sends the brick of a
// cell's lower corner to its slot, which holds the brick and a one-texel apron, so the
// eight texels of any cell, and a hardware trilinear fetch inside it, come from one slot.
// Textures hold values * valid; dividing by the matching lookup of `valid` interpolates
// over computed texels only (every lookup below returns the pair (value * w, w) for that
// reason).
//
// FACING 1: the side-aware lookup (trilinear irradiance, LOOKUP 0, and SH transfer). Each
// texel's facing m, the mean direction its paths started along, weights it by
// max(0, n.m)^FACING_POWER for a point whose normal n is turned to the eye (1 where m is
// unknown), so a face of a thin wall, or the other side of a sheet, does not show light
// gathered on the opposite face; where these weights sum to less than FACING_BLEND of the
// plain ones, the lookup blends into the plain mix (smoothstep from 0: no texel facing
// the point's way leaves the plain mix; baking.sided.sided_mix is the same on the CPU).
// Needs gbuffer.glsl (from_octahedral) included before it.
#ifndef FACING
#define FACING 0
#endif
#ifndef FACING_POWER
#define FACING_POWER 2
#endif
#ifndef FACING_BLEND
#define FACING_BLEND 0.1
#endif
#define BRICK 8
#define STORED 9
uniform sampler3D u_state;       // R: 1 where the texel has been computed; GB: its facing
uniform usampler3D u_bricks;     // per brick: the (x, y, z) of its slot, in slots
uniform vec3 u_lattice_size;     // texels of the lattice, x y z
uniform vec3 u_atlas_size;       // texels of the atlases, x y z
uniform vec3 u_box_lo;
uniform vec3 u_box_size;

uniform vec3 u_unbaked_sky;       // where no texel has light: the lattice's environment's
uniform vec3 u_unbaked_ground;    // irradiance for normals facing +z and -z (sun per pixel out)

const vec3 UNBAKED_TINT = vec3(0.8, 0.85, 1.0);

vec3 unbaked_irradiance(vec3 n) {
#if SHADING == 7
    return hemisphere_irradiance(n);  // ambient occlusion scales the local modes' ambient
#else
    return mix(u_unbaked_ground, u_unbaked_sky, 0.5 + 0.5 * n.z);
#endif
}

vec3 lattice_coord(vec3 world) {
    return (world - u_box_lo) / u_box_size;
}

// Baked radiance where the lattice is computed (w: weight of computed texels in the
// lookup); elsewhere Lambert under the hemisphere of the lattice's own environment, with a
// cool tint, shows through: unbaked regions are told apart but lit as brightly.
vec3 lattice_blend(float w, vec3 baked, vec3 n, vec3 albedo) {
#if DIRECT
    // the sun and the lights are added per pixel on top (direct.glsl): no key light here
    vec3 fallback = UNBAKED_TINT * albedo * unbaked_irradiance(n) / PI;
#else
    vec3 fallback = UNBAKED_TINT * albedo * (unbaked_irradiance(n) + 0.5 * u_key_irradiance
                    * max(dot(n, u_key_dir), 0.0)) / PI;
#endif
    return mix(fallback, baked, smoothstep(0.0, 0.25, w));
}

// Continuous texel coordinates of `tc` (texel centres at integers, x y z order) and the
// lower corner of the 2x2x2 texels around it, clamped like GL's CLAMP_TO_EDGE filtering.
vec3 texel_coord(vec3 tc) {
    return tc * u_lattice_size - 0.5;
}

ivec3 cell_base(vec3 c) {
    return clamp(ivec3(floor(c)), ivec3(0), ivec3(u_lattice_size) - 2);
}

// What turns lattice texels of the cell whose lower corner is `base` into atlas texels:
// atlas texel = lattice texel + atlas_shift(base).
ivec3 atlas_shift(ivec3 base) {
    ivec3 brick = base / BRICK;
    return ivec3(texelFetch(u_bricks, brick, 0).xyz) * STORED - brick * BRICK;
}

// The atlas texture coordinate that filters like the lattice coordinate `tc` (clamped to
// the edge texels like CLAMP_TO_EDGE).
vec3 atlas_coord(vec3 tc) {
    vec3 c = clamp(texel_coord(tc), vec3(0.0), u_lattice_size - 1.0);
    return (c + vec3(atlas_shift(cell_base(c))) + 0.5) / u_atlas_size;
}

ivec3 cell_corner(ivec3 base, int k) {  // corner k = x + 2 y + 4 z of the cell
    return base + ivec3(k & 1, (k >> 1) & 1, (k >> 2) & 1);
}

#if SHADING == 5 || SHADING == 7
uniform sampler3D u_irradiance;  // E * valid, GL_RGB9_E5

// (E * w, w) of one atlas texel.
vec4 texel_pair(ivec3 t) {
    return vec4(texelFetch(u_irradiance, t, 0).rgb, texelFetch(u_state, t, 0).r);
}

#if LOOKUP == 0
// Hardware trilinear filtering.
vec4 irradiance_lookup(vec3 tc) {
    vec3 a = atlas_coord(tc);
    return vec4(texture(u_irradiance, a).rgb, texture(u_state, a).r);
}
#elif LOOKUP == 1
// The computed texel, of the 8 around the point, whose centre is nearest (world distance).
vec4 irradiance_lookup(vec3 tc) {
    vec3 c = texel_coord(tc);
    ivec3 base = cell_base(c);
    ivec3 shift = atlas_shift(base);
    vec3 texel_size = u_box_size / u_lattice_size;
    vec4 best = vec4(0.0);
    float best_d2 = 1e30;
    for (int k = 0; k < 8; ++k) {
        ivec3 t = cell_corner(base, k);
        vec4 pair = texel_pair(t + shift);
        vec3 d = (c - vec3(t)) * texel_size;
        if (pair.w > 0.5 && dot(d, d) < best_d2) {
            best = pair;
            best_d2 = dot(d, d);
        }
    }
    return best;
}
#elif LOOKUP == 2
// The computed texel, of the 8 around the point, whose own isovalue rho(x_t) is closest to
// the displayed isovalue (ties: the first in corner order x + 2 y + 4 z).
uniform sampler3D u_texel_iso;  // rho at each texel centre, R32F
uniform float u_iso;            // displayed isovalue

vec4 irradiance_lookup(vec3 tc) {
    ivec3 base = cell_base(texel_coord(tc));
    ivec3 shift = atlas_shift(base);
    vec4 best = vec4(0.0);
    float best_gap = 1e30;
    for (int k = 0; k < 8; ++k) {
        ivec3 t = cell_corner(base, k) + shift;
        vec4 pair = texel_pair(t);
        float gap = abs(texelFetch(u_texel_iso, t, 0).r - u_iso);
        if (pair.w > 0.5 && gap < best_gap) {
            best = pair;
            best_gap = gap;
        }
    }
    return best;
}
#elif LOOKUP == 3
// Uniform cubic B-spline of the texels (approximating, C2), as 8 trilinear fetches
// (Sigg & Hadwiger, GPU Gems 2 ch. 20): along each axis the four weights w0..w3 of
// texels i-1..i+2 pair up into two linear fetches of weight g0 = w0 + w1 at i - 1 +
// w1 / g0 and g1 = w2 + w3 at i + 1 + w3 / g1. Texels past the edge repeat the edge
// texel (GL's CLAMP_TO_EDGE), as in the 64-texel sum with clamped indices.
vec4 irradiance_lookup(vec3 tc) {
    vec3 size = u_lattice_size;
    vec3 c = texel_coord(tc);
    vec3 i = floor(c);
    vec3 a = c - i;
    vec3 w0 = (1.0 - a) * (1.0 - a) * (1.0 - a) / 6.0;
    vec3 w1 = (4.0 - 6.0 * a * a + 3.0 * a * a * a) / 6.0;
    vec3 w3 = a * a * a / 6.0;
    vec3 w2 = 1.0 - w0 - w1 - w3;
    vec3 g[2] = vec3[2](w0 + w1, w2 + w3);
    vec3 h[2] = vec3[2]((i - 1.0 + w1 / g[0] + 0.5) / size, (i + 1.0 + w3 / g[1] + 0.5) / size);
    vec4 sum = vec4(0.0);
    for (int k = 0; k < 8; ++k) {
        ivec3 s = ivec3(k & 1, (k >> 1) & 1, (k >> 2) & 1);
        vec3 p = vec3(h[s.x].x, h[s.y].y, h[s.z].z);
        float weight = g[s.x].x * g[s.y].y * g[s.z].z;
        vec3 a = atlas_coord(p);
        sum += weight * vec4(texture(u_irradiance, a).rgb, texture(u_state, a).r);
    }
    return sum;
}
#endif
#endif

#if SHADING == 6
// SH transfer: E = sum_i tau_i l_i, with tau from SH_TEXTURES RGBA16F textures per colour
// group and the rotated environment coefficients l in u_light (four per vec4, red first).
// A split transfer holds the direct block, then the indirect one: l is then the sun-free
// sky's coefficients followed by the whole sky's (app/lattice_gl.py), the same sum.
SH_DECLARE
uniform vec4 u_light[3 * SH_TEXTURES];

// (E * w, w) of one atlas texel.
vec4 texel_pair(ivec3 t) {
    return vec4(SH_IRRADIANCE_AT(t), texelFetch(u_state, t, 0).r);
}
#endif

#if FACING
// The side weight of atlas texel t at a point of normal n (turned to the eye): its facing
// m is the state's GB, octahedral; (0, 0) unknown.
float side_weight(ivec3 t, vec3 n) {
    vec2 code = texelFetch(u_state, t, 0).gb;
    if (code == vec2(0.0)) return 1.0;
    float c = max(dot(n, from_octahedral(code * 2.0 - 1.0)), 0.0);
#if FACING_POWER == 2
    c *= c;
#elif FACING_POWER != 1
    c = pow(c, float(FACING_POWER));
#endif
    return c;
}

// (value * w, w) of the side-aware trilinear lookup at texture coordinate tc: the 8
// texels' pairs weighted by trilinear weight x side weight, scaled to the plain lookup's
// weight w (so the blend with local shading sees the same coverage), blended into the
// plain lookup where few texels face n's way.
vec4 sided_lookup(vec3 tc, vec3 n) {
    vec3 size = u_lattice_size;
    vec3 c = clamp(tc * size - 0.5, vec3(0.0), size - 1.0);
    ivec3 base = cell_base(c);
    ivec3 shift = atlas_shift(base);
    vec3 f = c - vec3(base);
    vec4 plain = vec4(0.0);
    vec4 sided = vec4(0.0);
    for (int k = 0; k < 8; ++k) {
        ivec3 t = cell_corner(base, k);
        vec3 a = mix(1.0 - f, f, vec3(t - base));
        vec4 pair = (a.x * a.y * a.z) * texel_pair(t + shift);
        plain += pair;
        sided += side_weight(t + shift, n) * pair;
    }
    vec4 side = sided.w > 0.0 ? sided * (plain.w / sided.w) : plain;
    return mix(plain, side, smoothstep(0.0, FACING_BLEND, sided.w / max(plain.w, 1e-30)));
}
#endif

#if SHADING == 5 || SHADING == 7
// E over the computed texels of the lookup at a point of normal n (turned to the eye),
// and their weight w.
vec3 lattice_irradiance(vec3 world, vec3 n, out float w) {
#if FACING && LOOKUP == 0
    vec4 pair = sided_lookup(lattice_coord(world), n);
#else
    vec4 pair = irradiance_lookup(lattice_coord(world));
#endif
    w = pair.w;
    return max(pair.rgb / max(w, 1e-4), 0.0);
}
#endif

#if SHADING == 6
vec3 lattice_radiance(vec3 world, vec3 n, vec3 albedo) {
    vec3 tc = lattice_coord(world);
#if FACING
    vec4 pair = sided_lookup(tc, n);
    float w = pair.w;
    vec3 e = max(pair.rgb / max(w, 1e-4), 0.0);
#else
    vec3 a = atlas_coord(tc);
    float w = texture(u_state, a).r;
    vec3 e = max(SH_IRRADIANCE(a) / max(w, 1e-4), 0.0);
#endif
    return lattice_blend(w, albedo * e / PI, n, albedo);
}
#endif

#if SHADING == 5
vec3 lattice_radiance(vec3 world, vec3 n, vec3 albedo) {
    float w;
    vec3 e = lattice_irradiance(world, n, w);
    return lattice_blend(w, albedo * e / PI, n, albedo);
}
#endif

#if SHADING == 7
// Ambient occlusion: the lattice was baked under a constant sky of radiance u_sky_radiance
// with no bounces, so A = E / (pi L_sky) is the cosine-weighted visible fraction of the
// sky, in [0, 1]. It scales hemisphere-ambient Lambert (no key light, no headlight).
uniform vec3 u_sky_radiance;

vec3 lattice_radiance(vec3 world, vec3 n, vec3 albedo) {
    float w;
    vec3 occlusion = lattice_irradiance(world, n, w) / (PI * u_sky_radiance);
    return lattice_blend(w, albedo * occlusion * hemisphere_irradiance(n) / PI, n, albedo);
}
#endif

