#version 410
layout(quads, equal_spacing, ccw) in;
in vec3 e_patch[];
uniform sampler2D u_frame;
uniform sampler2D u_height;
uniform float u_morph;     // how far the tile still shows its grid of half the cells (0..1)
uniform mat4 u_mvp;        // projection · view for positions in the tile frame
uniform mat3 u_rot;        // tile frame → view rotation
uniform vec3 u_offset;     // view-space position of the tile frame's origin
uniform vec3 u_up;         // where skirts hang (the tile frame's up at its centre)
uniform float u_skirt;
uniform float u_cells;
uniform vec3 u_uv;         // texture window: offset (u, v) and scale (an ancestor's texture)
uniform vec3 u_ground;     // the tile's west and north edges (metres, modulo) and its size
out vec2 v_uv;
out vec2 v_tuv;            // where in the tile (0..1), for the imagery layers' windows
out float v_dist;
out vec2 v_ground;
out vec3 v_view;
out vec3 v_normal;         // view space, from the height texture
out float v_skirt;
float coarse_height(vec2 uv) {
    // the surface of the grid of half the cells: bilinear between every other texel (what the
    // tile's parent, or its own coarser grid, showed there)
    float half_cells = 0.5 * u_cells;
    vec2 g = clamp(uv, 0.0, 1.0) * half_cells;
    vec2 g0 = min(floor(g), vec2(half_cells - 1.0));
    vec2 f = g - g0;
    ivec2 i = ivec2(g0) * 2;
    float h00 = texelFetch(u_height, i, 0).r, h10 = texelFetch(u_height, i + ivec2(2, 0), 0).r;
    float h01 = texelFetch(u_height, i + ivec2(0, 2), 0).r;
    float h11 = texelFetch(u_height, i + ivec2(2, 2), 0).r;
    return mix(mix(h00, h10, f.x), mix(h01, h11, f.x), f.y);
}
vec3 surface(vec2 uv) {
    float n = u_cells + 1.0;
    vec2 t = (clamp(uv, 0.0, 1.0) * u_cells + 0.5) / vec2(n, 2.0 * n);
    vec3 base = textureLod(u_frame, t, 0.0).xyz;
    vec3 up = textureLod(u_frame, t + vec2(0.0, 0.5), 0.0).xyz;
    float h = textureLod(u_height, (clamp(uv, 0.0, 1.0) * u_cells + 0.5) / n, 0.0).r;
    if (u_morph > 0.0 && u_cells >= 2.0 && mod(u_cells, 2.0) < 0.5) {
        h = mix(h, coarse_height(uv), u_morph);
    }
    return base + h * up;
}
void main() {
    float a = gl_TessCoord.x, b = gl_TessCoord.y;
    vec3 q = mix(mix(e_patch[0], e_patch[1], a), mix(e_patch[3], e_patch[2], a), b);
    vec3 p = surface(q.xy) - q.z * u_skirt * u_up;
    v_skirt = q.z;
    gl_Position = u_mvp * vec4(p, 1.0);
    v_uv = u_uv.xy + u_uv.z * q.xy;
    v_tuv = q.xy;
    v_ground = vec2(u_ground.x + q.x * u_ground.z, u_ground.y - q.y * u_ground.z);
    v_view = u_offset + u_rot * p;
    v_dist = -v_view.z;
    // the normal from the heights a texel either side (east, and north: v grows southwards)
    float d = 1.0 / u_cells;
    vec3 east = surface(q.xy + vec2(d, 0.0)) - surface(q.xy - vec2(d, 0.0));
    vec3 north = surface(q.xy - vec2(0.0, d)) - surface(q.xy + vec2(0.0, d));
    v_normal = u_rot * normalize(cross(east, north));
}
