// Exact direct light, per pixel: the point and directional lights and the sky's sun of a
// lattice baked with direct_light "pixels" (the lattice holds everything else). Shadows
// come from one depth atlas of tiles: one orthographic tile per directional light or sun,
// six 90-degree tiles per point light (+x -x +y -y +z -z). Every tile stores *linear*
// depth in [0, 1] (u_tile_depth: depth = dot(xyz, world) + w; range in world units), so
// biases and penumbra widths are distances, not perspective-warped depths.
//
// Soft sun shadows (angular radius r): percentage-closer soft shadows. A blocker search
// over the disc the sun's cone covers at the light's near plane finds the mean blocker
// depth; a receiver at distance d below it sees the sun disc cover a disc of radius
// d tan r in the map, and the fraction of that disc's depth comparisons that pass is the
// fraction of the sun disc in view (exact for an occluder at one depth). Each comparison
// is made against the receiver's own plane at that tap (receiver-plane depth bias), so
// a wide filter neither shadows the surface it lies on (acne) nor needs a large constant
// bias that would detach shadows from their casters (peter-panning).
#define MAX_DIRECT 8
#define MAX_TILES 16
#define SEARCH_TAPS 8
#define FILTER_TAPS 16
#define HARD_TAPS 4

uniform int u_direct_count;
uniform vec4 u_direct_where[MAX_DIRECT];  // w = 0: unit vector towards a distant light;
                                          // w = 1: a point light's position
uniform vec3 u_direct_rgb[MAX_DIRECT];    // irradiance at normal incidence, or intensity
uniform float u_direct_tan_radius[MAX_DIRECT];  // tan(angular radius); 0: a hard light
uniform int u_direct_tile[MAX_DIRECT];    // its (first) atlas tile
uniform mat4 u_tile_view_proj[MAX_TILES]; // world -> the tile's clip space
uniform vec4 u_tile_depth[MAX_TILES];     // linear depth = dot(xyz, world) + w
uniform vec4 u_tile_rect[MAX_TILES];      // atlas uv of the tile: offset xy, size zw
uniform float u_tile_range[MAX_TILES];    // world units per unit of depth
uniform vec2 u_direct_bias;               // (constant, slope) bias, in tile texels
uniform float u_direct_offset;            // world distance the shaded point is lifted along
                                          // its normal (the baker's start-point offset)
uniform sampler2DShadow u_direct_shadow;  // the atlas, compare <=, bilinear
uniform sampler2D u_direct_depth;         // the same atlas, raw depths (blocker search)

const float DIRECT_MAX_SLOPE = 10.0;
const float GOLDEN_ANGLE = 2.39996323;

// Tap k of n on the unit disc, uniform by area (Vogel's spiral), turned by `spin`.
vec2 vogel_tap(int k, int n, float spin) {
    float radius = sqrt((float(k) + 0.5) / float(n));
    float angle = float(k) * GOLDEN_ANGLE + spin;
    return radius * vec2(cos(angle), sin(angle));
}

// Per-pixel turn of the tap pattern (interleaved gradient noise): banding becomes fine
// noise that the eye and the tone curve forgive.
float tap_spin() {
    return 6.28318531 * fract(52.9829189 * fract(dot(gl_FragCoord.xy,
                                                     vec2(0.06711056, 0.00583715))));
}

// Atlas uv of tile-local uv, kept half a texel inside the tile (no bleeding).
vec2 atlas_uv(int tile, vec2 uv) {
    vec2 half_texel = 0.5 / (u_tile_rect[tile].zw * vec2(textureSize(u_direct_depth, 0)));
    return u_tile_rect[tile].xy + u_tile_rect[tile].zw * clamp(uv, half_texel,
                                                               1.0 - half_texel);
}

// Visibility of a distant light (tile `tile`, unit vector `l` towards it, tan(angular
// radius) `tan_r`) at `world` with facet normal `facet`.
float distant_visibility(int tile, vec3 l, float tan_r, vec3 world, vec3 facet) {
    vec3 p = (u_tile_view_proj[tile] * vec4(world, 1.0)).xyz * 0.5 + 0.5;
    if (any(lessThan(p.xy, vec2(0.0))) || any(greaterThan(p.xy, vec2(1.0)))) return 1.0;
    // an orthographic tile spans as many world units across (uv 0 to 1) as in depth
    // (0 to 1): offsets in uv and depths share one unit, u_tile_range world units
    float depth = dot(u_tile_depth[tile].xyz, world) + u_tile_depth[tile].w;
    float texel = 1.0 / (u_tile_rect[tile].z * float(textureSize(u_direct_depth, 0).x));
    // receiver plane: how its depth (away from the light) grows per uv step across
    vec3 right = normalize(vec3(u_tile_view_proj[tile][0][0], u_tile_view_proj[tile][1][0],
                                u_tile_view_proj[tile][2][0]));
    vec3 up = normalize(vec3(u_tile_view_proj[tile][0][1], u_tile_view_proj[tile][1][1],
                             u_tile_view_proj[tile][2][1]));
    float towards = dot(facet, l);
    float c = sign(towards) * max(abs(towards), 1e-4);
    vec2 plane = clamp(vec2(dot(facet, right), dot(facet, up)) / c,
                       -DIRECT_MAX_SLOPE, DIRECT_MAX_SLOPE);
    float bias = (u_direct_bias.x + u_direct_bias.y * length(plane)) * texel;
    float spin = tap_spin();
    float filter_uv = texel;  // a hard light: one texel around the point
    if (tan_r > 0.0) {
        // blocker search over the widest disc the sun can need: its cone from the receiver
        // up to the tile's near plane
        float search = max(depth * tan_r, texel);
        float blockers = 0.0;
        float blocker_depth = 0.0;
        for (int k = 0; k < SEARCH_TAPS; ++k) {
            vec2 o = search * vogel_tap(k, SEARCH_TAPS, spin);
            float stored = texture(u_direct_depth, atlas_uv(tile, p.xy + o)).r;
            if (stored < depth + dot(plane, o) - bias) {
                blockers += 1.0;
                blocker_depth += stored;
            }
        }
        if (blockers == 0.0) return 1.0;  // nothing can shade it
        if (blockers == float(SEARCH_TAPS)) return 0.0;  // the wider disc is all blocked
        // the sun disc seen from the receiver covers a disc of radius gap * tan r at the
        // blockers' mean depth
        filter_uv = max((depth - blocker_depth / blockers) * tan_r, texel);
    }
    int taps = tan_r > 0.0 ? FILTER_TAPS : HARD_TAPS;
    float lit = 0.0;
    for (int k = 0; k < taps; ++k) {
        vec2 o = filter_uv * vogel_tap(k, taps, spin);
        float receiver = depth + dot(plane, o) - bias;
        lit += texture(u_direct_shadow, vec3(atlas_uv(tile, p.xy + o), receiver));
    }
    return lit / float(taps);
}

// Visibility of a point light at `light` (first tile `first`) from `world` (facet normal).
float point_visibility(int first, vec3 light, vec3 world, vec3 facet) {
    vec3 d = world - light;
    vec3 a = abs(d);
    int face = a.x >= a.y && a.x >= a.z ? (d.x >= 0.0 ? 0 : 1)
             : a.y >= a.z ? (d.y >= 0.0 ? 2 : 3) : (d.z >= 0.0 ? 4 : 5);
    int tile = first + face;
    vec4 clip = u_tile_view_proj[tile] * vec4(world, 1.0);
    vec2 uv = clip.xy / clip.w * 0.5 + 0.5;
    float range = u_tile_range[tile];
    float depth = dot(u_tile_depth[tile].xyz, world) + u_tile_depth[tile].w;
    float distance = depth * range;  // along the face's axis
    vec2 map_texels = u_tile_rect[tile].zw * vec2(textureSize(u_direct_depth, 0));
    float texel_world = 2.0 * distance / map_texels.x;  // a 90-degree face
    vec3 l = normalize(-d);
    float c = max(abs(dot(facet, l)), 1e-4);
    float tilt = min(sqrt(max(1.0 - c * c, 0.0)) / c, DIRECT_MAX_SLOPE);
    float reference = depth - (u_direct_bias.x + 1.5 * u_direct_bias.y * tilt) * texel_world
                      / range;
    vec2 texel = 1.0 / map_texels;
    float lit = 0.0;
    for (int j = -1; j <= 1; ++j) {
        for (int i = -1; i <= 1; ++i) {
            lit += texture(u_direct_shadow, vec3(atlas_uv(tile, uv + vec2(i, j) * texel),
                                                 reference));
        }
    }
    return lit / 9.0;
}

// Irradiance at `world` (shading normal n, facet normal `facet`, both turned to the eye)
// from the per-pixel lights, shadowed.
vec3 direct_irradiance(vec3 world, vec3 n, vec3 facet) {
    vec3 e = vec3(0.0);
    for (int i = 0; i < u_direct_count; ++i) {
        vec4 where = u_direct_where[i];
        vec3 l = where.w > 0.5 ? where.xyz - world : where.xyz;
        float r2 = max(dot(l, l), 1e-20);
        l *= inversesqrt(r2);
        float cosine = dot(n, l);
        if (cosine <= 0.0) continue;
        float falloff = where.w > 0.5 ? 1.0 / r2 : 1.0;
        float visible = where.w > 0.5
            ? point_visibility(u_direct_tile[i], where.xyz, world, facet)
            : distant_visibility(u_direct_tile[i], where.xyz, u_direct_tan_radius[i], world,
                                 facet);
        e += u_direct_rgb[i] * (cosine * falloff * visible);
    }
    return e;
}
