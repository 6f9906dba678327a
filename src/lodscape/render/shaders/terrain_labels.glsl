#ifdef LABELS
uniform float u_class_label[16];
vec4 labelled(vec3 n, vec3 view, float label) {
    n = normalize(n);
    return vec4(dot(n, view) > 0.0 ? -n : n, label);
}
#endif
