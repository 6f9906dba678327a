#ifdef LABELS
uniform float u_class_label[16];
vec4 labelled(vec3 n, vec3 view, float label) {
    n = normalize(n);
    return vec4(dot(n, view) > 0.0 ? -n : n, label);
}
#endif
// the label pass's pixel (the view-space normal and ``label``), or the terrain's underside
// seen from below: true when the fragment is done with
bool drawn_apart(float label) {
#ifdef LABELS
#ifdef HEIGHT_NORMALS
    f_color = labelled(v_normal, v_view, label);
#else
    f_color = labelled(cross(dFdx(v_view), dFdy(v_view)), v_view, label);
#endif
    f_dist = v_dist;
    return true;
#else
    if (underside(v_view)) {
        f_color = vec4(mix(UNDERSIDE, u_tint.rgb, u_tint.a), 1.0);
        f_dist = v_dist;
        return true;
    }
    return false;
#endif
}
