// Local lighting models. Units: irradiance E at normal incidence (linear RGB); a diffuse
// surface of albedo a returns radiance a * E / pi. `key_visibility` in [0, 1] scales the
// key light (1: unshadowed, 0: in its shadow); the headlight is never shadowed.
const float PI = 3.14159265358979;

uniform vec3 u_key_dir;        // unit vector towards the key light (world)
uniform vec3 u_key_irradiance; // key light irradiance at normal incidence
uniform vec3 u_head_irradiance;// headlight (from the eye) irradiance
uniform vec3 u_sky_irradiance; // hemisphere ambient: irradiance of a normal facing +z ...
uniform vec3 u_ground_irradiance; // ... and facing -z
uniform float u_shininess;
uniform float u_specular;      // specular albedo

vec3 lambert_irradiance(vec3 n, vec3 v, float key_visibility) {
    return u_key_irradiance * (key_visibility * max(dot(n, u_key_dir), 0.0))
         + u_head_irradiance * max(dot(n, v), 0.0);
}

vec3 hemisphere_irradiance(vec3 n) {
    return mix(u_ground_irradiance, u_sky_irradiance, 0.5 + 0.5 * n.z);
}

// Energy-normalised Blinn-Phong lobe for the key light and the headlight.
vec3 phong_radiance(vec3 n, vec3 v, float key_visibility) {
    vec3 h = normalize(u_key_dir + v);
    float norm = (u_shininess + 8.0) / (8.0 * PI);
    float key = pow(max(dot(n, h), 0.0), u_shininess) * max(dot(n, u_key_dir), 0.0);
    float head = pow(max(dot(n, v), 0.0), u_shininess) * max(dot(n, v), 0.0);
    return u_specular * norm * (u_key_irradiance * (key_visibility * key)
                                + u_head_irradiance * head);
}

// OpenGL-style exponential fog: the fraction of surface radiance that reaches the eye
// through `distance` world units of fog, counted from the near side of the scene.
uniform float u_fog_density;   // per world unit
uniform float u_fog_start;     // world distance from the eye where the fog begins

float fog_transmittance(float distance) {
    return exp(-u_fog_density * max(distance - u_fog_start, 0.0));
}
