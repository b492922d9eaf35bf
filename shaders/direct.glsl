// Exact direct light, per pixel: the point and directional lights and the sky's sun of a
// lattice baked with direct_light "pixels" (the lattice holds everything else). Shadows
// come from one depth atlas of tiles: one orthographic tile per directional light or sun,
// six 90-degree tiles per point light (+x -x +y -y +z -z). Every tile stores *linear*
// depth in [0, 1] (u_tile_depth: depth = dot(xyz, world) + w; u_tile_range world units
// per unit), so biases and penumbra widths are distances, not perspective-warped depths.
//
// Soft sun shadows (angular radius r): percentage-closer soft shadows. A blocker search
// over the disc the sun's cone covers at the light's near plane finds the mean blocker
// depth; a receiver at distance d below it sees the sun disc cover a disc of radius
// d tan r in the map, and the fraction of that disc's depth comparisons that pass is the
// fraction of the sun disc in view (exact for an occluder at one depth). Each comparison
// is made against the receiver's own plane at that tap (receiver-plane depth bias), so
// a wide filter neither shadows the surface it lies on (acne) nor needs a large constant
// bias that would detach shadows from their casters (peter-panning).
//
// The renderer specialises this file to its lights: DIRECT_SUM(p, n, f) is defined as the
// sum of one call per light with constant light and tile indices (distant_soft,
// distant_hard, point_light), so every uniform array is indexed by constants and nothing
// loops over lights at run time (llvmpipe runs such code twice as fast). llvmpipe runs
// both sides of every branch, so a pixel costs all the texture reads in the code: a hard
// light reads one, a sun 8 + 16. It runs in a full-screen pass (deferred.frag), once
// per pixel.
//
// With TRACED, each light's share at each pixel comes from rays instead (baking.shadow_rays:
// the reference's own estimate, for off-screen pictures): u_traced holds, per pixel and
// light, the cosine-weighted fraction of the light seen from the pixel's start point, with
// the exact smoothed-gradient normal there, and no atlas is read.
#ifndef TRACED
#define TRACED 0
#endif
#define MAX_DIRECT 8
#define MAX_TILES 16
#ifndef SEARCH_TAPS
#define SEARCH_TAPS 8
#define SEARCH_PATTERN TAPS_8
#endif
#ifndef FILTER_TAPS
#define FILTER_TAPS 16
#define FILTER_PATTERN TAPS_16
#endif
#ifndef HARD_TAPS
#define HARD_TAPS 1  // a hard light: the hardware's bilinear comparison at the point
#define HARD_PATTERN TAPS_1
#endif

uniform vec4 u_direct_where[MAX_DIRECT];  // w = 0: unit vector towards a distant light;
                                          // w = 1: a point light's position
uniform vec3 u_direct_rgb[MAX_DIRECT];    // irradiance at normal incidence, or intensity
uniform float u_direct_tan_radius[MAX_DIRECT];  // tan(angular radius) of a sun
uniform mat4 u_tile_view_proj[MAX_TILES]; // world -> the tile's clip space
uniform vec4 u_tile_depth[MAX_TILES];     // linear depth = dot(xyz, world) + w
uniform vec4 u_tile_rect[MAX_TILES];      // atlas uv of the tile: offset xy, size zw
uniform float u_tile_range[MAX_TILES];    // world units per unit of depth
uniform vec3 u_tile_right[MAX_TILES];     // distant tiles: unit vectors along their u ...
uniform vec3 u_tile_up[MAX_TILES];        // ... and v axes
uniform float u_tile_texel[MAX_TILES];    // one texel in tile uv
uniform vec2 u_direct_bias;               // (constant, slope) bias, in tile texels
uniform float u_direct_offset;            // world distance the shaded point is lifted along
                                          // its normal (the baker's start-point offset)
uniform sampler2DShadow u_direct_shadow;  // the atlas, compare <=, bilinear
uniform sampler2D u_direct_depth;         // the same atlas, raw depths (blocker search)

const float DIRECT_MAX_SLOPE = 10.0;
// Taps on the unit disc, uniform by area (Vogel's spiral: radius sqrt((k + 0.5) / n),
// angle k times the golden angle), turned per pixel by `tap_turn`.
const vec2 TAPS_1[1] = vec2[1](vec2(0.0));
const vec2 TAPS_4[4] = vec2[4](vec2(0.353553, 0.000000), vec2(-0.451544, 0.413652),
    vec2(0.069116, -0.787542), vec2(0.569142, 0.742346));
const vec2 TAPS_8[8] = vec2[8](vec2(0.250000, 0.000000), vec2(-0.319290, 0.292496),
    vec2(0.048872, -0.556877), vec2(0.402444, 0.524918), vec2(-0.738535, -0.130636),
    vec2(0.699605, -0.445031), vec2(-0.234004, 0.870484), vec2(-0.446271, -0.859268));
const vec2 TAPS_16[16] = vec2[16](vec2(0.176777, 0.000000), vec2(-0.225772, 0.206826),
    vec2(0.034558, -0.393771), vec2(0.284571, 0.371173), vec2(-0.522223, -0.092374),
    vec2(0.494695, -0.314685), vec2(-0.165466, 0.615525), vec2(-0.315561, -0.607594),
    vec2(0.684642, 0.250030), vec2(-0.712256, 0.294009), vec2(0.343355, -0.733729),
    vec2(0.253730, 0.808932), vec2(-0.764746, -0.443186), vec2(0.897134, -0.197232),
    vec2(-0.547507, 0.778772), vec2(-0.126487, -0.976090));

// Per-pixel turn of the tap pattern (interleaved gradient noise), as a 2x2 rotation:
// banding becomes fine noise that the eye and the tone curve forgive.
mat2 tap_turn() {
    float a = 6.28318531 * fract(52.9829189 * fract(dot(gl_FragCoord.xy,
                                                        vec2(0.06711056, 0.00583715))));
    float c = cos(a), s = sin(a);
    return mat2(c, s, -s, c);
}

// Atlas uv of tile-local uv, kept half a texel inside the tile (no bleeding).
vec2 atlas_uv(int tile, vec2 uv) {
    float half_texel = 0.5 * u_tile_texel[tile];
    return u_tile_rect[tile].xy + u_tile_rect[tile].zw * clamp(uv, half_texel,
                                                               1.0 - half_texel);
}

// A distant light's tile: the point's uv and linear depth, the receiver plane's depth
// change per uv step, and the depth bias (an orthographic tile spans as many world units
// across, uv 0 to 1, as in depth, 0 to 1: offsets and depths share one unit).
struct Receiver {
    vec2 uv;
    float depth;
    vec2 plane;
    float bias;
};

Receiver distant_receiver(int tile, vec3 l, vec3 world, vec3 facet) {
    Receiver r;
    r.uv = (u_tile_view_proj[tile] * vec4(world, 1.0)).xy * 0.5 + 0.5;
    r.depth = dot(u_tile_depth[tile].xyz, world) + u_tile_depth[tile].w;
    float towards = dot(facet, l);
    float c = sign(towards) * max(abs(towards), 1e-4);
    r.plane = clamp(vec2(dot(facet, u_tile_right[tile]), dot(facet, u_tile_up[tile])) / c,
                    -DIRECT_MAX_SLOPE, DIRECT_MAX_SLOPE);
    r.bias = (u_direct_bias.x + u_direct_bias.y * length(r.plane)) * u_tile_texel[tile];
    return r;
}

// Fraction of `taps` comparisons (offsets TAPS_n * radius, turned) that see the light.
float filtered(int tile, Receiver r, float radius, mat2 turn, int taps) {
    float lit = 0.0;
    if (taps == HARD_TAPS) {
        for (int k = 0; k < HARD_TAPS; ++k) {
            vec2 o = radius * (turn * HARD_PATTERN[k]);
            lit += texture(u_direct_shadow, vec3(atlas_uv(tile, r.uv + o),
                                                 r.depth + dot(r.plane, o) - r.bias));
        }
        return lit / float(HARD_TAPS);
    }
    for (int k = 0; k < FILTER_TAPS; ++k) {
        vec2 o = radius * (turn * FILTER_PATTERN[k]);
        lit += texture(u_direct_shadow, vec3(atlas_uv(tile, r.uv + o),
                                             r.depth + dot(r.plane, o) - r.bias));
    }
    return lit / float(FILTER_TAPS);
}

// Whether a receiver falls outside its tile (the map covers every blocker in the scene).
bool off_tile(Receiver r) {
    return any(lessThan(r.uv, vec2(0.0))) || any(greaterThan(r.uv, vec2(1.0)));
}

// Where distant light i meets the receiver at `world` (normal n, facet normal `facet`):
// its cosine (0 facing away) and the receiver in tile `tile`. False when no shadow lookup
// is needed: facing away, or outside the map (nothing there shades it).
bool distant_receiver_in(int i, int tile, vec3 world, vec3 n, vec3 facet, out float cosine,
                         out Receiver r) {
    vec3 l = u_direct_where[i].xyz;
    cosine = max(dot(n, l), 0.0);
    if (cosine == 0.0) return false;
    r = distant_receiver(tile, l, world, facet);
    return !off_tile(r);
}

#if TRACED
uniform sampler2DArray u_traced;  // layer i: light i's traced factor, per pixel

float traced_factor(int i) {
    return texelFetch(u_traced, ivec3(ivec2(gl_FragCoord.xy), i), 0).r;
}

// Irradiance of distant light i: its irradiance at normal incidence times the traced
// factor (the cosine where seen; a sun's cosine-weighted share of its disc).
vec3 distant_hard(int i, int tile, vec3 world, vec3 n, vec3 facet) {
    return u_direct_rgb[i] * traced_factor(i);
}

vec3 distant_soft(int i, int tile, vec3 world, vec3 n, vec3 facet) {
    return distant_hard(i, tile, world, n, facet);
}

// Irradiance of point light i at `world`: its intensity / r² times the traced factor.
vec3 point_light(int i, int first, vec3 world, vec3 n, vec3 facet) {
    vec3 to_light = u_direct_where[i].xyz - world;
    return u_direct_rgb[i] * (traced_factor(i) / max(dot(to_light, to_light), 1e-20));
}
#else
// Irradiance of distant light i (tile `tile`) at `world` (normal n, facet normal `facet`).
vec3 distant_hard(int i, int tile, vec3 world, vec3 n, vec3 facet) {
    float cosine;
    Receiver r;
    if (!distant_receiver_in(i, tile, world, n, facet, cosine, r)) return u_direct_rgb[i] * cosine;
    return u_direct_rgb[i] * (cosine * filtered(tile, r, u_tile_texel[tile], tap_turn(),
                                                HARD_TAPS));
}

vec3 distant_soft(int i, int tile, vec3 world, vec3 n, vec3 facet) {
    float cosine;
    Receiver r;
    if (!distant_receiver_in(i, tile, world, n, facet, cosine, r)) return u_direct_rgb[i] * cosine;
    float tan_r = u_direct_tan_radius[i];
    float texel = u_tile_texel[tile];
    mat2 turn = tap_turn();
    // blocker search over the widest disc the sun can need: its cone from the receiver up
    // to the tile's near plane
    float search = max(r.depth * tan_r, texel);
    float blockers = 0.0;
    float blocker_depth = 0.0;
    for (int k = 0; k < SEARCH_TAPS; ++k) {
        vec2 o = search * (turn * SEARCH_PATTERN[k]);
        float stored = texture(u_direct_depth, atlas_uv(tile, r.uv + o)).r;
        float hit = float(stored < r.depth + dot(r.plane, o) - r.bias);
        blockers += hit;
        blocker_depth += hit * stored;
    }
    if (blockers == 0.0) return u_direct_rgb[i] * cosine;  // nothing can shade it
    if (blockers == float(SEARCH_TAPS)) return vec3(0.0);  // the wider disc is all blocked
    // the sun disc seen from the receiver covers a disc of radius gap * tan r at the
    // blockers' mean depth
    float radius = max((r.depth - blocker_depth / blockers) * tan_r, texel);
    return u_direct_rgb[i] * (cosine * filtered(tile, r, radius, turn, FILTER_TAPS));
}

// Irradiance of point light i (first tile `first`) at `world`.
vec3 point_light(int i, int first, vec3 world, vec3 n, vec3 facet) {
    vec3 light = u_direct_where[i].xyz;
    vec3 to_light = light - world;
    float r2 = max(dot(to_light, to_light), 1e-20);
    vec3 l = to_light * inversesqrt(r2);
    float cosine = dot(n, l);
    if (cosine <= 0.0) return vec3(0.0);
    vec3 d = -to_light;
    vec3 a = abs(d);
    int face = a.x >= a.y && a.x >= a.z ? (d.x >= 0.0 ? 0 : 1)
             : a.y >= a.z ? (d.y >= 0.0 ? 2 : 3) : (d.z >= 0.0 ? 4 : 5);
    int tile = first + face;
    vec4 clip = u_tile_view_proj[tile] * vec4(world, 1.0);
    vec2 uv = clip.xy / clip.w * 0.5 + 0.5;
    float range = u_tile_range[tile];
    float depth = dot(u_tile_depth[tile].xyz, world) + u_tile_depth[tile].w;
    float texel_world = 2.0 * depth * range * u_tile_texel[tile];  // a 90-degree face
    float c = max(abs(dot(facet, l)), 1e-4);
    float tilt = min(sqrt(max(1.0 - c * c, 0.0)) / c, DIRECT_MAX_SLOPE);
    float reference = depth - (u_direct_bias.x + 1.5 * u_direct_bias.y * tilt) * texel_world
                      / range;
    float texel = u_tile_texel[tile];
    float lit = 0.0;
    for (int j = -1; j <= 1; ++j) {
        for (int k = -1; k <= 1; ++k) {
            lit += texture(u_direct_shadow, vec3(atlas_uv(tile, uv + vec2(k, j) * texel),
                                                 reference));
        }
    }
    return u_direct_rgb[i] * (cosine / r2 * lit / 9.0);
}

#endif

// Irradiance at `world` (shading normal n, facet normal `facet`, both turned to the eye)
// from the per-pixel lights, shadowed.
vec3 direct_irradiance(vec3 world, vec3 n, vec3 facet) {
    return DIRECT_SUM(world, n, facet);
}
