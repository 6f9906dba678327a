#version 330
uniform mat3 u_to_world;   // view -> world (ECEF axes)
uniform vec2 u_tan;        // tan of half the horizontal and vertical fields of view
uniform vec2 u_size;       // viewport, pixels
uniform vec3 u_eye;        // the camera in the ellipsoid's scaled space (a unit sphere)
uniform float u_c;         // |u_eye|^2 - 1, from float64 on the CPU
uniform vec3 u_inv_axes;   // 1/a, 1/a, 1/b
uniform vec3 u_sun;        // towards the sun, world
uniform vec3 u_colour;
#ifdef EARTH
uniform sampler2D u_earth; // equirectangular: row 0 at latitude 90, column 0 at longitude -180
uniform vec4 u_data;       // the data's box (west, south, east, north, radians): no data there
#endif
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_dist;
void main() {
    vec2 ndc = gl_FragCoord.xy / u_size * 2.0 - 1.0;
    // a ray whose parameter is the view depth: z = -1 in view space
    vec3 d = u_to_world * vec3(ndc.x * u_tan.x, ndc.y * u_tan.y, -1.0);
    vec3 dp = d * u_inv_axes;
    float a = dot(dp, dp);
    float b = dot(u_eye, dp);
    float disc = b * b - a * u_c;
    if (u_c <= 0.0 || b >= 0.0 || disc < 0.0) discard;
    // the nearer root as c / (-b + sqrt(disc)): no cancellation however near the camera is
    float t = u_c / (-b + sqrt(disc));
    vec3 n = normalize((u_eye + t * dp) * u_inv_axes);
    float light = 0.35 + 0.65 * max(dot(n, u_sun), 0.0);
#ifdef LABELS
    f_color = vec4(n * u_to_world, NO_DATA_LABEL);  // the view-space normal, the no-data label
#elif defined(EARTH)
    // the ellipsoid's normal is the geodetic vertical: its latitude and longitude. atan, not
    // asin(n.z): llvmpipe's asin is a coarse approximation (the image a fraction of a texel
    // row off from 30 to 84 degrees against test_render's float64 reference), its atan is not
    float lat = atan(n.z, length(n.xy));
    float lon = atan(n.y, n.x);
    vec2 uv = vec2(lon / 6.28318531 + 0.5, 0.5 - lat / 3.14159265);
    // no mip across the antimeridian's seam: the level of the texels a pixel spans here
    vec3 earth = textureGrad(u_earth, uv, dFdx(uv) - floor(dFdx(uv) + 0.5),
                             dFdy(uv) - floor(dFdy(uv) + 0.5)).rgb;
    // inside the data's box what shows through is its holes and collars: no data, grey
    bool inside = lon >= u_data.x && lon <= u_data.z && lat >= u_data.y && lat <= u_data.w;
    f_color = vec4((inside ? u_colour : earth) * light, 1.0);
#else
    f_color = vec4(u_colour * light, 1.0);
#endif
    f_dist = t;
}
