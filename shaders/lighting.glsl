// Local lighting models. Units: irradiance E at normal incidence (linear RGB); a diffuse
// surface of albedo a returns radiance a * E / pi.
const float PI = 3.14159265358979;

uniform vec3 u_key_dir;        // unit vector towards the key light (world)
uniform vec3 u_key_irradiance; // key light irradiance at normal incidence
uniform vec3 u_head_irradiance;// headlight (from the eye) irradiance
uniform vec3 u_sky_irradiance; // hemisphere ambient: irradiance of a normal facing +z ...
uniform vec3 u_ground_irradiance; // ... and facing -z
uniform float u_shininess;
uniform float u_specular;      // specular albedo

vec3 lambert_irradiance(vec3 n, vec3 v) {
    return u_key_irradiance * max(dot(n, u_key_dir), 0.0)
         + u_head_irradiance * max(dot(n, v), 0.0);
}

vec3 hemisphere_irradiance(vec3 n) {
    return mix(u_ground_irradiance, u_sky_irradiance, 0.5 + 0.5 * n.z);
}

// Energy-normalised Blinn-Phong lobe for the key light and the headlight.
vec3 phong_radiance(vec3 n, vec3 v) {
    vec3 h = normalize(u_key_dir + v);
    float norm = (u_shininess + 8.0) / (8.0 * PI);
    float key = pow(max(dot(n, h), 0.0), u_shininess) * max(dot(n, u_key_dir), 0.0);
    float head = pow(max(dot(n, v), 0.0), u_shininess) * max(dot(n, v), 0.0);
    return u_specular * norm * (u_key_irradiance * key + u_head_irradiance * head);
}
