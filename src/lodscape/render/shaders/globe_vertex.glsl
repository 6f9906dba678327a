#version 330
uniform mat4 u_mvp;     // projection · view for positions relative to the camera
uniform mat3 u_rot;
in vec3 in_pos;
in vec2 in_uv;
in float in_shade;
out vec2 v_uv;
out float v_dist;
out float v_shade;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    v_uv = in_uv;
    v_dist = -(u_rot * in_pos).z;
    v_shade = in_shade;
}
