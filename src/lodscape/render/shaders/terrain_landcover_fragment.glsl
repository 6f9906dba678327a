#version 330
uniform sampler2D u_tex;          // the tile's class mask, one byte a texel (255: no data)
uniform sampler2DArray u_ground_materials;
uniform vec3 u_sun;               // towards the sun, view space
uniform vec4 u_tint;              // the viewer's LOD colouring
in vec2 v_uv;
in float v_dist;
in vec2 v_ground;                 // metres east and north (modulo a whole number of repeats)
in vec3 v_view;
#ifdef HEIGHT_NORMALS
in vec3 v_normal;                 // view space, from the height texture
#endif
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_dist;
UNDERSIDE_GLSL
int cls(ivec2 t, ivec2 size) {
    return int(texelFetch(u_tex, clamp(t, ivec2(0), size - 1), 0).r * 255.0 + 0.5);
}
void main() {
    ivec2 size = textureSize(u_tex, 0);
    int here = cls(ivec2(floor(v_uv * vec2(size))), size);
    if (here == 255) discard;
#ifdef LABELS
    if (drawn_apart(u_class_label[here])) return;
#else
    if (drawn_apart(0.0)) return;
#endif
    // near ground repeats every 8 m, far ground every 64 m: sharp close up, no shimmer afar
    float far = smoothstep(200.0, 1500.0, v_dist);
    vec2 st = v_uv * vec2(size) - 0.5;
    ivec2 i0 = ivec2(floor(st));
    vec2 f = st - vec2(i0);
    vec3 acc = vec3(0.0);
    float total = 0.0;
    for (int k = 0; k < 4; ++k) {
        ivec2 o = ivec2(k & 1, k >> 1);
        int c = cls(i0 + o, size);
        if (c == 255) continue;
        float w = (o.x == 1 ? f.x : 1.0 - f.x) * (o.y == 1 ? f.y : 1.0 - f.y);
        vec3 near = texture(u_ground_materials, vec3(v_ground / 8.0, float(c))).rgb;
        vec3 wide = texture(u_ground_materials, vec3(v_ground / 64.0, float(c))).rgb;
        acc += w * mix(near, wide, far);
        total += w;
    }
    vec3 albedo = acc / max(total, 1e-6);
#ifdef HEIGHT_NORMALS
    vec3 n = normalize(v_normal);
#else
    vec3 n = normalize(cross(dFdx(v_view), dFdy(v_view)));
#endif
    if (dot(n, v_view) > 0.0) n = -n;
    float light = 0.35 + 0.65 * max(dot(n, u_sun), 0.0);
    f_color = vec4(mix(albedo * light, u_tint.rgb, u_tint.a), 1.0);
    f_dist = v_dist;
}
