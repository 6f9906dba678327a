#version 330
uniform mat4 u_mvp;      // projection · view, for positions relative to the tile centre
uniform mat3 u_rot;      // world → view rotation
uniform vec3 u_offset;   // view-space position of the tile centre
uniform vec3 u_up;       // direction skirts hang from (ellipsoid normal at the centre)
uniform float u_skirt;   // metres to lower skirt vertices in this draw
uniform vec3 u_uv;       // texture window: offset (u, v) and scale (an ancestor's texture)
uniform vec3 u_ground;   // the tile's west and north edges (metres, modulo) and its size
uniform float u_morph;   // how far the tile still shows the surface it replaced (0..1)
in vec3 in_pos;
in vec2 in_uv;
in float in_skirt;
in vec3 in_morph;        // the move onto the next coarser surface
out vec2 v_uv;
out vec2 v_tuv;
out float v_dist;
out vec2 v_ground;
out vec3 v_view;
out float v_skirt;
out float v_above;
void main() {
    vec3 p = in_pos + u_morph * in_morph - in_skirt * u_skirt * u_up;
    v_skirt = in_skirt;
    gl_Position = u_mvp * vec4(p, 1.0);
    v_uv = u_uv.xy + u_uv.z * in_uv;
    v_tuv = in_uv;
    v_ground = vec2(u_ground.x + in_uv.x * u_ground.z, u_ground.y - in_uv.y * u_ground.z);
    v_view = u_offset + u_rot * p;
    // both linear in view space, so perspective-correct interpolation keeps them exact
    v_dist = -v_view.z;
    v_above = dot(v_view, u_rot * u_up);
}
