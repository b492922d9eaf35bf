#version 330 core
// Linear HDR radiance -> display: exposure, tone curve, sRGB encoding.
// TONEMAP: 0 clamp (linear, for predicted-pixel tests), 1 Reinhard, 2 ACES (Narkowicz fit).
uniform sampler2D u_hdr;
uniform float u_exposure;   // multiplier (2^EV)
uniform vec3 u_background;  // linear RGB where nothing was drawn (alpha = 0)

in vec2 v_uv;
out vec4 frag_color;

vec3 tone(vec3 x) {
#if TONEMAP == 1
    return x / (1.0 + x);
#elif TONEMAP == 2
    return clamp((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0);
#else
    return clamp(x, 0.0, 1.0);
#endif
}

vec3 srgb_encode(vec3 c) {
    vec3 lo = 12.92 * c;
    vec3 hi = 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055;
    return mix(lo, hi, step(vec3(0.0031308), c));
}

void main() {
    vec4 hdr = texelFetch(u_hdr, ivec2(gl_FragCoord.xy), 0);
    vec3 linear = hdr.a > 0.0 ? hdr.rgb * u_exposure : u_background;
    frag_color = vec4(srgb_encode(tone(linear)), 1.0);
}
