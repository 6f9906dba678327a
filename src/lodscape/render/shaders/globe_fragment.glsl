#version 330
uniform sampler2D u_tex;
uniform sampler2D u_region;  // the terrain's own imagery over its box (alpha 0: no data)
uniform vec4 u_box;          // the box in u_tex's coordinates: u0, v0, u1, v1
uniform bool u_has_region;
uniform bool u_behind_region;  // the terrain's own tiles draw the region: only fill there
in vec2 v_uv;
in float v_dist;
in float v_shade;
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_dist;
LOG_DEPTH_GLSL
void main() {
    vec3 rgb = min(texture(u_tex, v_uv).rgb * v_shade, vec3(1.0));
    float covered = 0.0;
    if (u_has_region) {
        // a facet's own longitudes may run past ±180: try the box a turn either way too
        for (int k = -1; k <= 1; k++) {
            vec2 uv = (v_uv + vec2(float(k), 0.0) - u_box.xy) / (u_box.zw - u_box.xy);
            if (all(greaterThanEqual(uv, vec2(0.0))) && all(lessThanEqual(uv, vec2(1.0)))) {
                vec4 r = texture(u_region, uv);
                rgb = mix(rgb, r.rgb, r.a);  // its tint carries its own hillshade
                covered = max(covered, r.a);
            }
        }
    }
    f_color = vec4(rgb, 0.0);  // alpha 0: the globe's pixel (the terrain scene's are 1)
    f_dist = v_dist;
    // over the data the terrain's tiles win wherever they draw (the globe fills their holes),
    // a surface below the ellipsoid included; elsewhere the nearer wins, the terrain where
    // the two meet within a hair (its skirts and edges lie on the same ellipsoid)
    bool behind = u_behind_region && covered > 0.5;
    gl_FragDepth = behind ? behind_depth(v_dist) : log_depth(v_dist * 1.001 + 1.0);
}
