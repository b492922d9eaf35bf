// Hard shadows of the key light by shadow mapping. The map holds the depth of the
// surfaces nearest the (directional) key light in an orthographic view fitted to the
// scene's bounding sphere; u_light_view_proj maps world -> that view's clip space.
uniform sampler2DShadow u_shadow_map;  // depth, compare mode <=, bilinear comparison
uniform mat4 u_light_view_proj;
uniform vec2 u_shadow_bias;  // depth-units bias: constant + slope * tan(angle to light)

const float MAX_SLOPE = 10.0;  // tan(84 deg): beyond it the key term is < 0.1 anyway

// Fraction of the key light reaching `world` (normal n): 3x3 taps one texel apart, each a
// bilinear 2x2 depth comparison (percentage-closer filtering over a 4x4-texel footprint).
// The receiver's depth is pulled towards the light by a slope-scaled bias that covers the
// depth change across that footprint, so lit surfaces do not shadow themselves (acne).
float key_visibility(vec3 world, vec3 n) {
    vec3 p = (u_light_view_proj * vec4(world, 1.0)).xyz * 0.5 + 0.5;
    if (any(lessThan(p, vec3(0.0))) || any(greaterThan(p, vec3(1.0)))) return 1.0;
    float c = abs(dot(n, u_key_dir));
    float slope = min(sqrt(max(1.0 - c * c, 0.0)) / max(c, 1e-4), MAX_SLOPE);
    float reference = p.z - (u_shadow_bias.x + u_shadow_bias.y * slope);
    vec2 texel = 1.0 / vec2(textureSize(u_shadow_map, 0));
    float lit = 0.0;
    for (int j = -1; j <= 1; ++j) {
        for (int i = -1; i <= 1; ++i) {
            lit += texture(u_shadow_map, vec3(p.xy + vec2(i, j) * texel, reference));
        }
    }
    return lit / 9.0;
}
