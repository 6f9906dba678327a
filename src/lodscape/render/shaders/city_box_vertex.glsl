#version 330
#ifdef BLOCKS
layout(std140) uniform Frame { mat4 f_mvp; mat4 f_rot; vec4 f_offset; vec4 f_sun; };
#define MVP f_mvp
#else
uniform mat4 u_mvp;
#define MVP u_mvp
#endif
uniform vec3 u_lo;
uniform vec3 u_hi;
in vec3 in_pos;
void main() { gl_Position = MVP * vec4(mix(u_lo, u_hi, in_pos), 1.0); }
