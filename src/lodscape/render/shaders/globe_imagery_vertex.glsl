#version 330
uniform mat4 u_mvp;
uniform mat3 u_rot;
in vec3 in_pos;
in vec2 in_t;     // where the point is in its tile: 0..1 west to east, north to south
in vec4 in_sub;   // where the tile lies in the image drawn: u0, v0, du, dv
out vec2 v_t;
out float v_dist;
flat out vec4 v_sub;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    v_t = in_t;
    v_dist = -(u_rot * in_pos).z;
    v_sub = in_sub;
}
