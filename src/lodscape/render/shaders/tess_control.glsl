#version 410
layout(vertices = 4) out;
in vec3 c_patch[];
out vec3 e_patch[];
uniform sampler2D u_frame;    // (S+1) x 2(S+1): base positions, then normals (tile frame)
uniform sampler2D u_height;   // (S+1)^2 metres
uniform sampler2D u_errors;   // LEVELS + 2 columns: per patch, then per patch edge
uniform vec3 u_eye;           // camera position in the tile frame
uniform float u_scale;        // pixels per unit of tangent (the d of H = h·d/dist)
uniform float u_px;           // target pixels per segment (the pixel rule)
uniform float u_budget;       // screen-space error this tile may add, pixels
uniform float u_near;
uniform float u_cells;        // S
uniform float u_patches;      // P
uniform float u_max;          // cells a patch side: the finest level

vec3 corner(vec2 uv) {
    ivec2 t = ivec2(round(uv * u_cells));
    int n = int(u_cells) + 1;
    vec3 base = texelFetch(u_frame, t, 0).xyz;
    vec3 up = texelFetch(u_frame, ivec2(t.x, t.y + n), 0).xyz;
    return base + texelFetch(u_height, t, 0).r * up;
}

float error_level(int row, float dist) {
    // the coarsest level whose error, seen from the nearest the piece can be, fits the budget
    for (int i = 0; i < 5; ++i) {
        float e = texelFetch(u_errors, ivec2(i, row), 0).r;
        if (e * u_scale <= u_budget * dist) return float(1 << i);
    }
    return u_max;
}

float quantise(float l) { return min(exp2(ceil(log2(clamp(l, 1.0, u_max)))), u_max); }

float edge_level(vec2 a, vec2 b) {
    // the same arithmetic whichever patch asks: ends in a fixed order
    if (a.x > b.x || (a.x == b.x && a.y > b.y)) { vec2 t = a; a = b; b = t; }
    vec3 pa = corner(a), pb = corner(b);
    float len = length(pb - pa);
    int P = int(u_patches);
    int row;
    if (a.y == b.y) {
        row = P * P + int(round(a.y * u_patches)) * P + int(round(a.x * u_patches));
    } else {
        row = P * P + P * (P + 1) + int(round(a.x * u_patches)) * P + int(round(a.y * u_patches));
    }
    float lo = texelFetch(u_errors, ivec2(5, row), 0).r;
    float hi = texelFetch(u_errors, ivec2(6, row), 0).r;
    float dist = max(min(distance(u_eye, pa), distance(u_eye, pb)) - 0.5 * len - (hi - lo), u_near);
    return quantise(max(len * u_scale / dist / u_px, error_level(row, dist)));
}

void main() {
    e_patch[gl_InvocationID] = c_patch[gl_InvocationID];
    if (gl_InvocationID != 0) return;
    vec3 q0 = c_patch[0], q1 = c_patch[1], q2 = c_patch[2], q3 = c_patch[3];
    if (q3.z > 0.5) {
        // a skirt: q0-q1 on the tile's edge, q3-q2 hanging below it
        float l = edge_level(q0.xy, q1.xy);
        gl_TessLevelOuter[0] = 1.0; gl_TessLevelOuter[1] = l;
        gl_TessLevelOuter[2] = 1.0; gl_TessLevelOuter[3] = l;
        gl_TessLevelInner[0] = l; gl_TessLevelInner[1] = 1.0;
        return;
    }
    gl_TessLevelOuter[0] = edge_level(q0.xy, q3.xy);
    gl_TessLevelOuter[1] = edge_level(q0.xy, q1.xy);
    gl_TessLevelOuter[2] = edge_level(q1.xy, q2.xy);
    gl_TessLevelOuter[3] = edge_level(q3.xy, q2.xy);
    int P = int(u_patches);
    int row = int(round(q0.y * u_patches)) * P + int(round(q0.x * u_patches));
    vec3 p0 = corner(q0.xy), p1 = corner(q1.xy), p2 = corner(q2.xy), p3 = corner(q3.xy);
    vec3 c = 0.25 * (p0 + p1 + p2 + p3);
    float r = max(max(distance(c, p0), distance(c, p1)), max(distance(c, p2), distance(c, p3)));
    float lo = texelFetch(u_errors, ivec2(5, row), 0).r;
    float hi = texelFetch(u_errors, ivec2(6, row), 0).r;
    float dist = max(distance(u_eye, c) - r - (hi - lo), u_near);
    float side = max(distance(p0, p2), distance(p1, p3)) * 0.70710678;
    float inner = quantise(max(side * u_scale / dist / u_px, error_level(row, dist)));
    gl_TessLevelInner[0] = inner;
    gl_TessLevelInner[1] = inner;
}
