uniform mat3 u_rot;      // the tile's frame -> view
uniform vec3 u_up;       // the terrain's outside (up at the tile's centre), in its frame
in float v_skirt;
const vec3 UNDERSIDE = vec3(0.16, 0.16, 0.18);
#ifdef HEIGHT_NORMALS
bool underside(vec3 view) {
    vec3 up = u_rot * u_up;
    vec3 n = cross(dFdx(view), dFdy(view));
    if (dot(n, up) < 0.0) n = -n;
    return v_skirt > 0.0 ? dot(view, up) > 0.0 : dot(n, view) > 1e-3 * length(n) * length(view);
}
#else
in float v_above;        // how far the fragment is above the eye, along the tile's up
bool underside(vec3 view) {
    // a surface fragment is the underside where the rasteriser says it faces away and it lies
    // above the eye: below the eye only a plumb face could show its back, and what does is a
    // sliver triangle seen edge-on, whose facing rounding may flip (isolated dark pixels on
    // the ground and along the horizon)
    return v_skirt > 0.0 ? v_above > 0.0 : !gl_FrontFacing && v_above > 0.0;
}
#endif
