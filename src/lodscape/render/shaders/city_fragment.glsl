#version 330
uniform sampler2DArray u_materials;
uniform float u_layer;   // the material's layer
uniform vec2 u_repeat;   // metres one repeat of its texture covers
#ifdef BLOCKS
layout(std140) uniform Frame { mat4 f_mvp; mat4 f_rot; vec4 f_offset; vec4 f_sun; };
#define SUN f_sun.xyz
#else
uniform vec3 u_sun;
#define SUN u_sun
#endif
#ifdef LABELS
uniform float u_label;   // a dataset's pass: the view-space normal and the object's label
#endif
in vec3 v_normal;
in vec2 v_uv;
in float v_dist;
in vec3 v_view;
in vec3 v_view_normal;
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_dist;
void main() {
#ifdef LABELS
    vec3 m = normalize(v_view_normal);
    f_color = vec4(dot(m, v_view) > 0.0 ? -m : m, u_label);
    f_dist = v_dist;
    return;
#endif
    vec3 n = normalize(v_normal);
    float light = 0.45 + 0.55 * max(dot(n, SUN), 0.0) + 0.1 * n.z;
    vec3 albedo = texture(u_materials, vec3(v_uv / u_repeat, u_layer)).rgb;
    f_color = vec4(albedo * light, 1.0);
    f_dist = v_dist;
}
