#version 330
uniform sampler2D u_tile;
uniform sampler2D u_dist;   // the globe pass's view distance per pixel (negated: its data)
in vec2 v_t;
in float v_dist;
flat in vec4 v_sub;
out vec4 f_color;
void main() {
    float g = abs(texelFetch(u_dist, ivec2(gl_FragCoord.xy), 0).r);
    if (isinf(g) || v_dist > g * 1.002 + 30.0) discard;  // no globe here, or hidden
    // inside its tile a patch is drawn at its depth; in its margin only where no tile's own
    // patch is (the farthest depth: a crack between two patches' meshes), with its edge texels
    bool inside = all(greaterThanEqual(v_t, vec2(0.0))) && all(lessThanEqual(v_t, vec2(1.0)));
    gl_FragDepth = inside ? gl_FragCoord.z : 1.0;
    f_color = texture(u_tile, v_sub.xy + v_sub.zw * clamp(v_t, 0.0, 1.0));
}
